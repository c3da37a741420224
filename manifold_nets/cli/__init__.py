"""The commands: thin hydra and argparse entry points over the library.

======================================  ==================================================
``python -m manifold_nets.cli.train``    train the observer (or pick a baseline), evaluate it
``python -m manifold_nets.cli.evaluate`` evaluate a trained run folder or a baseline
``python -m manifold_nets.cli.generate`` simulate (or find in the cache) one dataset
``python -m manifold_nets.cli.sweep``    one table for a hydra multirun
``python -m manifold_nets.cli.compare``  methods side by side, one table per sigma
``python -m manifold_nets.cli.apply``    a trained observer over a dataset file, estimates out
======================================  ==================================================

Each command builds objects from its config with :mod:`manifold_nets.builders`, logs a line,
and calls the library; no library module imports a command. Every command sets torch's threads
one way, :func:`manifold_nets.threads.use_threads` (one thread unless asked).
"""

#: Where the hydra commands find their primary configs: the repository's ``configs/``, installed as
#: the package ``manifold_nets_configs``, so the commands run from any folder. A user's own configs
#: join with ``--config-dir`` (docs/your_own_project.md).
CONFIG_PATH = "pkg://manifold_nets_configs"
