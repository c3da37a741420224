"""Checkpoints: a ``state_dict`` with the resolved config beside it, safe to load.

A checkpoint is one ``torch.save`` file holding only tensors and plain Python data (dicts,
lists, strings, numbers), so it loads with ``torch.load(weights_only=True)``: no pickled
module, no code execution on load. Keys:

* ``format``: ``"manifold_nets.checkpoint/2"`` (``/1``, the first format, with flat model keys,
  still loads: :mod:`manifold_nets.observer.legacy`);
* ``model``: the observer's ``state_dict``; ``signature``: what the model must match
  (group, update rules, measurement, pieces, core) — loading into another model fails with a
  clear message;
* ``config``: the resolved run config (a plain dict), so a run can be rebuilt from it;
* ``epoch``: the last finished epoch; optionally ``optimizer`` (its ``state_dict``), ``rng``
  (``torch.Generator`` states as byte tensors), ``best`` and ``history`` (for resuming).

Files are written to a temporary name in the same folder and renamed (``os.replace``), so an
interrupted write never leaves a half checkpoint.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from .atomic import atomic_open

__all__ = [
    "FORMAT",
    "CheckpointError",
    "save_checkpoint",
    "load_checkpoint",
    "check_contents",
    "check_signature",
    "load_state",
    "resolve_checkpoint",
    "load_weights",
    "observer_state",
]

FORMAT = "manifold_nets.checkpoint/2"
#: The first format: flat model keys in the config and the signature.
FORMAT_V1 = "manifold_nets.checkpoint/1"


class CheckpointError(ValueError):
    """A checkpoint file is missing, unreadable, of another format or for another model."""


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Writes ``payload`` (plain data and tensors) with the format tag to ``path``, atomically."""
    path = Path(path)
    for key in ("model", "signature", "config", "epoch"):
        if key not in payload:
            raise ValueError(f"a checkpoint needs the key {key!r}; got {sorted(payload)}.")
    with atomic_open(path, "wb") as f:
        torch.save({"format": FORMAT, **payload}, f)
    return path


def _describe_diff(found: dict, expected: dict, prefix: str = "") -> list[str]:
    out = []
    for key in sorted(set(found) | set(expected)):
        a, b = found.get(key, "<missing>"), expected.get(key, "<missing>")
        if isinstance(a, dict) and isinstance(b, dict):
            out += _describe_diff(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}: checkpoint {a!r}, model {b!r}")
    return out


def check_signature(found: dict, expected: dict, where: str = "checkpoint") -> None:
    """Raises :class:`CheckpointError` naming every field where two model signatures differ."""
    diff = _describe_diff(found, expected)
    if diff:
        raise CheckpointError(
            f"{where} was made for another model (" + "; ".join(diff) + "). Build the model "
            "with the checkpoint's config (its 'config' entry), or point to the right checkpoint."
        )


def load_checkpoint(
    path: str | os.PathLike,
    expected_signature: dict | None = None,
    map_location: str | torch.device = "cpu",
) -> dict[str, Any]:
    """Reads a checkpoint with ``torch.load(weights_only=True)`` and checks it.

    Raises :class:`CheckpointError` for a missing file, a file that is not a manifold_nets
    checkpoint, fields missing or of the wrong type (:func:`check_contents`), or (given
    ``expected_signature``, e.g. ``model.signature()``) a checkpoint of another model.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}; train first or fix the path.")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # unpickling errors come in many types
        raise CheckpointError(
            f"{path} is not a loadable checkpoint ({type(err).__name__}: {str(err)[:300]}); "
            "only files written by manifold_nets (plain data and tensors) load safely."
        ) from None
    if not isinstance(ckpt, dict) or ckpt.get("format") not in (FORMAT, FORMAT_V1):
        fmt = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise CheckpointError(f"{path} has format {fmt!r}, expected {FORMAT!r}.")
    check_contents(ckpt, path)
    if expected_signature is not None:
        check_signature(ckpt["signature"], expected_signature, where=str(path))
    return ckpt


def _bad(path, key: str, why: str) -> CheckpointError:
    return CheckpointError(
        f"{path}: the field {key!r} {why}. The file is damaged or was not written by "
        "manifold_nets; use another checkpoint (a run's checkpoints/best.pt or last.pt)."
    )


def _kind(value) -> str:
    return f"{value!r}" if isinstance(value, (int, float, str)) else type(value).__name__


def check_contents(ckpt: dict, path: str | os.PathLike = "checkpoint") -> None:
    """Raises :class:`CheckpointError` naming ``path`` and the field unless the checkpoint's
    fields have the types :func:`save_checkpoint` writes (the required ``model``, ``signature``,
    ``config``, ``epoch``; the optional ``best``, ``optimizer``, ``rng``, ``history``)."""
    for key in ("model", "signature", "config", "epoch"):
        if key not in ckpt:
            raise _bad(path, key, f"is missing (the file has {sorted(ckpt)})")
    model = ckpt["model"]
    if not isinstance(model, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in model.items()
    ):
        raise _bad(path, "model", f"must be a state_dict (names to tensors), got {_kind(model)}")
    for key in ("signature", "config"):
        if not isinstance(ckpt[key], dict):
            raise _bad(path, key, f"must be a dict, got {_kind(ckpt[key])}")
    epoch = ckpt["epoch"]
    if isinstance(epoch, bool) or not isinstance(epoch, int) or epoch < 0:
        raise _bad(path, "epoch", f"must be an integer >= 0, got {_kind(epoch)}")
    if "best" in ckpt:
        best = ckpt["best"]
        ok = (
            isinstance(best, dict)
            and isinstance(best.get("epoch"), int)
            and not isinstance(best.get("epoch"), bool)
            and isinstance(best.get("val_loss"), (int, float))
        )
        if not ok:
            raise _bad(
                path, "best", f"must be {{'epoch': int, 'val_loss': float}}, got {_kind(best)}"
            )
    if "optimizer" in ckpt:
        opt = ckpt["optimizer"]
        if not (isinstance(opt, dict) and {"state", "param_groups"} <= set(opt)):
            raise _bad(path, "optimizer", "must be an optimizer's state_dict (state, param_groups)")
    if "rng" in ckpt:
        rng = ckpt["rng"]
        for name in ("generator", "torch"):
            state = rng.get(name) if isinstance(rng, dict) else None
            if not (isinstance(state, torch.Tensor) and state.dtype == torch.uint8):
                raise _bad(
                    path, f"rng.{name}", f"must be a generator state (a uint8 tensor), got "
                    f"{_kind(state)}"
                )
    if "history" in ckpt and not (
        isinstance(ckpt["history"], list) and all(isinstance(r, dict) for r in ckpt["history"])
    ):
        raise _bad(path, "history", "must be a list of log rows (dicts)")


def load_state(model: torch.nn.Module, ckpt: dict, path: str | os.PathLike) -> None:
    """``model.load_state_dict(ckpt["model"])``, or a :class:`CheckpointError` naming ``path``
    when the tensors do not fit the model (a missing or unexpected name, a wrong shape, a sparse,
    meta or complex tensor, an integer weight for a floating one); checked
    before any is copied, so a refused checkpoint leaves the model as it was."""
    state, own = ckpt["model"], model.state_dict()
    problems = [f"missing {k}" for k in own if k not in state]
    problems += [f"unexpected {k}" for k in state if k not in own]
    problems += [
        f"{k}: checkpoint {tuple(state[k].shape)}, model {tuple(v.shape)}"
        for k, v in own.items()
        if k in state and state[k].shape != v.shape
    ]
    problems += [  # a weight is a dense real tensor of the model's kind (never cast silently)
        f"{k}: {_tensor_kind(state[k])}, model {v.dtype}" for k, v in own.items()
        if k in state and (state[k].layout != torch.strided or state[k].is_meta
                           or state[k].is_complex() or state[k].is_floating_point()
                           != v.is_floating_point())
    ]
    if problems:
        more = f"; {len(problems) - 5} more" if len(problems) > 5 else ""
        shown = "; ".join(problems[:5]) + more
        raise _bad(path, "model", f"does not fit the model ({shown})")
    try:
        model.load_state_dict(state)
    except RuntimeError as err:
        detail = " ".join(str(err).split())
        raise _bad(path, "model", f"does not fit the model ({detail[:500]})") from None


def _tensor_kind(t: torch.Tensor) -> str:
    if t.layout != torch.strided:
        return f"a {t.layout} tensor"
    if t.is_meta:
        return "a meta tensor (no data)"
    return f"dtype {t.dtype}"


def resolve_checkpoint(path: str | os.PathLike, name: str = "last.pt") -> Path:
    """A checkpoint file from a file path, a run folder (``<dir>/checkpoints/<name>``) or a zoo
    entry (``zoo:rigid_body/nominal``, :func:`manifold_nets.plugins.locate`)."""
    from .plugins import locate

    try:
        p = locate(path)
    except ValueError as err:
        raise CheckpointError(str(err)) from None
    if p.is_dir():
        for cand in (p / "checkpoints" / name, p / name):
            if cand.is_file():
                return cand
        if (p / "members").is_dir():
            raise CheckpointError(
                f"{path} is an ensemble folder (one run folder per member under members/), not one "
                f"checkpoint: name one member, e.g. {p / 'members' / '<name>'}."
            )
        raise CheckpointError(f"no {name} in the run folder {p} (looked in {p}/checkpoints/).")
    return p


def observer_state(model: torch.nn.Module, ckpt: dict, path: str | os.PathLike) -> dict:
    """The checkpoint's ``state_dict`` for ``model`` after checking its signature; a checkpoint
    of the first format is checked against the first format's signature of ``model`` and its
    tensors renamed (:mod:`manifold_nets.observer.legacy`)."""
    from .observer.legacy import flat_signature, state_from_v1

    if ckpt.get("format") == FORMAT_V1:
        check_signature(ckpt["signature"], flat_signature(model), where=str(path))
        return state_from_v1(ckpt["model"])
    check_signature(ckpt["signature"], model.signature(), where=str(path))
    return ckpt["model"]


def load_weights(
    model: torch.nn.Module,
    where: str | os.PathLike,
    map_location: str | torch.device = "cpu",
    widen: bool = False,
) -> tuple[Path, dict[str, Any]]:
    """Loads the weights of ``where`` (a checkpoint, or a run folder: its ``best.pt``) into
    ``model`` after checking the checkpoint is for the same model (``model.signature()``).

    With ``widen`` (``train.init_from``) the checkpoint of an observer with fewer pieces (a
    feature, learned robust weights, a gain head it lacked) or other settings of weightless
    pieces (a centring, a step decay) loads too, so that ``model`` starts out computing what
    the checkpoint's observer does (:func:`manifold_nets.observer.widen.widen_state`; a
    checkpoint of the first format loads only into the same observer).

    Returns the file and the checkpoint's contents.
    """
    from .observer.widen import widen_state

    path = resolve_checkpoint(where, name="best.pt")
    ckpt = load_checkpoint(path, map_location=map_location)
    if widen and ckpt.get("format") == FORMAT:
        try:
            state = widen_state(model, ckpt["model"], ckpt["signature"])
        except (ValueError, KeyError) as err:
            raise CheckpointError(
                f"{path} cannot start this model ({err}). Build the model with the checkpoint's "
                "config, or point to the right checkpoint."
            ) from None
    else:
        state = observer_state(model, ckpt, path)
    load_state(model, {**ckpt, "model": state}, path)
    return path, ckpt
