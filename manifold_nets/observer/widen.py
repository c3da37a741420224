"""Fine-tuning from an older observer (``train.init_from``): its weights into one with more pieces.

:func:`widen_state` takes the ``state_dict`` and signature of a trained observer and returns a
``state_dict`` for ``observer``. Pieces with weights that the trained observer lacked start as
the identity, so the observer computes what the trained one did, but for the weightless pieces
whose settings it changes (a centring, a step decay: those compute what their settings say):

* a feature the trained observer did not read gets zero input weights in the core's first layer
  (a :class:`~manifold_nets.cores.GRUCore`), wherever it sits in the list;
* every other piece says how it widens (:meth:`Piece.widen`): learned robust weights start as the
  identity, a gain head's ``K`` at zero, an output scale rescales the head; pieces without
  weights (a centring, a step decay, a complementary prior's correction, their settings) load
  across any settings.

What cannot be widened (another group, measurement, core type or size, a feature the trained
observer read but this one does not) raises ``ValueError`` naming it.
"""

from __future__ import annotations

import torch

__all__ = ["widen_state"]


def _same(what: str, old, new) -> None:
    if old != new:
        raise ValueError(f"{what} differs: checkpoint {old!r}, model {new!r}")


def widen_state(observer, state: dict, found: dict) -> dict:
    """``state`` (of an observer whose signature is ``found``) widened for ``observer``."""
    own = observer.signature()
    for key in ("group", "update"):
        _same(key, found.get(key), own[key])
    fm, om = dict(found.get("measurement", {})), dict(own["measurement"])
    for key in ("dim", "input_dim", "factors"):
        _same(f"measurement.{key}", fm.get(key), om.get(key))
    fc, oc = found.get("core", {}), own["core"]
    for key in set(fc) | set(oc):
        if key not in ("input_size", "output_size"):
            _same(f"core.{key}", fc.get(key), oc.get(key))
    state = _widen_features(observer, dict(state), list(found.get("features", [])))
    pieces = observer.pieces()
    for kind, wrapper, default in (("prior", "complementary", "none"), ("head", "centred", "plain")):
        _only_adds(kind, _unwrapped(found.get(kind), wrapper, default),
                   _unwrapped(own[kind], wrapper, default))
    _only_adds("measurement", _base(fm), _base(om))
    old_scales = {s.get("type"): s for s in found.get("scales", [])}
    gone = sorted(set(old_scales) - {s.name for s in observer.scales} - {"output"})
    if gone:
        raise ValueError(f"the checkpoint's scales {gone} are not in this observer")
    state = pieces["measurement"].widen(state, "measurement.", fm)
    state = pieces["prior"].widen(state, "prior.", found.get("prior"))
    state = pieces["head"].widen(state, "head.", found.get("head"))
    for i, scale in enumerate(observer.scales):  # an output scale adds no weight: _rescale
        state = scale.widen(state, f"scales.{i}.", old_scales.get(scale.name))
    return _rescale(state, old_scales.get("output"), own)


#: What a piece of the checkpoint may become (adding weights that start as the identity).
_WIDENS = {"system": "robust_system", "measurement": "robust", "plain": "gain"}


def _base(sig: dict | None) -> str:
    return (sig or {}).get("type", "none")


def _unwrapped(sig: dict | None, wrapper: str, default: str) -> str:
    """A piece's type less a weightless wrapper around an inner piece (a head's centring, a
    prior's complementary correction); ``default`` where there is none."""
    sig = sig or {"type": default}
    while sig.get("type") == wrapper:  # complementary priors nest
        sig = sig.get("inner", {"type": default})
    return sig.get("type", default)


def _only_adds(kind: str, old: str, new: str) -> None:
    if old != new and _WIDENS.get(old) != new:
        raise ValueError(
            f"the checkpoint's {kind} is {old!r}, this observer's {new!r}: that changes what the "
            "trained observer computes (only robust weights or a gain can be added)"
        )


def _rescale(state: dict, old: dict | None, own: dict) -> dict:
    """An output scale changed (or added, or dropped): the head's rows rescaled so that ``v`` is
    what it was (``v = s T(z)``)."""
    before = 1.0 if old is None else float(old.get("scale", 1.0))
    after = next((float(s["scale"]) for s in own["scales"] if s["type"] == "output"), 1.0)
    if before == after:
        return state
    ratio = before / after
    return {k: (v * ratio if k in ("core.head.weight", "core.head.bias") else v)
            for k, v in state.items()}


def _widen_features(observer, state: dict, old: list[dict]) -> dict:
    """Zero input columns for each feature ``observer`` reads that ``old`` did not."""
    new = [f.signature() for f in observer.features]
    inserted, j = [], 0
    at = 0
    for f, sig in zip(observer.features, new):
        if j < len(old) and old[j] == sig:
            j += 1
        else:
            inserted.append((at, f.width, sig["type"]))
        at += f.width
    if j != len(old):
        raise ValueError(
            f"the checkpoint's features {[o.get('type') for o in old]} are not all among this "
            f"observer's {[s['type'] for s in new]}, in order; only features can be added."
        )
    if not inserted:
        return state
    key = "core.gru.weight_ih_l0"
    w = state.get(key)
    if w is None or w.dim() != 2:
        raise ValueError(
            f"features {[t for _, _, t in inserted]} can be added only to a GRU core (core.gru)."
        )
    for at, width, _ in inserted:  # in order: each offset is in the widened layout
        zeros = torch.zeros((w.shape[0], width), dtype=w.dtype, device=w.device)
        w = torch.cat([w[:, :at], zeros, w[:, at:]], dim=1)
    return {**state, key: w}
