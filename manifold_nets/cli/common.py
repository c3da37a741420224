"""What the commands share: paths from the launch folder, JSON, the checks of a config that need
no work, and what a sweeper reads."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from manifold_nets.config import RunConfig
from manifold_nets.objective import parse_objective

__all__ = [
    "absolute", "check_config", "check_sigmas", "json_safe", "say_where_on_failure",
    "sweeper_reads_the_objective", "to_json",
]

log = logging.getLogger(__name__)


def absolute(path: str) -> str:
    """``path`` from the folder the command was launched in (hydra may have moved the cwd); a zoo
    entry (``zoo:...``) as it is."""
    if str(path).startswith("zoo:"):
        return str(path)
    try:
        from hydra.utils import to_absolute_path

        return to_absolute_path(path)
    except ValueError:  # hydra not initialised (tests, plain Python)
        return str(Path(path).absolute())


def json_safe(value: Any) -> Any:
    """``value`` with every float that is not finite (an undefined metric: the measurement
    error at k = 0, a reduction against a measurement error of 0) replaced by ``None``."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def to_json(value: Any, **kwargs) -> str:
    """Valid JSON always (``allow_nan=False``): undefined values are written as ``null``."""
    return json.dumps(json_safe(value), allow_nan=False, default=str, **kwargs)


def check_sigmas(sigmas: Sequence[float]) -> list[float]:
    """The noise levels as floats; ``ValueError`` unless each is finite, ``>= 0`` and at most
    :data:`~manifold_nets.training_settings.MAX_SIGMA`."""
    from manifold_nets.training_settings import MAX_SIGMA

    out = [float(s) for s in sigmas]
    for s in out:
        if not (math.isfinite(s) and 0 <= s <= MAX_SIGMA):
            raise ValueError(f"eval.sigmas must be finite numbers in [0, {MAX_SIGMA:g}], got {s!r}.")
    if not out:
        raise ValueError("eval.sigmas is empty; name at least one noise level, e.g. [0.1].")
    return out


def check_config(cfg: DictConfig) -> None:
    """Raises ``ValueError`` unless ``cfg`` fits :class:`~manifold_nets.config.RunConfig`.

    Composing already checks overrides; this also catches keys appended with ``+``.
    """
    try:
        OmegaConf.merge(OmegaConf.structured(RunConfig), OmegaConf.to_container(cfg))
    except Exception as err:  # omegaconf's ConfigKeyError / ValidationError
        msg = str(err).splitlines()[0]
        raise ValueError(
            f"the config does not fit the schema: {msg} (not in the schema "
            "manifold_nets/config.py; check the spelling)."
        ) from None


def sweeper_reads_the_objective(cfg: DictConfig) -> bool:
    """Whether this hydra job runs under a sweeper that reads its return value (Optuna, ...):
    a multirun whose sweeper is not hydra's basic one, which ignores the value. Warns when the
    sweeper's ``direction`` goes against the objective (minimising a ``reduction %``)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    hc = HydraConfig.get()
    target = str(OmegaConf.select(hc, "sweeper._target_", default="") or "")
    direction = OmegaConf.select(hc, "sweeper.direction", default=None)
    direction = getattr(direction, "name", direction)  # the Optuna sweeper's enum, or a str
    if isinstance(direction, str) and direction in ("minimize", "maximize"):
        minimize = parse_objective(cfg.objective).minimize
        if (direction == "minimize") != minimize:
            log.warning(
                "the sweeper will %s objective=%r, which is better %s: set "
                "hydra.sweeper.direction=%s", direction,
                cfg.objective, "smaller" if minimize else "larger",
                "minimize" if minimize else "maximize",
            )
    return hc.mode == RunMode.MULTIRUN and not target.endswith(".BasicSweeper")


@contextmanager
def say_where_on_failure(out_dir: str | Path):
    """Logs the run folder when the run fails: hydra made it (its ``.hydra/`` and log) before
    the run could check anything, so a refused run leaves it behind; this says where."""
    try:
        yield
    except Exception:
        log.error("the run failed; its folder (hydra's files, and what the run wrote): %s", out_dir)
        raise
