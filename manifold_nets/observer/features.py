"""Features: what the core reads, ``z = cat(f(view) for f in features)``, in the listed order.

Each feature maps the step's :class:`~manifold_nets.observer.measurement.StepView` to a
``(B, width)`` tensor in the network dtype. The paper's core reads ``(embed(xhat_k), y_{k+1},
u_k)``: :class:`Embedding` then :class:`Readings`. The others are extensions:

* :class:`Innovation`: the measured factors' innovations ``log(xhat_f^-1 m_f)``, which turn the
  nonlinear comparison of two embedded elements into an input the network can use linearly;
* :class:`Rotated`: body-frame 3-vectors of ``(y, u)`` (an accelerometer's, a magnetometer's)
  rotated to the world frame by a rotation factor's estimate, ``Rhat v``;
* :class:`FramedInnovation`: a vector factor's innovation in a rotation factor's estimated frame,
  ``Rhat^T (p^m - phat)`` (the rigid body's velocity bias enters the position through ``R``).

``Embedding(drop=[p])`` and ``Readings(drop=[p])`` leave a factor's absolute estimate and
measurement out, so the core sees it only through its innovation (for the rigid body: an
observer invariant to translations). A feature added to a trained observer (``train.init_from``)
starts with zero weights: it reads its input, but the observer computes what it did.
"""

from __future__ import annotations

import torch

from .fused import cast
from .piece import Piece, check_factor

__all__ = [
    "Feature", "Embedding", "Readings", "Innovation", "Rotated", "FramedInnovation",
    "reads_as_one",
]


def _spans(owner: str, value) -> tuple[tuple[int, int], ...]:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
        raise ValueError(f"{owner} must be a list of (start, stop) spans, got {value!r}.")
    out = []
    for span in value:
        try:
            a, b = (int(i) for i in span)
        except (TypeError, ValueError):
            raise ValueError(f"{owner}: {span!r} is not (start, stop).") from None
        out.append((a, b))
    return tuple(out)


class Feature(Piece):
    """``forward(view) -> (B, width)`` in the network dtype; ``width`` is set by :meth:`bind`."""

    kind = "feature"
    width: int = 0

    def widen(self, state, prefix, old):  # the observer widens the core's input instead
        return state


class _Dropping(Feature):
    """A feature that may leave some factors out (``drop``)."""

    def __init__(self, drop=()):
        super().__init__()
        if isinstance(drop, str):
            drop = [drop]
        self.drop = tuple(str(n) for n in drop)

    def settings(self):
        return {"drop": list(self.drop)} if self.drop else {}

    def _check(self, group, measurement):
        for n in self.drop:
            check_factor(f"{self.name}: drop", group, n)
            if n not in measurement.factors:
                raise ValueError(
                    f"{self.name}: drop={list(self.drop)} leaves factor {n!r} out, but the "
                    "measurement does not measure it, so the core would not see it at all; "
                    "give it a span in the measurement's factors or keep it."
                )


class Embedding(_Dropping):
    """``embed(x^-)``, less the dropped factors' columns."""

    name = "embedding"

    def bind(self, group, measurement):
        from .update import GroupUpdate

        self._check(group, measurement)
        self.update = GroupUpdate().bind(group)  # its embed of a flat state
        keep = torch.ones(group.embedding_dim, dtype=torch.bool)
        for n in self.drop:
            keep[group.embedding_slice(n)] = False
        idx = keep.nonzero().flatten() if self.drop else None
        self.register_buffer("keep", idx, persistent=False)
        self.width = group.embedding_dim if idx is None else len(idx)
        return self

    def forward(self, view):
        e = self.update.embed(view.x)
        if self.keep is not None:
            e = e.index_select(-1, self.keep)
        return cast(e, view.yu.dtype)


class Readings(_Dropping):
    """``(y, u)`` as the core reads them, less the dropped factors' measured columns."""

    name = "readings"

    def bind(self, group, measurement):
        self._check(group, measurement)
        width = measurement.dim + measurement.input_dim
        keep = torch.ones(width, dtype=torch.bool)
        for n in self.drop:
            a, b = measurement.factors[n]
            keep[a:b] = False
        idx = keep.nonzero().flatten() if self.drop else None
        self.register_buffer("keep", idx, persistent=False)
        self.width = width if idx is None else len(idx)
        return self

    def forward(self, view):
        return view.yu if self.keep is None else view.yu.index_select(-1, self.keep)


class Innovation(Feature):
    """The measured factors' innovations, in the measurement's order."""

    name = "innovation"

    def bind(self, group, measurement):
        if not measurement.factors:
            raise ValueError(
                "the innovation feature reads the measured factors' innovations, but the "
                "measurement names none; give its factors ({R: [0, 9], p: [9, 12]})."
            )
        self.width = measurement.innovation_dim
        return self

    def forward(self, view):
        if view.nu_flat is not None:
            return view.nu_flat
        return view.nu[0] if len(view.nu) == 1 else torch.cat(view.nu, dim=-1)


class Rotated(Feature):
    """Body-frame 3-vectors of ``(y, u)`` rotated to the world frame by an SO(3) factor's estimate.

    Args:
        vectors: ``{rotation factor: [(start, stop), ...]}``, each span 3 entries of ``(y, u)``.
    """

    name = "rotated"

    def __init__(self, vectors: dict):
        super().__init__()
        self.vectors = {
            str(k): _spans(f"rotated: vectors[{k!r}]", v) for k, v in dict(vectors or {}).items()
        }
        if not self.vectors:
            raise ValueError("rotated: name a rotation factor and its vectors' spans.")

    def settings(self):
        return {"vectors": {k: [list(s) for s in v] for k, v in self.vectors.items()}}

    def bind(self, group, measurement):
        width = measurement.dim + measurement.input_dim
        self._parts = []
        for fname, spans in self.vectors.items():
            check_factor("rotated: vectors", group, fname)
            if tuple(group.factor(fname).element_shape) != (3, 3):
                raise ValueError(
                    f"rotated: vectors[{fname!r}]: the factor must be a rotation of R^3 (elements "
                    f"(3, 3), SO(3)), got {group.factor(fname)!r}."
                )
            cols = []
            for a, b in spans:
                if not (0 <= a and b <= width and b - a == 3):
                    raise ValueError(
                        f"rotated: span ({a}, {b}) must be 3 entries of (y, u) (size {width}): a "
                        "body-frame 3-vector."
                    )
                cols.extend(range(a, b))
            self._parts.append((group.element_slice(fname), torch.tensor(cols)))
        self.width = 3 * sum(len(s) for s in self.vectors.values())
        return self

    def forward(self, view):
        out = []
        for xs, cols in self._parts:
            R = view.x[:, xs].unflatten(-1, (3, 3)).to(view.yu.dtype)
            vecs = view.yu[:, cols.to(view.yu.device)].unflatten(-1, (-1, 3))
            out.append((vecs @ R.transpose(-1, -2)).flatten(-2))
        return out[0] if len(out) == 1 else torch.cat(out, dim=-1)


class FramedInnovation(Feature):
    """Vector factors' innovations in rotation factors' estimated frames, ``Rhat^T nu_p``.

    Args:
        frames: ``{vector factor: rotation factor}``, e.g. ``{p: R}``; each vector factor a
            measured 3-vector, each rotation factor SO(3).
    """

    name = "framed_innovation"

    def __init__(self, frames: dict):
        super().__init__()
        frames = dict(frames or {})
        plain = all(isinstance(k, str) and isinstance(v, str) for k, v in frames.items())
        if not frames or not plain:
            raise ValueError(
                f"framed_innovation: frames must map vector factors to rotation factors, e.g. "
                f"{{p: R}}, got {frames!r}."
            )
        self.frames = frames

    def settings(self):
        return {"frames": dict(self.frames)}

    def bind(self, group, measurement):
        names = list(measurement.factors)
        self._frames = []
        for vec, rot in self.frames.items():
            for n in (vec, rot):
                check_factor("framed_innovation: frames", group, n)
            if vec not in measurement.factors or group.factor(vec).tangent_dim != 3:
                raise ValueError(
                    f"framed_innovation: {vec!r} must be a measured 3-vector factor (a span in the "
                    f"measurement's factors), got {group.factor(vec)!r}."
                )
            if tuple(group.factor(rot).element_shape) != (3, 3):
                raise ValueError(
                    f"framed_innovation: {rot!r} must be a rotation of R^3 (SO(3)), got "
                    f"{group.factor(rot)!r}."
                )
            self._frames.append((names.index(vec), group.element_slice(rot)))
        self.width = 3 * len(self._frames)
        return self

    def forward(self, view):
        out = [  # Rhat^T nu, as the row nu^T Rhat
            (view.nu[i].unsqueeze(-2) @ view.x[:, rs].unflatten(-1, (3, 3)).to(view.yu.dtype))
            .squeeze(-2)
            for i, rs in self._frames
        ]
        return out[0] if len(out) == 1 else torch.cat(out, dim=-1)


def reads_as_one(observer) -> bool:
    """Whether ``observer``'s step can read its features as one autograd node
    (:class:`~manifold_nets.observer.measurement.DeferredView`): they are the embedding (flat),
    the readings (nothing dropped) and the innovation, in that order, of a fusable measurement,
    and the plain head reads nothing else of the step. Decided once, when it is built."""
    from .heads import PlainHead
    from .measurement import Measurement

    return (
        [type(f) for f in observer.features] == [Embedding, Readings, Innovation]
        and observer.group.embedding_is_flat
        and all(f.keep is None for f in observer.features[:2])
        and type(observer.measurement) is Measurement  # (a robust one makes its own view)
        and observer.measurement._fused
        and type(observer.head) is PlainHead
    )
