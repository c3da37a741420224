"""From config to objects: the system, the observer, a baseline estimator, the device.

Each ``build_*`` takes one part of a run's config (the dataclasses of
:mod:`manifold_nets.config`, or the same keys in an omegaconf ``DictConfig``) and returns the
library object, checking the part against what it must fit and naming the config key in its
errors. The commands call these; so can a user's own script.
"""

from __future__ import annotations

import functools
import inspect
import warnings
from collections.abc import Callable
from typing import Any

import torch

from groups import LieGroup

from omegaconf import DictConfig, ListConfig, OmegaConf

from .config import DTYPES, MethodConfig, ModelConfig
from .cores import CORES, GRUCore, RecurrentCore
from .observer import GroupUpdate, ResidualObserver
from .observer.legacy import BLOCK_OF, blocks_from_flat, flat_keys_set
from .observer.piece import piece_class
from .relax import relax
from .system import System

__all__ = [
    "LEARNED_METHODS",
    "build_system",
    "build_observer",
    "build_piece",
    "model_blocks",
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

    Each block names a registered piece (:data:`manifold_nets.observer.PIECES`), never a module
    to import; a block's keys are the piece's arguments, checked by the piece, and its errors name
    the block. ``system`` is what a system prior predicts with, ``dt`` the kinematic prior's step
    (default ``system.dt``). ``model.core`` is ``gru`` or a
    :class:`~manifold_nets.cores.RecurrentCore` subclass by dotted path; with
    ``import_core=False`` (a config read from a file) only one already imported."""
    blocks = model_blocks(model)
    group = relax(group, list(model.relax))
    context = {"system": system, "dt": dt if dt is not None else getattr(system, "dt", None),
               "dim": measurement_dim, "input_dim": input_dim}
    measurement = build_piece("measurement", blocks["measurement"], "model.measurement", context)
    prior = build_piece("prior", blocks["prior"], "model.prior", context)
    features = [
        build_piece("feature", b, f"model.features[{i}]", context)
        for i, b in enumerate(blocks["features"])
    ]
    head = build_piece("head", blocks["head"], "model.head", context)
    scales = [
        build_piece("scale", b, f"model.scales[{i}]", context) for i, b in enumerate(blocks["scales"])
    ]
    rules = dict(model.updates)
    unknown = sorted(set(rules) - set(group.factor_names))
    if unknown:
        raise ValueError(
            f"model.updates names factors {unknown} that the group {group!r} does not have; "
            f"its factors: {list(group.factor_names)}."
        )
    update = GroupUpdate(
        {name: rules.get(name, model.default_update) for name in group.factor_names},
        torch_dtype(model.state_dtype, "model.state_dtype"),
    )
    bound = measurement.bind(group)
    # bound here first only so that an error names its block; the observer binds them again
    for where, piece in [("model.prior", prior), ("model.head", head)] + [
        (f"model.features[{i}]", f) for i, f in enumerate(features)
    ] + [(f"model.scales[{i}]", s) for i, s in enumerate(scales)]:
        try:
            piece.bind(group, bound)
        except ValueError as err:
            raise ValueError(f"{where} ({piece.name}): {err}") from None
    core = functools.partial(  # the observer sizes it and starts it where the head says
        _core_class(model.core, import_core), hidden_size=model.hidden_size,
        num_layers=model.num_layers,
    )
    observer = ResidualObserver(
        group, measurement, core, update=update, prior=prior, features=features, head=head,
        scales=scales,
    )
    return observer.to(torch_dtype(model.net_dtype, "model.net_dtype"))


def _block(value: Any, where: str) -> dict:
    """A block as a plain dict: a name alone is ``{type: name}``."""
    if isinstance(value, str):
        return {"type": value}
    if hasattr(value, "items"):
        return {str(k): _plain(v) for k, v in value.items()}
    raise ValueError(f"{where} must be a block ({{type: <name>, ...}}) or a name, got {value!r}.")


def _plain(value: Any) -> Any:
    if isinstance(value, (DictConfig, ListConfig)):
        return OmegaConf.to_container(value, resolve=True)
    return value


def model_blocks(model: ModelConfig | Any) -> dict[str, Any]:
    """The piece blocks of ``model``: ``measurement``, ``prior``, ``features``, ``head``,
    ``scales``. A config in the first format (flat keys) is translated, with a
    ``FutureWarning`` that shows the blocks to write instead; both at once is an error."""
    get = model.get if hasattr(model, "get") else (lambda k, d=None: getattr(model, k, d))
    prior = _plain(get("prior", None))
    old_prior = prior if isinstance(prior, str) else "none"
    flat = blocks_from_flat(model, old_prior)
    new = {
        "measurement": _plain(get("measurement", None)) or {},
        "prior": prior if not isinstance(prior, str) else None,
        "features": _plain(get("features", None)),
        "head": _plain(get("head", None)) or {},
        "scales": _plain(get("scales", None)) or [],
    }
    given = [k for k, v in new.items() if v not in (None, {}, [])]
    if flat is not None:
        if given:
            where = "; ".join(f"model.{k} -> {BLOCK_OF.get(k, 'model.prior')}"
                              for k in flat_keys_set(model) or ["prior"])
            raise ValueError(
                f"the model config is written in blocks ({given}) but also sets flat keys of the "
                f"first format; set them in their blocks instead ({where}), e.g. "
                "'++model.head={type: centred, c: 0.7}'."
            )
        warnings.warn(
            f"the model config's flat keys {flat_keys_set(model) or ['prior']} are deprecated; "
            f"write these blocks instead (configs/model/ has examples): {_yaml(flat)}",
            FutureWarning,
            stacklevel=3,
        )
        return flat
    measurement = _block(new["measurement"], "model.measurement") if new["measurement"] else {}
    features = new["features"]
    if features is None:
        features = ["embedding", "readings"] + (["innovation"] if measurement.get("factors") else [])
    return {
        "measurement": {"type": "measurement", **measurement},
        "prior": _block(new["prior"] or "none", "model.prior"),
        "features": [_block(f, f"model.features[{i}]") for i, f in enumerate(features)],
        "head": _block(new["head"] or "plain", "model.head"),
        "scales": [_block(s, f"model.scales[{i}]") for i, s in enumerate(new["scales"])],
    }


def _yaml(blocks: dict) -> str:
    import yaml

    return "\n" + yaml.safe_dump(blocks, sort_keys=False, default_flow_style=None)


#: Arguments a builder supplies to a piece when its constructor takes them: the system (a system
#: prior), the step length (a kinematic prior), the measurement's sizes.
_CONTEXT = ("system", "dt", "dim", "input_dim")


def build_piece(kind: str, block: dict, where: str, context: dict | None = None):
    """The piece of ``kind`` that ``block`` names (``{type: name, **arguments}``), its
    arguments checked against the piece's constructor; errors name ``where``. Nested blocks
    (a centred head's ``inner``) are built likewise. Nothing is imported."""
    block = dict(block)
    cls = piece_class(kind, block.pop("type", None), f"{where}.type")
    params = {
        name: p for name, p in inspect.signature(cls.__init__).parameters.items()
        if name != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    }
    for name in _CONTEXT:  # a block may repeat what the system fixes (a signature's settings)
        if name in block and name in params and context and context.get(name) is not None:
            if block[name] != context[name]:
                raise ValueError(
                    f"{where} ({cls.name}): {name}={block[name]!r}, but the system's is "
                    f"{context[name]!r}; leave {name} out (the system gives it)."
                )
    allowed = [p for p in params if p not in _CONTEXT or p in block]
    unknown = sorted(set(block) - set(allowed))
    if unknown:
        raise ValueError(
            f"{where} ({cls.name}): unknown key(s) {unknown}; a {cls.name} {kind} takes "
            f"{allowed or 'no arguments'}."
        )
    if "inner" in block:
        block["inner"] = build_piece(kind, _block(block["inner"], f"{where}.inner"),
                                     f"{where}.inner", context)
    for name in _CONTEXT:
        if name in params and name not in block and context and context.get(name) is not None:
            block[name] = context[name]
    missing = [
        p for p, spec in params.items() if spec.default is inspect.Parameter.empty and p not in block
    ]
    if missing:
        need = " (pass build_observer(..., system=system))" if "system" in missing else ""
        raise ValueError(f"{where} ({cls.name}): needs {missing}{need}.")
    try:
        return cls(**block)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where} ({cls.name}): {err}") from None


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
