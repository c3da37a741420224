"""Concrete systems on Lie groups, one folder each (simulator, measurement model, config).

Installed as ``manifold_nets_examples`` (the repository's ``examples/`` folder):
``manifold_nets_examples.rigid_body`` is the paper's rigid body. A new system is a new folder
here (or anywhere importable: ``docs/your_own_project.md``) with a
:class:`manifold_nets.system.System` subclass and a ``configs/system/<name>.yaml``; nothing in
``manifold_nets`` changes. See ``docs/systems.md``.
"""
