"""Concrete systems on Lie groups, one folder each (simulator, measurement model, config).

``examples.rigid_body`` is the paper's rigid body. A new system is a new folder here (or
anywhere importable) with a :class:`manifold_nets.system.System` subclass and a
``configs/system/<name>.yaml``; nothing in ``manifold_nets`` changes. See ``docs/systems.md``.
"""
