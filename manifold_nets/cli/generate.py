"""``python -m manifold_nets.cli.generate``: simulate one dataset (or find it in the cache).

::

    python -m manifold_nets.cli.generate system=rigid_body dataset=paper_train
    python -m manifold_nets.cli.generate -m dataset=paper_inference dataset.sigma=0.1,0.2,0.3

Configs: ``configs/generate.yaml``, ``configs/system/``, ``configs/dataset/``. The file lands in
``dataset.cache_dir`` under a name made of the system, the sizes and a hash of everything that
determines its contents (:mod:`manifold_nets.datasets`), which the train command then reuses.
"""

from __future__ import annotations

import logging

from omegaconf import DictConfig, OmegaConf

from manifold_nets.builders import build_system
from manifold_nets.config import DatasetConfig
from manifold_nets.datasets import load_or_generate

from . import CONFIG_PATH
from .evaluate import absolute

__all__ = ["generate", "main"]

log = logging.getLogger(__name__)


def generate(cfg: DictConfig) -> dict:
    """The splits of ``cfg.dataset`` for ``cfg.system``, generated or read from the cache."""
    from manifold_nets.threads import use_threads

    use_threads()  # one thread, or OMP_NUM_THREADS (simulation is per-step work too)
    dataset: DatasetConfig = OmegaConf.to_object(cfg.dataset)
    system = build_system(cfg.system)
    parts = load_or_generate(system, dataset, cache_dir=absolute(dataset.cache_dir))
    for name, ds in parts.items():
        print(
            f"{name:>10}: {len(ds):6d} x {ds.length:5d} sigma={ds.meta['sigma']:g} "
            f"seed={ds.meta['seed']} <- {ds.meta['path']}"
        )
    log.debug("config:\n%s", OmegaConf.to_yaml(cfg))
    return parts


def main() -> None:
    """The command-line entry (configs from the package ``manifold_nets_configs``, primary config ``generate.yaml``)."""
    import hydra

    hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="generate")(generate)()


if __name__ == "__main__":
    main()
