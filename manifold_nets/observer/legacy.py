"""Compatibility with the first model format: flat ``model.*`` keys and version-1 checkpoints.

Before the observer was made of pieces, a model config switched each extension on with a flat
key (``model.innovation``, ``model.centering``, ``model.robust_drive``, ...), and a checkpoint
(``manifold_nets.checkpoint/1``) recorded them in a flat signature, with the robust weights
under ``robust_drive.*`` and ``robust_innovation.*``. This module translates both:

* :func:`blocks_from_flat`: the piece blocks (``measurement``, ``prior``, ``features``,
  ``head``, ``scales``) that a config's flat keys mean, or ``None`` when it sets none;
* :func:`flat_signature`: what the first format's signature of an observer is, to check a
  version-1 checkpoint against the observer built from its config;
* :func:`state_from_v1`: a version-1 ``state_dict`` with today's parameter names.

Two flat options are gone, because they measured nothing: ``model.clock`` (clock inputs:
"changed nothing" in two ablations) and ``model.prior_drive`` (the prior's drive as an input:
-0.2 to -0.4 %). A config or checkpoint that sets them is refused with that reason.
"""

from __future__ import annotations

from typing import Any

__all__ = ["FLAT_KEYS", "REMOVED", "blocks_from_flat", "flat_signature", "state_from_v1"]

#: The flat keys of the first format and their defaults (unset).
FLAT_KEYS: dict[str, Any] = {
    "innovation": {}, "relative_only": [], "rotated": {}, "propagate": {}, "clock": [],
    "innovation_frame": {}, "prior_drive": False, "gain": False, "gain_offset": True,
    "centering": 0.0, "centering_ramp": 0, "centering_factors": {}, "step_decay": {},
    "robust_drive": 0, "robust_innovation": 0, "robust_span": 4.0, "output_scale": 1.0,
}
#: Where each flat key went: the block that holds it now.
BLOCK_OF = {
    "innovation": "model.measurement.factors", "relative_only": "the drop of model.features' "
    "embedding and readings", "rotated": "a {type: rotated, vectors: ...} feature", "propagate":
    "model.prior={type: kinematic, velocities: ...}", "innovation_frame": "a {type: "
    "framed_innovation, frames: ...} feature", "gain": "model.head={type: gain}", "gain_offset":
    "model.head.offset", "centering": "model.head={type: centred, c: ...}", "centering_ramp":
    "model.head.ramp", "centering_factors": "model.head.factors", "step_decay": "a {type: "
    "step_decay, factors: ...} entry of model.scales", "robust_drive": "model.prior={type: "
    "robust_system, width: ...}", "robust_innovation": "model.measurement={type: robust, width: "
    "...}", "robust_span": "the span of the robust prior or measurement", "output_scale": "a "
    "{type: output, scale: ...} entry of model.scales",
}
#: Flat options that were removed, and why.
REMOVED = {
    "clock": "clock inputs changed nothing in two ablations",
    "prior_drive": "the prior's drive as an input measured -0.2 to -0.4 %, within noise",
}


def _get(model, key):
    value = model.get(key, FLAT_KEYS[key]) if isinstance(model, dict) else getattr(
        model, key, FLAT_KEYS[key]
    )
    if hasattr(value, "items"):
        return {k: _plain(v) for k, v in value.items()}
    return _plain(value)


def _plain(value):
    if isinstance(value, (list, tuple)) or type(value).__name__ == "ListConfig":
        return [_plain(v) for v in value]
    if hasattr(value, "items"):
        return {k: _plain(v) for k, v in value.items()}
    return value


def flat_keys_set(model) -> list[str]:
    """The flat keys ``model`` sets to other than their defaults."""
    return [k for k, default in FLAT_KEYS.items() if _get(model, k) != default]


def blocks_from_flat(model, prior: str = "none") -> dict | None:
    """The piece blocks of a config's flat keys (``prior`` the old ``model.prior`` string), or
    ``None`` when it sets none and ``prior`` is ``none``. Raises ``ValueError`` for a removed
    option."""
    used = flat_keys_set(model)
    if prior not in (None, "none", "system"):
        raise ValueError(
            f"model.prior={prior!r} is not one of ('none', 'system'); write the prior as a block, "
            "e.g. model.prior={type: system} (types: none, system, robust_system, kinematic)."
        )
    partners = {"gain_offset": ("gain", "model.gain=true"),
                "centering_ramp": ("centering", "model.centering (0 < c <= 1)"),
                "centering_factors": ("centering", "model.centering (0 < c <= 1)")}
    for key, (partner, fix) in partners.items():
        if key in used and partner not in used:
            raise ValueError(f"model.{key} is a setting of model.{partner}, which is not set; set "
                             f"{fix}, or write the head as a block (model.head).")
    if "robust_drive" in used and prior != "system":
        raise ValueError("model.robust_drive weighs the drive of the model prior, but there is no "
                         "model prior; set model.prior=system, or write model.prior={type: "
                         "robust_system}.")
    for key in used:
        if key in REMOVED:
            raise ValueError(
                f"model.{key} was removed ({REMOVED[key]}); drop it from the config. An observer "
                "trained with it cannot be loaded by this version."
            )
    if not used and prior in (None, "none"):
        return None
    g = {k: _get(model, k) for k in FLAT_KEYS}
    measured = g["innovation"]
    measurement: dict[str, Any] = {"type": "measurement", "factors": measured}
    if g["robust_innovation"]:
        measurement = {"type": "robust", "factors": measured, "width": g["robust_innovation"],
                       "span": g["robust_span"]}
    if prior == "system":
        prior_block = {"type": "system"}
        if g["robust_drive"]:
            prior_block = {"type": "robust_system", "width": g["robust_drive"],
                           "span": g["robust_span"]}
    elif g["propagate"]:
        prior_block = {"type": "kinematic", "velocities": g["propagate"]}
    else:
        prior_block = {"type": "none"}
    drop = g["relative_only"]
    features: list[dict] = [
        {"type": "embedding", **({"drop": drop} if drop else {})},
        {"type": "readings", **({"drop": list(drop)} if drop else {})},
    ]
    if measured:
        features.append({"type": "innovation"})
    if g["rotated"]:
        features.append({"type": "rotated", "vectors": g["rotated"]})
    if g["innovation_frame"]:
        features.append({"type": "framed_innovation", "frames": g["innovation_frame"]})
    head: dict[str, Any] = {"type": "plain"}
    if g["gain"]:
        head = {"type": "gain", **({} if g["gain_offset"] else {"offset": False})}
    if g["centering"]:
        head = {"type": "centred", "c": g["centering"],
                **({"ramp": g["centering_ramp"]} if g["centering_ramp"] else {}),
                **({"factors": g["centering_factors"]} if g["centering_factors"] else {}),
                **({"inner": head} if head["type"] != "plain" else {})}
    scales: list[dict] = []
    if g["step_decay"]:
        scales.append({"type": "step_decay", "factors": g["step_decay"]})
    if g["output_scale"] != 1.0:
        scales.append({"type": "output", "scale": g["output_scale"]})
    return {"measurement": measurement, "prior": prior_block, "features": features,
            "head": head, "scales": scales}


def flat_signature(observer) -> dict:
    """The first format's signature of ``observer`` (a version-1 checkpoint must match it)."""
    sig = observer.signature()
    m = sig["measurement"]
    by_type = {f["type"]: f for f in sig["features"]}
    prior, head = sig["prior"], sig["head"]
    out: dict[str, Any] = {
        "group": sig["group"], "measurement_dim": m["dim"], "input_dim": m["input_dim"],
        "update": sig["update"], "innovation": m["factors"],
        "relative_only": list(by_type.get("embedding", {}).get("drop", [])),
    }
    rotated = by_type.get("rotated", {}).get("vectors", {})
    propagate = prior.get("velocities", {}) if prior["type"] == "kinematic" else {}
    if rotated or propagate:
        out.update(rotated=rotated, propagate=propagate, dt=prior.get("dt"))
    if "framed_innovation" in by_type:
        out["innovation_frame"] = by_type["framed_innovation"]["frames"]
    out["core"] = sig["core"]
    for s in sig["scales"]:
        if s["type"] == "output":
            out["output_scale"] = s["scale"]
        if s["type"] == "step_decay":
            out["step_decay"] = s["factors"]
    if prior["type"] in ("system", "robust_system"):
        out["prior"] = "system"
    inner = head.get("inner", head) if head["type"] == "centred" else head
    if inner["type"] == "gain":
        out["gain"] = True
        if inner.get("offset") is False:
            out["offset"] = False
    if head["type"] == "centred":
        out["centering"] = head["c"]
        if head.get("ramp"):
            out["centering_ramp"] = head["ramp"]
        if head.get("factors"):
            out["centering_factors"] = head["factors"]
    if prior["type"] == "robust_system":
        out["robust_drive"] = {"channels": observer.prior.robust.channels,
                               "width": prior["width"], "span": prior["span"]}
    if m["type"] == "robust":
        out["robust_innovation"] = {"channels": len(m["factors"]), "width": m["width"],
                                    "span": m["span"]}
    return out


def state_from_v1(state: dict) -> dict:
    """A version-1 ``state_dict`` with today's names (the robust weights moved into their pieces)."""
    rename = {"robust_drive.": "prior.robust.", "robust_innovation.": "measurement.robust."}
    out = {}
    for key, value in state.items():
        for old, new in rename.items():
            if key.startswith(old):
                key = new + key[len(old):]
        out[key] = value
    return out
