"""A trained observer back from a run folder or a checkpoint, in one call, executing nothing.

:func:`load_observer` reads the resolved config a run left behind (``<run>/config.yaml``, or the
``config`` entry of a checkpoint), rebuilds the system and the observer from it and loads the
weights::

    from manifold_nets import load_observer

    observer, system, config = load_observer("outputs/default/<run id>")
    observer, system, config = load_observer("zoo:rigid_body/nominal")     # a zoo entry

A file from elsewhere is data, not code. What it may make happen:

* the config is parsed as plain YAML (``yaml.safe_load``) or read from a checkpoint with
  ``torch.load(weights_only=True)``; it must be plain data (mappings, lists, numbers, strings),
  without omegaconf interpolations (``${...}``; a resolved config has none);
* ``system._target_`` is only *looked up* among the :class:`~manifold_nets.system.System`
  subclasses the program has imported or the installed packages declare
  (:data:`manifold_nets.system.SYSTEMS`, :mod:`manifold_nets.plugins`); the class is called
  with the other keys as keyword arguments, which must be plain values (no nested ``_target_``,
  no other ``_``-keys of hydra's instantiate);
* ``model.core`` is ``gru`` or an imported :class:`~manifold_nets.cores.RecurrentCore` subclass
  (:data:`manifold_nets.cores.CORES`);
* the weights load with ``weights_only=True`` after the checkpoint's signature (group, update
  rules, measurement, pieces, core) is checked against the rebuilt observer
  (:func:`manifold_nets.checkpoint.check_signature`).

An ensemble folder (``members/<name>/``, each a run folder; :func:`ensemble_members`) loads
member by member as above; its members are real folders inside ``members/`` (no link), at most
:data:`MAX_MEMBERS`, of one system.

Nothing named by the file is imported or called otherwise; an unknown name is an error that says
to import the module defining it first. Not checked: that the system's parameters describe the
system the data came from (they are the run's), nor anything about the estimates.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import torch
import yaml
from omegaconf import DictConfig, OmegaConf

from .builders import build_observer
from .checkpoint import load_checkpoint, load_state, observer_state, resolve_checkpoint
from .config import RunConfig
from .observer import ResidualObserver, with_readings_filter
from .plugins import locate
from .system import SYSTEMS, System

__all__ = [
    "LoadedObserver", "ArtefactError", "LIMITS", "check_sizes", "load_observer",
    "build_system_safely", "ensemble_members", "MAX_MEMBERS",
]


class ArtefactError(ValueError):
    """A run folder or checkpoint cannot be turned back into an observer (and nothing ran)."""


class LoadedObserver(NamedTuple):
    """What :func:`load_observer` returns (unpacks as ``observer, system, config``)."""

    #: The trained observer, its best weights loaded, in eval mode, on ``map_location`` (an
    #: :class:`~manifold_nets.observer.EnsembleObserver` from an ensemble folder).
    observer: ResidualObserver
    #: The system it was trained on, built from the run's ``system`` config.
    system: System
    #: The run's resolved config, typed by :class:`~manifold_nets.config.RunConfig`.
    config: DictConfig

    def filtered(self):
        """The observer behind its system's readings filter (a
        :class:`~manifold_nets.observer.FilteredObserver`: raw readings in, for rollouts, online
        steps and :func:`~manifold_nets.export_observer`), or the observer itself when the
        system has none (:func:`~manifold_nets.observer.with_readings_filter`)."""
        return with_readings_filter(self.observer, self.system)


#: Bounds on a config read from a file: bytes, nesting depth, nodes (mappings, lists, values).
MAX_CONFIG_BYTES, MAX_DEPTH, MAX_NODES = 1 << 20, 32, 100_000


def _check_plain(value: Any, where: str, _budget: list | None = None, _depth: int = 0) -> None:
    """Raises :class:`ArtefactError` unless ``value`` is plain data without interpolations,
    nested at most :data:`MAX_DEPTH` levels and of at most :data:`MAX_NODES` nodes (shared
    references count each time they are reached, so a structure that shares itself 2^40 ways is
    refused after 100000 nodes instead of walked)."""
    budget = [MAX_NODES] if _budget is None else _budget
    budget[0] -= 1
    if budget[0] < 0:
        raise ArtefactError(f"{where}: the config has more than {MAX_NODES} nodes; refused.")
    if _depth > MAX_DEPTH:
        raise ArtefactError(f"{where}: the config nests deeper than {MAX_DEPTH} levels; refused.")
    if value is None or isinstance(value, (bool, int, float)):
        if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 2**63:
            raise ArtefactError(f"{where} is an integer of {value.bit_length()} bits; refused.")
        return
    if isinstance(value, str):
        if "${" in value:
            raise ArtefactError(
                f"{where} = {value!r:.200} is an interpolation; a resolved config holds plain "
                "values."
            )
        return
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _check_plain(v, f"{where}[{i}]", budget, _depth + 1)
        return
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str):
                raise ArtefactError(f"{where} has a key {k!r:.100} that is not a string.")
            _check_plain(v, f"{where}.{k}", budget, _depth + 1)
        return
    raise ArtefactError(
        f"{where} is a {type(value).__name__}; a config file holds plain values only."
    )


class _PlainLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` without aliases (a billion-laughs file is refused, not expanded) and
    with a bound on nesting."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.YAMLError(f"an alias (*{event.anchor}) at {event.start_mark}: a resolved "
                                 "config has none")
        self._depth = getattr(self, "_depth", 0) + 1
        try:
            if self._depth > MAX_DEPTH:
                raise yaml.YAMLError(f"nesting deeper than {MAX_DEPTH} levels")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def read_plain_yaml(path: Path) -> Any:
    """A config file as plain data: at most :data:`MAX_CONFIG_BYTES`, UTF-8, YAML without aliases,
    nested at most :data:`MAX_DEPTH` levels; :class:`ArtefactError` naming the file otherwise."""
    size = path.stat().st_size
    if size > MAX_CONFIG_BYTES:
        raise ArtefactError(f"{path} is {size} bytes; a config is at most {MAX_CONFIG_BYTES}.")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as err:
        raise ArtefactError(f"{path} is not UTF-8 text ({err.reason} at byte {err.start}).") from None
    try:
        return yaml.load(text, Loader=_PlainLoader)  # noqa: S506 - a SafeLoader subclass
    except (yaml.YAMLError, ValueError, RecursionError) as err:
        detail = " ".join(str(err).split())[:300]
        raise ArtefactError(f"{path} is not a plain YAML config ({detail}).") from None


def _check_parameter(value: Any, where: str) -> None:
    """A system parameter: plain, with no mapping that asks hydra to build an object."""
    if isinstance(value, dict):
        nested = sorted(k for k in value if k.startswith("_"))
        if nested:
            raise ArtefactError(
                f"{where} holds {nested}: system parameters are plain values, never objects to "
                "build (manifold_nets does not instantiate nested targets from a file)."
            )
        for k, v in value.items():
            _check_parameter(v, f"{where}.{k}")
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _check_parameter(v, f"{where}[{i}]")


def build_system_safely(system_cfg: Any, where: str = "system") -> System:
    """The system of a ``system`` config read from a file: ``_target_`` looked up among the
    imported :class:`~manifold_nets.system.System` subclasses and called with the other keys,
    plain values. Raises :class:`ArtefactError` before anything is called otherwise."""
    if isinstance(system_cfg, DictConfig):
        system_cfg = OmegaConf.to_container(system_cfg, resolve=False)
    if not isinstance(system_cfg, dict):
        raise ArtefactError(f"{where} must be a mapping with a _target_, got {system_cfg!r}.")
    _check_plain(system_cfg, where)
    params = dict(system_cfg)
    target = params.pop("_target_", None)
    cls = SYSTEMS.lookup(target, where=f"{where}._target_")
    hydra_keys = sorted(k for k in params if k.startswith("_"))
    if hydra_keys:
        raise ArtefactError(
            f"{where} holds {hydra_keys}: only _target_ and the class's parameters are read."
        )
    for name, value in params.items():
        _check_parameter(value, f"{where}.{name}")
    system = cls(**params)
    if not isinstance(system, System):  # a registered class always is; a guard for subclasses
        raise ArtefactError(f"{where}._target_ {target!r} did not make a System.")
    return system


#: The largest sizes a file may ask for: a GRU of 16384 units is already 3 GB a layer.
LIMITS = {"hidden_size": 16384, "num_layers": 64}


def check_sizes(model: Any, signature: dict, where: str) -> None:
    """Refuses, before anything is built, a model config whose core sizes exceed :data:`LIMITS`
    or differ from the checkpoint's signature (``ArtefactError`` naming the file and the key)."""
    core = signature.get("core") if isinstance(signature, dict) else None
    core = core if isinstance(core, dict) else {}
    for key, limit in LIMITS.items():
        value = getattr(model, key, None)
        if isinstance(value, int) and not 1 <= value <= limit:
            raise ArtefactError(
                f"{where}: model.{key}={value} is outside 1 .. {limit}; refused before building."
            )
        if key in core and core[key] != value:
            raise ArtefactError(
                f"{where}: model.{key}={value}, but the checkpoint's core has {core[key]}; the "
                "config does not describe these weights (refused before building)."
            )


def _read_config(path: Path) -> tuple[dict, Path, dict | None]:
    """``(config, checkpoint file, checkpoint or None)`` of a run folder or a checkpoint file."""
    if path.is_dir():
        cfg_file = path / "config.yaml"
        ckpt_file = resolve_checkpoint(path, name="best.pt")
        if not cfg_file.is_file():
            ckpt = load_checkpoint(ckpt_file)
            return ckpt.get("config"), ckpt_file, ckpt
        return read_plain_yaml(cfg_file), ckpt_file, None
    if not path.exists():
        raise ArtefactError(f"{path} is neither a run folder nor a checkpoint file.")
    ckpt = load_checkpoint(path)
    return ckpt.get("config"), path, ckpt


def load_observer(
    path: str | os.PathLike, map_location: str | torch.device = "cpu"
) -> LoadedObserver:
    """The trained observer, its system and its config from a run folder (``config.yaml`` and
    ``checkpoints/best.pt``) or a checkpoint file (its ``config`` entry); see the module
    docstring for what is checked and what never runs.

    ``path`` may be a zoo entry, ``zoo:rigid_body/nominal``, or an ensemble folder (its run
    folders under ``members/``, :func:`ensemble_members`): the observer is then an
    :class:`~manifold_nets.observer.EnsembleObserver` of theirs. The system class
    (``system._target_``) and a core other than ``gru`` must have been imported by the program or
    be declared by an installed package (:mod:`manifold_nets.plugins`); the project's own example
    systems are.
    """
    try:
        path = locate(path)
    except ValueError as err:
        raise ArtefactError(str(err)) from None
    members = ensemble_members(path)
    if members is not None:
        return _load_ensemble(path, members, map_location)
    raw, ckpt_file, ckpt = _read_config(path)
    where = str(path / "config.yaml" if path.is_dir() and ckpt is None else ckpt_file)
    if not isinstance(raw, dict) or "system" not in raw:
        raise ArtefactError(f"{where} holds no run config (a mapping with 'system' and 'model').")
    _check_plain(raw, where)
    system = build_system_safely(raw["system"], where=f"{where}: system")
    try:
        cfg = OmegaConf.merge(OmegaConf.structured(RunConfig), raw)
    except Exception as err:  # omegaconf's validation errors
        msg = str(err).splitlines()[0]
        raise ArtefactError(f"{where} does not fit the run schema: {msg}.") from None
    if ckpt is None:
        ckpt = load_checkpoint(ckpt_file, map_location=map_location)
    check_sizes(cfg.model, ckpt["signature"], str(ckpt_file))  # before anything is allocated
    with warnings.catch_warnings():  # a file's first-format keys: the reader's business
        warnings.simplefilter("ignore", FutureWarning)
        model = build_observer(
            system.group, system.measurement_dim, system.input_dim, cfg.model, import_core=False,
            dt=getattr(system, "dt", None), system=system,
        )
    load_state(model, {**ckpt, "model": observer_state(model, ckpt, ckpt_file)}, ckpt_file)
    return LoadedObserver(model.to(map_location).eval(), system, cfg)


#: The most members an ensemble folder may hold (a file must not make the loader build without
#: bound).
MAX_MEMBERS = 16


def ensemble_members(path: Path) -> list[Path] | None:
    """The member run folders of an ensemble folder (``<path>/members/<name>/``, by name), or
    ``None`` when ``path`` is not one (a run folder, a checkpoint). ``ArtefactError`` for an
    empty ``members/``, more than :data:`MAX_MEMBERS`, a member that is a link, not a folder or
    an ensemble folder itself, or a ``config.yaml`` beside ``members/`` (one folder, one
    observer)."""
    folder = Path(path) / "members"
    if not folder.is_dir():
        return None
    if (Path(path) / "config.yaml").exists():
        raise ArtefactError(f"{path} holds both a config.yaml and members/: a run folder or an "
                            "ensemble folder, not both.")
    members = sorted(folder.iterdir(), key=lambda p: p.name)
    if not members or len(members) > MAX_MEMBERS:
        raise ArtefactError(f"{folder} holds {len(members)} entries; an ensemble folder holds 1 "
                            f"to {MAX_MEMBERS} member run folders.")
    for m in members:
        if m.is_symlink() or not m.is_dir():
            raise ArtefactError(f"{m} is not a run folder (a link or a file); an ensemble's "
                                "members are run folders inside members/ itself.")
        if (m / "members").exists():  # refused before anything loads, however deep it nests
            raise ArtefactError(f"{m} is itself an ensemble folder; an ensemble's members are "
                                "run folders (flatten the ensembles into one members/).")
    return members


def _load_ensemble(path: Path, members: list[Path], map_location) -> LoadedObserver:
    """An ensemble folder's members loaded, one system: their ensemble, the first's config."""
    from .observer import EnsembleObserver

    loaded = [load_observer(m, map_location) for m in members]
    first = OmegaConf.to_container(loaded[0].config.system)
    for m, one in zip(members[1:], loaded[1:]):
        if OmegaConf.to_container(one.config.system) != first:
            raise ArtefactError(f"{m}'s system differs from {members[0]}'s: an ensemble's members "
                                "observe one system.")
    try:
        ensemble = EnsembleObserver([one.observer for one in loaded])
    except (TypeError, ValueError) as err:
        raise ArtefactError(f"{path}: {err}") from None
    return LoadedObserver(ensemble.eval(), loaded[0].system, loaded[0].config)
