"""Concrete systems on Lie groups, one folder each (simulator, measurement model, config).

Installed as ``manifold_nets_examples`` (the repository's ``examples/`` folder):
``manifold_nets_examples.rigid_body`` is the paper's rigid body. A new system is a new folder
here (or anywhere importable: ``docs/your_own_project.md``) with a
:class:`manifold_nets.system.System` subclass and a ``configs/system/<name>.yaml``; nothing in
``manifold_nets`` changes. See ``docs/systems.md``.
"""

if __name__ == "examples":  # the folder imported by its path, not by its installed name
    raise ImportError(
        "this folder is the package manifold_nets_examples: run its commands as `python -m "
        "manifold_nets_examples.broad.train ...` (after `pip install -e .`), not `python -m "
        "examples...`. Imported as `examples`, its classes get a second name (examples.broad."
        "simulator.BroadSimulator) that a run folder would record and no loader accepts."
    )
