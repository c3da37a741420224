"""``python -m manifold_nets.cli.evaluate``: a trained observer or a baseline on the inference sets.

The evaluation task of every run: per sigma of ``eval.sigmas`` the inference set (generated or
read from the cache), the estimates of the method, the paper's metrics, one table row and one
figure. Written into ``<run folder>/results/``: ``table.csv``, ``table.md``, ``metrics.json``,
``curves.json`` and ``errors_sigma<s>.png`` per sigma::

    python -m manifold_nets.cli.evaluate experiment=default eval.checkpoint=outputs/default/<id>
    python -m manifold_nets.cli.evaluate experiment=paper_cpu method=ekf
    python -m manifold_nets.cli.evaluate -m experiment=default eval.checkpoint=<run> \
        'eval.sigmas=[0.1],[0.2],[0.3]'

The train command calls :func:`evaluate` after training; this command evaluates without
training (``method=learned`` then needs ``eval.checkpoint``).
"""
from __future__ import annotations

from omegaconf import DictConfig

from . import CONFIG_PATH
from .common import absolute, check_sigmas, json_safe, say_where_on_failure, to_json
from .common import check_plugins, sweeper_reads_the_objective
from .tasks import evaluate, run

__all__ = ["absolute", "check_sigmas", "evaluate", "json_safe", "main", "run", "to_json"]


def _hydra_main(cfg: DictConfig) -> float | None:
    """Evaluates and returns the run's objective (``objective=``, e.g. ``'R est'``) to a sweeper."""
    from hydra.core.hydra_config import HydraConfig

    if cfg.method.name == "learned" and not cfg.method.target and not cfg.eval.checkpoint:
        raise ValueError(
            "the evaluate command does not train: give eval.checkpoint=<run folder or .pt> for "
            "method=learned, or pick a baseline (method=ekf, raw, ...); to train, use "
            "manifold_nets.cli.train."
        )
    required = sweeper_reads_the_objective(cfg)
    out_dir = HydraConfig.get().runtime.output_dir
    with say_where_on_failure(out_dir):
        return run(cfg, out_dir, objective_required=required)["objective"]


def main() -> None:
    """The command-line entry (configs from the package ``manifold_nets_configs``, primary config ``train.yaml``)."""
    import sys

    import hydra

    check_plugins(sys.argv[1:])
    hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="train")(_hydra_main)()


if __name__ == "__main__":
    main()
