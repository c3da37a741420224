"""What the commands share: paths from the launch folder, JSON, the checks of a config that need
no work (hydra's plugins among them), what a sweeper reads, and the run folder of a failed run."""

from __future__ import annotations

import importlib.util
import json
import logging
import math
import shutil
import sys
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from manifold_nets.config import RunConfig
from manifold_nets.objective import parse_objective

__all__ = [
    "HYDRA_PLUGINS", "absolute", "check_config", "check_plugins", "check_sigmas", "json_safe",
    "say_where_on_failure", "sweeper_reads_the_objective", "to_json",
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


#: ``hydra/<group>=<option>`` -> the module of hydra's plugin that provides it. All three are the
#: ``sweeps`` extra (docs/sweeps.md).
HYDRA_PLUGINS = {
    "hydra/launcher=joblib": "hydra_plugins.hydra_joblib_launcher",
    "hydra/launcher=submitit_local": "hydra_plugins.hydra_submitit_launcher",
    "hydra/launcher=submitit_slurm": "hydra_plugins.hydra_submitit_launcher",
    "hydra/sweeper=optuna": "hydra_plugins.hydra_optuna_sweeper",
}


def check_plugins(argv: Sequence[str]) -> None:
    """Exits (status 1) naming the extra when a command-line argument picks a launcher or
    sweeper whose hydra plugin is not installed; hydra's own error ("Could not find
    'hydra/launcher/joblib'") does not say what to install."""
    for arg in argv:
        module = HYDRA_PLUGINS.get(arg.lstrip("+~").replace("override ", "").strip())
        if module is not None and importlib.util.find_spec(module) is None:
            name = module.removeprefix("hydra_plugins.").replace("_", "-")
            sys.exit(
                f"error: {arg} needs hydra's plugin {name}, which is not installed; it comes "
                "with the `sweeps` extra: pip install 'manifold_nets[sweeps]' (docs/sweeps.md)."
            )


def _only_hydras_files(out_dir: Path) -> bool:
    """Whether ``out_dir`` holds nothing but what hydra writes before a job starts: its
    ``.hydra/`` folder (``hydra.output_subdir``) and the job's log."""
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    hydras = {str(hc.output_subdir), f"{hc.job.name}.log"}
    return out_dir.is_dir() and all(p.name in hydras for p in out_dir.iterdir())


def _remove_run_folder(out_dir: Path) -> None:
    """Removes ``out_dir`` (the log handlers writing into it closed first), and the folders
    above it that this leaves empty, up to the launch folder (``outputs/<name>/``, ``outputs/``)."""
    from hydra.core.hydra_config import HydraConfig

    for logger in (logging.getLogger(), *logging.Logger.manager.loggerDict.values()):
        for handler in list(getattr(logger, "handlers", ())):
            name = getattr(handler, "baseFilename", None)
            if name is not None and out_dir in Path(name).parents:
                logger.removeHandler(handler)
                handler.close()
    shutil.rmtree(out_dir, ignore_errors=True)
    launch = Path(HydraConfig.get().runtime.cwd).resolve()
    for parent in out_dir.resolve().parents:
        if parent == launch or launch not in parent.parents:
            break
        try:
            parent.rmdir()  # only when empty: another run's folder keeps it
        except OSError:
            break


@contextmanager
def say_where_on_failure(out_dir: str | Path):
    """What a failed run leaves: hydra made its folder (``.hydra/`` and the log) before the run
    could check anything. A run that fails before it wrote a file of its own (a refused config,
    path or checkpoint: before any work) has its folder removed; otherwise the folder is kept
    and its path logged."""
    try:
        yield
    except Exception:
        out_dir = Path(out_dir)
        if _only_hydras_files(out_dir):
            _remove_run_folder(out_dir)
            log.info("the run failed before any work; its folder %s is removed", out_dir)
        else:
            log.error("the run failed; its folder (what it wrote, and hydra's files): %s", out_dir)
        raise
