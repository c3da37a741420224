"""``python -m manifold_nets.cli.train``: data -> training -> the paper's table and figure, by hydra.

One command generates (or reuses from the cache) the datasets of the configured system, trains
the residual observer, keeps the best-validation model, evaluates it on a noisy inference set
per sigma and writes everything into its own run folder::

    python -m manifold_nets.cli.train experiment=default            # small: minutes on a CPU
    python -m manifold_nets.cli.train experiment=default debug=tiny # seconds: a smoke test
    python -m manifold_nets.cli.train experiment=paper_rigid_body   # the paper's sizes
    python -m manifold_nets.cli.train -m experiment=default seed=0,1,2
    python -m manifold_nets.cli.train experiment=default method=ekf # a baseline, same evaluation

``method=`` (``configs/method/``) picks what produces the estimates: ``learned`` (default: train
the observer, or evaluate ``eval.checkpoint``), ``untrained`` (the observer at its seeded
initialisation), or a classical estimator of the system (``System.estimators()``). Every method
goes through the same evaluation (:mod:`manifold_nets.cli.evaluate`).

A run folder (``outputs/<name>/<date_time_pid>/``, or ``multirun/<name>/<date_time_pid>/<job>/``)
holds ``config.yaml`` (resolved), ``log.csv``/``log.json`` (per epoch), ``checkpoints/best.pt``
and ``last.pt``, ``results/`` (see the evaluation command), and with ``train.tensorboard=true``
``tensorboard/`` (losses, learning rate, metrics: :mod:`manifold_nets.tensorboard_log`).
Interrupted? Resume with ``train.resume=<run folder>``.

The hydra entry returns the run's objective (``objective=``: ``best_val_loss`` by default,
``test_loss``, or a table column such as ``'R est'`` or ``'R est@0.1'``; see
:mod:`manifold_nets.objective`) as a float, which hydra's Optuna sweeper optimises::

    python -m manifold_nets.cli.train -m hydra/sweeper=optuna hydra.sweeper.n_trials=20 \
        experiment=default 'train.lr=interval(1e-4,1e-2)'

A run with no loss to return (a baseline under the default objective) returns ``None``, unless
a sweeper that reads the value runs it: then it fails before any work. docs/sweeps.md has the
launchers (joblib, submitit) and the search.

:func:`run` does the work of one composed config (what tests call); :func:`train` is the
training task alone.
"""
from __future__ import annotations

from omegaconf import DictConfig

from . import CONFIG_PATH
from .common import check_plugins, say_where_on_failure, sweeper_reads_the_objective
from .tasks import run, train

__all__ = ["main", "run", "train"]


def _hydra_main(cfg: DictConfig) -> float | None:
    from hydra.core.hydra_config import HydraConfig

    required = sweeper_reads_the_objective(cfg)
    out_dir = HydraConfig.get().runtime.output_dir
    with say_where_on_failure(out_dir):
        metrics = run(cfg, out_dir, objective_required=required)
    return metrics["objective"]


def main() -> None:
    """The command-line entry (configs from the package ``manifold_nets_configs``, primary config ``train.yaml``)."""
    import sys

    import hydra

    check_plugins(sys.argv[1:])
    hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="train")(_hydra_main)()


if __name__ == "__main__":
    main()
