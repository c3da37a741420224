"""From config to objects: the system, the observer, a baseline estimator, the device.

Each ``build_*`` takes one part of a run's config (the dataclasses of
:mod:`manifold_nets.config`, or the same keys in an omegaconf ``DictConfig``) and returns the
library object, checking the part against what it must fit and naming the config key in its
errors. The commands call these; so can a user's own script.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from groups import LieGroup

from .config import DTYPES, MethodConfig, ModelConfig
from .cores import CORES, GRUCore, RecurrentCore
from .inputs import ObserverInputs
from .observer import ResidualObserver, core_output_size
from .relax import relax
from .robust import RobustWeights, check_span
from .system import System

__all__ = [
    "LEARNED_METHODS",
    "build_system",
    "build_observer",
    "build_estimator_factory",
    "resolve_device",
    "torch_dtype",
]

#: The methods that are the residual observer (``method.name``); any other is an estimator.
LEARNED_METHODS = ("learned", "untrained")


def torch_dtype(name: str, key: str) -> torch.dtype:
    """``torch.float32`` or ``torch.float64`` from its name; ``key`` names the setting in errors."""
    if name not in DTYPES:
        raise ValueError(f"{key} must be one of {DTYPES}, got {name!r}.")
    return getattr(torch, name)


def build_system(system_cfg: Any) -> System:
    """The system of a ``system`` config (``_target_`` and its parameters), checked to be a
    :class:`~manifold_nets.system.System`. A ``ValueError`` or ``TypeError`` of the system's
    constructor (parameters it refuses) comes through as it was raised."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    try:
        system = instantiate(system_cfg)
    except InstantiationException as err:
        if isinstance(err.__cause__, (ValueError, TypeError)):
            # the system refused its parameters: its own message, not hydra's wrapping of it
            raise err.__cause__ from None
        if not isinstance(err.__cause__, ImportError):
            raise
        target = system_cfg.get("_target_") if hasattr(system_cfg, "get") else None
        cause = " ".join(str(err.__cause__).split())
        raise ValueError(
            f"system._target_={target!r} could not be imported ({cause}). The module of "
            "your system must be importable: run the command from the folder that holds it "
            "with `python -m manifold_nets.cli.<command>` (Python puts that folder on sys.path), "
            "or set PYTHONPATH (`PYTHONPATH=. mn-train ...`); see docs/your_own_project.md."
        ) from None
    if not isinstance(system, System):
        raise TypeError(
            f"the configured system {type(system).__name__} is not a manifold_nets.System; "
            "configs/system/<name>.yaml must name a System subclass in its _target_."
        )
    return system


def _core_class(name: str, import_core: bool = True) -> type[RecurrentCore]:
    """``gru``, a registered :class:`~manifold_nets.cores.RecurrentCore` subclass (its module
    imported), or, only when ``import_core``, the dotted path of one to import."""
    if name == "gru":
        return GRUCore
    if name in CORES or not import_core:
        return CORES.lookup(name, where="model.core")
    from hydra.utils import get_class

    try:
        cls = get_class(name)
    except Exception as err:
        raise ValueError(
            f"model.core must be 'gru' or the dotted path of a RecurrentCore subclass; "
            f"{name!r} could not be imported ({err})."
        ) from None
    if not (isinstance(cls, type) and issubclass(cls, RecurrentCore)):
        raise ValueError(f"model.core={name!r} is not a RecurrentCore subclass.")
    return cls


def build_observer(
    group: LieGroup,
    measurement_dim: int,
    input_dim: int,
    model: ModelConfig | Any,
    *,
    import_core: bool = True,
    dt: float | None = None,
    system: System | None = None,
) -> ResidualObserver:
    """The observer of a ``model`` config (:class:`~manifold_nets.config.ModelConfig`) for a
    system's ``group`` and sizes; ``model.relax`` takes factors off the group
    (:func:`~manifold_nets.relax.relax`).

    ``model.core`` is ``gru`` or a :class:`~manifold_nets.cores.RecurrentCore` subclass by dotted
    path; with ``import_core=False`` (a config read from a file,
    :func:`manifold_nets.load_observer`) only one already imported
    (:data:`manifold_nets.cores.CORES`), never a module to import. ``dt`` (the system's step)
    scales the kinematic prior ``model.propagate``; ``system`` gives the model prior
    ``model.prior=system`` (its :meth:`~manifold_nets.system.System.predict`)."""
    prior = _model_prior(model, system)
    group = relax(group, list(model.relax))
    inputs = ObserverInputs(
        dict(model.innovation),
        tuple(model.relative_only),
        rotated={
            name: [tuple(span) for span in spans]
            for name, spans in dict(getattr(model, "rotated", None) or {}).items()
        },
        propagate=dict(getattr(model, "propagate", None) or {}),
        dt=dt,
        clock=tuple(getattr(model, "clock", None) or ()),
        innovation_frame=dict(getattr(model, "innovation_frame", None) or {}),
        prior_drive=system.drive_dim if _prior_drive(model, prior) else 0,
    )
    in_size = inputs.core_input_size(group, measurement_dim, input_dim)
    gain, offset, centering, ramp = _update_form(model, inputs)
    core_cls = _core_class(model.core, import_core)
    core = core_cls(
        in_size,
        core_output_size(group, inputs, gain, offset),
        hidden_size=model.hidden_size,
        num_layers=model.num_layers,
    )
    rules = dict(model.updates)
    unknown = sorted(set(rules) - set(group.factor_names))
    if unknown:
        raise ValueError(
            f"model.updates names factors {unknown} that the group {group!r} does not have; "
            f"its factors: {list(group.factor_names)}."
        )
    update = {name: rules.get(name, model.default_update) for name in group.factor_names}
    robust_drive, robust_innovation = _robust_weights(model, prior, system, inputs)
    observer = ResidualObserver(
        group,
        measurement_dim,
        input_dim,
        core,
        update=update,
        inputs=inputs,
        state_dtype=torch_dtype(model.state_dtype, "model.state_dtype"),
        output_scale=float(getattr(model, "output_scale", 1.0)),
        prior=prior,
        prior_drive=(
            system.compensated_drive if inputs.prior_drive or robust_drive is not None else None
        ),
        gain=gain,
        offset=offset,
        centering=centering,
        centering_ramp=ramp,
        centering_factors=dict(getattr(model, "centering_factors", None) or {}),
        step_decay=dict(getattr(model, "step_decay", None) or {}),
        prior_step=system.step if robust_drive is not None else None,
        robust_drive=robust_drive,
        robust_innovation=robust_innovation,
    )
    return observer.to(torch_dtype(model.net_dtype, "model.net_dtype"))


def _update_form(model: ModelConfig | Any, inputs: ObserverInputs) -> tuple[bool, bool, float, int]:
    """``model.gain``, ``model.gain_offset``, ``model.centering`` and ``model.centering_ramp``,
    checked against each other and the inputs."""
    gain = getattr(model, "gain", False)
    if not isinstance(gain, bool):
        raise ValueError(f"model.gain must be true or false, got {gain!r}.")
    if gain and not inputs.innovation:
        raise ValueError(
            "model.gain=true multiplies a learned gain with the innovation, but model.innovation "
            "is empty; name the measured factors there (e.g. {R: [0, 9], p: [9, 12]}) or set "
            "model.gain=false."
        )
    offset = getattr(model, "gain_offset", True)
    if not offset and not gain:
        raise ValueError(
            "model.gain_offset=false (v = K nu) is a form of the gain head; set model.gain=true."
        )
    centering = getattr(model, "centering", 0.0)
    if isinstance(centering, bool) or not isinstance(centering, (int, float)) or not (
        0 <= centering <= 1
    ):
        raise ValueError(f"model.centering must be a number in [0, 1], got {centering!r}.")
    if centering and not inputs.innovation:
        raise ValueError(
            "model.centering subtracts the core's output at zero innovation, but "
            "model.innovation is empty; name the measured factors there (e.g. {R: [0, 9], "
            "p: [9, 12]}) or set model.centering=0."
        )
    if centering and (getattr(model, "prior", "none") or "none") == "none" and not inputs.propagate:
        raise ValueError(
            "model.centering subtracts the core's output at the measurement its prediction "
            "expects, but the observer has no prediction (model.prior=none, no model.propagate): "
            "then that output is the motion itself, and centring takes it away. Set "
            "model.prior=system (model=small_relative_prior) or model.centering=0."
        )
    ramp = getattr(model, "centering_ramp", 0)
    if isinstance(ramp, bool) or not isinstance(ramp, int) or ramp < 0:
        raise ValueError(f"model.centering_ramp must be an integer >= 0 (steps), got {ramp!r}.")
    if ramp and not centering:
        raise ValueError(
            f"model.centering_ramp={ramp} ramps in the centred update, but model.centering is 0; "
            "set model.centering (0 < c <= 1) or model.centering_ramp=0."
        )
    return gain, offset, float(centering), ramp


#: The values of ``model.prior``.
PRIORS = ("none", "system")


def _model_prior(model: ModelConfig | Any, system: System | None):
    """The prior callable of ``model.prior`` (``None`` for ``none``), checked before any work."""
    name = getattr(model, "prior", "none") or "none"
    if name not in PRIORS:
        raise ValueError(
            f"model.prior={name!r} is not one of {PRIORS} (system: the system's nominal "
            "prediction System.predict moves the estimate before the learned update)."
        )
    if name == "none":
        return None
    if system is None:
        raise ValueError(
            "model.prior=system needs the system: pass build_observer(..., system=system)."
        )
    if list(model.relax):
        raise ValueError(
            f"model.prior=system predicts on the system's own group; it cannot be combined with "
            f"model.relax={list(model.relax)} (factors taken off the group)."
        )
    return system.predict


def _prior_drive(model: ModelConfig | Any, prior) -> bool:
    """``model.prior_drive``, checked: a boolean, and only with a model prior."""
    on = getattr(model, "prior_drive", False)
    if not isinstance(on, bool):
        raise ValueError(f"model.prior_drive must be true or false, got {on!r}.")
    if on and prior is None:
        raise ValueError(
            "model.prior_drive=true has the core read the drive the model prior integrates, "
            "but there is no model prior; set model.prior=system (model=small_relative_prior) "
            "or model.prior_drive=false."
        )
    return on


def _robust_weights(
    model: ModelConfig | Any, prior, system: System | None, inputs: ObserverInputs
) -> tuple[RobustWeights | None, RobustWeights | None]:
    """The learned robust weights of ``model.robust_drive`` and ``model.robust_innovation``
    (their widths; 0: none) with ``model.robust_span``, checked before any work."""
    widths = {}
    for key in ("robust_drive", "robust_innovation"):
        width = getattr(model, key, 0)
        if isinstance(width, bool) or not isinstance(width, int) or width < 0:
            raise ValueError(
                f"model.{key} must be an integer >= 0 (the steps of each learned weight "
                f"function; 0: none), got {width!r}."
            )
        widths[key] = width
    span = check_span(getattr(model, "robust_span", 4.0), "model.robust_span")
    drive = innovation = None
    if widths["robust_drive"]:
        if prior is None:
            raise ValueError(
                "model.robust_drive weighs the drive the model prior steps with, but there is no "
                "model prior; set model.prior=system (model=small_relative_prior) or "
                "model.robust_drive=0."
            )
        if type(system).predict is not System.predict:
            raise ValueError(
                f"model.robust_drive steps the weighted drive with {type(system).__name__}.step, "
                f"but {type(system).__name__} overrides predict, so its prior may not be "
                "step(x, compensated_drive(x, y, u)). Write the prediction's drive in "
                "compensated_drive and leave predict to the base class, or set "
                "model.robust_drive=0."
            )
        drive = RobustWeights(system.drive_dim, widths["robust_drive"], span)
    if widths["robust_innovation"]:
        if not inputs.innovation:
            raise ValueError(
                "model.robust_innovation weighs the innovation, but model.innovation is empty; "
                "name the measured factors there (e.g. {R: [0, 9], p: [9, 12]}) or set "
                "model.robust_innovation=0."
            )
        innovation = RobustWeights(len(inputs.innovation), widths["robust_innovation"], span)
    return drive, innovation


def build_estimator_factory(system: System, method: MethodConfig | Any) -> Callable[..., Any]:
    """The estimator factory of a non-learned ``method`` config: ``method.target`` (a dotted
    path) or ``system.estimators()[method.name]``. Raises before any work for an unknown one."""
    if method.target:
        from hydra.utils import get_object

        try:
            return get_object(method.target)
        except Exception as err:
            raise ValueError(
                f"method.target={method.target!r} could not be imported ({err}); give the dotted "
                "path of a factory (system, sigma=..., **params) -> Estimator."
            ) from None
    table = system.estimators()
    if method.name not in table:
        raise ValueError(
            f"method={method.name!r}: {type(system).__name__} has no estimator of that name; the "
            f"methods are {list(LEARNED_METHODS)} (the observer) and {sorted(table)} "
            "(System.estimators()); or set method.target to the dotted path of a factory."
        )
    return table[method.name]


def resolve_device(name: str) -> torch.device:
    """``cpu``, ``cuda[:i]`` or ``auto`` (or another torch device type this machine has, e.g.
    ``mps``); a ``ValueError`` naming ``train.device`` for a name that is not a device, or a
    ``RuntimeError`` for one this machine does not have."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(
            f"train.device={name!r} is not a device; use cpu, cuda, cuda:<index> or auto (cuda "
            "when available)."
        ) from None
    if dev.type == "cpu":
        return dev
    backend = getattr(torch, dev.type, None)
    available = getattr(backend, "is_available", None)
    if not (callable(available) and available()):
        raise RuntimeError(
            f"train.device={name!r} but {dev.type.upper()} is not available here; use "
            "train.device=cpu (or auto)."
        )
    count = getattr(backend, "device_count", None)
    if dev.index is not None and callable(count) and dev.index >= count():
        raise RuntimeError(
            f"train.device={name!r} but this machine has {count()} {dev.type} device(s), "
            f"numbered from 0; use train.device={dev.type}:0 (or auto)."
        )
    return dev
