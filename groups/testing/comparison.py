"""How the axiom suite compares: tolerances per dtype, the result of a check, and one case.

A :class:`Case` is one property being checked on one group, dtype and batch shape. It draws the
inputs (from hypothesis, or the deterministic grid of :mod:`groups.testing.strategies`), compares
actual with expected values and records the worst error in a :class:`CheckResult`; a comparison
that fails raises ``AssertionError`` naming the property, group, dtype, batch shape, the error
against its tolerance and the input where it occurred.

Errors are relative: an element's error is ``max |actual - expected| / scale`` (the difference
is the group's ``element_difference``, so a double cover compares ``q`` with ``-q`` as equal) with
``scale >= 1 + max |expected|`` (times the sizes of the factors where rounding is amplified,
e.g. ``|x| |x^-1|`` for ``x x^-1 = e``); tangent vectors are compared with the angle blocks and
the other coordinates scaled separately. All tolerances live in :data:`TOLERANCES`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from ..base import LieGroup
from .strategies import elements, grid_elements, grid_tangents, seeds, tangent_vectors

__all__ = [
    "Tolerances",
    "TOLERANCES",
    "tolerances_for",
    "CheckResult",
    "Case",
    "format_tensor",
    "magnitude",
    "element_magnitude",
]


@dataclass(frozen=True)
class Tolerances:
    """The tolerances of one dtype. Every comparison of ``check_group`` reads them from here."""

    #: Relative error of values: ``max |actual - expected| <= value * scale`` per element, with
    #: ``scale >= 1 + max |expected|``.
    value: float
    #: ``membership_error`` allowed on the output of an operation.
    member: float
    #: ``log(exp v) = v`` is only required where every angle is ``< pi - pi_margin``: the log is
    #: two-valued at pi, and rounding ``exp(v)`` can carry an angle within a few eps of pi across.
    pi_margin: float
    #: Extra tolerance ``near_pi * eps / (pi - angle)`` for ``log(exp v) = v`` near pi. 0 by
    #: default: on the group the log is well conditioned up to pi (``|J_r^-1| <= pi / 2``), and
    #: the shipped groups keep ~4 eps there, while a log through ``acos`` of the trace or an axis
    #: from ``(R - R^T) / (2 sin theta)`` loses ``eps / (pi - angle)``. Raise it to accept such
    #: a log knowingly.
    near_pi: float = 0.0


#: Tolerances per dtype, measured against the shipped groups' worst errors (which stay below a
#: tenth of these; see ``docs/groups.md``). float16/bfloat16 are not supported.
TOLERANCES: dict[torch.dtype, Tolerances] = {
    torch.float32: Tolerances(value=5e-6, member=1e-5, pi_margin=1e-5),
    torch.float64: Tolerances(value=1e-11, member=1e-12, pi_margin=1e-9),
}


def tolerances_for(dtype: torch.dtype) -> Tolerances:
    """``TOLERANCES[dtype]``; ValueError naming the supported dtypes for any other."""
    if dtype not in TOLERANCES:
        raise ValueError(
            f"groups.testing has tolerances for {sorted(map(str, TOLERANCES))}, not {dtype}."
        )
    return TOLERANCES[dtype]


@dataclass
class CheckResult:
    """The outcome of one property on one group, dtype and batch shape."""

    prop: str
    group: str
    dtype: torch.dtype
    batch_shape: tuple[int, ...]
    #: The largest error seen (in the units of the comparison that came closest to failing).
    worst_error: float = 0.0
    #: The largest ``error / tolerance`` seen; ``<= 1`` when the property holds.
    worst_ratio: float = 0.0
    #: Which comparison came closest to failing.
    worst_what: str = ""
    skipped: str = ""

    def __str__(self) -> str:
        where = f"{self.prop} {self.group} {self.dtype} {self.batch_shape}"
        if self.skipped:
            return f"{where}: skipped ({self.skipped})"
        return (
            f"{where}: worst error {self.worst_error:.3g} ({self.worst_ratio:.3g} of the "
            f"tolerance) in {self.worst_what}"
        )


# ---------------------------------------------------------------------------------- formatting


def format_tensor(t: torch.Tensor) -> str:
    """The first 16 entries of ``t``, flattened, to 9 significant digits (for messages)."""
    vals = t.detach().double().reshape(-1).tolist()
    head = ", ".join(f"{a:.9g}" for a in vals[:16])
    return "[" + head + (", ..." if len(vals) > 16 else "") + "]"


def _at(t: torch.Tensor, batch: torch.Size, index: tuple[int, ...]) -> torch.Tensor:
    """Element ``index`` of ``t`` whose leading dimensions broadcast to ``batch``."""
    nb = len(batch)
    lead = t.shape[: min(nb, t.dim())]
    if t.dim() < nb or tuple(lead) != tuple(batch):
        try:
            t = t.expand(*batch, *t.shape[nb:]) if t.dim() >= nb else t
        except RuntimeError:
            return t
    return t[index] if index else t


# ---------------------------------------------------------------------------------- error sizes


def _amax(d: torch.Tensor, trailing: int) -> torch.Tensor:
    """``max |d|`` over the last ``trailing`` dimensions (NaN if any entry is NaN)."""
    d = d.abs()
    if trailing == 0:
        return d
    flat = d.flatten(d.dim() - trailing)
    nan = torch.isnan(flat).any(-1)
    out = flat.amax(-1) if flat.shape[-1] else flat.sum(-1)
    return torch.where(nan, torch.nan, out)


def magnitude(t: torch.Tensor, trailing: int) -> torch.Tensor:
    """``1 + max |t|`` over the last ``trailing`` dimensions (in float64): a comparison's scale."""
    return 1.0 + _amax(t.detach().double(), trailing).nan_to_num(0.0)


def element_magnitude(group: LieGroup, x: torch.Tensor) -> torch.Tensor:
    """:func:`magnitude` of group elements ``x``, ``(*batch,)``."""
    return magnitude(x, len(group.element_shape))


def _tangent_blocks(group: LieGroup) -> list[torch.Tensor]:
    """Boolean column masks: one per angle slice, then one for all other coordinates."""
    blocks, other = [], torch.ones(group.tangent_dim, dtype=torch.bool)
    for s in group.angle_slices:
        m = torch.zeros(group.tangent_dim, dtype=torch.bool)
        m[s] = True
        other[s] = False
        blocks.append(m)
    return [*blocks, other]


# ---------------------------------------------------------------------------------- the case


@dataclass
class Case:
    """One property being checked on one group, dtype and batch shape: draws, compares, records.

    With ``grid=True`` the inputs are not drawn by hypothesis but are the deterministic
    adversarial batch of :func:`~groups.testing.strategies.grid_tangents` (batch shape
    ``(GRID_SIZE,)``). A property receives the case and ``data`` (hypothesis' ``st.data()``, or
    None on the grid) and passes ``data`` back to :meth:`x`, :meth:`v` and :meth:`seed`.
    """

    group: LieGroup
    dtype: torch.dtype
    batch_shape: tuple[int, ...]
    magnitudes: tuple[float, ...]
    result: CheckResult
    grid: bool = False
    device: torch.device | str = "cpu"
    tol: Tolerances = field(init=False)
    _draws: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self.tol = tolerances_for(self.dtype)
        self.device = torch.empty(0, device=self.device).device  # "cuda" -> "cuda:0"

    @property
    def eps(self) -> float:
        return torch.finfo(self.dtype).eps

    def header(self) -> str:
        where = (
            f"on the adversarial grid (batch shape {self.batch_shape})"
            if self.grid
            else f"with batch shape {self.batch_shape}"
        )
        return f"property '{self.result.prop}' fails for {self.group!r} in {self.dtype} {where}"

    def fail(self, msg: str) -> None:
        raise AssertionError(f"{self.header()}: {msg}")

    # -- drawing (hypothesis' data, or the grid when data is None)

    def _grid_take(self, t: torch.Tensor, batch_shape, trailing: tuple[int, ...]) -> torch.Tensor:
        if batch_shape is None:
            return t
        n = math.prod(batch_shape)
        return t[:n].reshape(*batch_shape, *trailing)

    def x(self, data, label: str, *, batch_shape=None) -> torch.Tensor:
        """Group elements of the case's batch shape (or ``batch_shape``), drawn as ``label``."""
        if data is None:
            self._draws += 1
            x = grid_elements(
                self.group, dtype=self.dtype, magnitudes=self.magnitudes, draw=self._draws
            )
            x = self._grid_take(x, batch_shape, tuple(self.group.element_shape))
            return x.to(self.device)
        bs = self.batch_shape if batch_shape is None else batch_shape
        drawn = elements(self.group, batch_shape=bs, dtype=self.dtype, magnitudes=self.magnitudes)
        return data.draw(drawn, label=label).to(self.device)

    def v(self, data, label: str, *, batch_shape=None) -> torch.Tensor:
        """Tangent vectors of the case's batch shape (or ``batch_shape``), drawn as ``label``."""
        if data is None:
            self._draws += 1
            v = grid_tangents(
                self.group, dtype=self.dtype, magnitudes=self.magnitudes, roll=5 * self._draws
            )
            return self._grid_take(v, batch_shape, (self.group.tangent_dim,)).to(self.device)
        bs = self.batch_shape if batch_shape is None else batch_shape
        drawn = tangent_vectors(
            self.group, batch_shape=bs, dtype=self.dtype, magnitudes=self.magnitudes
        )
        return data.draw(drawn, label=label).to(self.device)

    def seed(self, data, label: str) -> int:
        """A seed for a ``torch.Generator``, drawn as ``label``."""
        if data is None:
            self._draws += 1
            return self._draws
        return data.draw(seeds(), label=label)

    # -- shapes

    def shape(self, what: str, t: torch.Tensor, trailing: tuple[int, ...], *, batch=None) -> None:
        """Requires ``t`` to be a tensor of shape ``(*batch, *trailing)`` in the case's dtype, on
        the case's device (``batch`` defaults to the case's batch shape)."""
        want = (*(self.batch_shape if batch is None else batch), *trailing)
        if not isinstance(t, torch.Tensor):
            self.fail(f"{what} returned {type(t).__name__}, not a torch.Tensor")
        if tuple(t.shape) != want or t.dtype != self.dtype:
            self.fail(
                f"{what} has shape {tuple(t.shape)} and dtype {t.dtype}; expected shape {want} "
                f"and dtype {self.dtype}"
            )
        if t.device != self.device:
            self.fail(
                f"{what} is on {t.device}, its inputs on {self.device}: build constants on the "
                "input's device (torch.zeros(..., dtype=x.dtype, device=x.device))"
            )

    # -- comparisons

    def finite(
        self,
        what: str,
        t: torch.Tensor,
        trailing: int,
        *,
        inputs: dict[str, torch.Tensor] | None = None,
    ) -> None:
        """Requires every entry of ``t`` to be finite; else fails with ``what``, the first batch
        index holding NaN or Inf (``trailing``: the number of non-batch dimensions of ``t``)
        and the inputs there."""
        bad = ~torch.isfinite(t.detach())
        if trailing:
            bad = bad.flatten(-trailing).any(-1)
        if not bool(bad.any()):
            return
        i = int(bad.reshape(-1).nonzero()[0])
        n = int(bad.sum())
        self._fail_at(
            lambda index: f"{what} at batch index {index} ({n} of {bad.numel()} element(s))",
            bad.shape, i, inputs,
        )

    def _fail_at(self, headline, batch: torch.Size, i: int, inputs) -> None:
        """Fails with ``headline(index)`` for the flat position ``i`` in ``batch``, followed by
        every input's value at that batch index."""
        index = tuple(int(j) for j in torch.unravel_index(torch.tensor(i), batch)) if batch else ()
        lines = [headline(index)]
        for name, x in (inputs or {}).items():
            lines.append(f"    {name}[{index}] = {format_tensor(_at(x, batch, index))}")
        self.fail("\n".join(lines))

    def within(
        self,
        what: str,
        err: torch.Tensor,
        tol: torch.Tensor | float,
        *,
        inputs: dict[str, torch.Tensor] | None = None,
        unit: str = "",
    ) -> None:
        """Requires ``err <= tol`` per batch element (``err`` and ``tol`` broadcast; NaN fails)."""
        err = err.detach().double()
        tol_t = torch.as_tensor(tol, dtype=torch.float64, device=err.device).expand_as(err)
        if err.numel() == 0:
            return
        # err / tol, with a zero tolerance meaning "err <= 0" and NaN counting as infinitely bad
        zero_tol = torch.where(err <= 0, 0.0, torch.inf)
        ratio = torch.where(tol_t > 0, err / tol_t.clamp_min(1e-300), zero_tol)
        ratio = torch.where(torch.isnan(ratio), torch.inf, ratio).reshape(-1)
        i = int(ratio.argmax())
        worst_ratio = float(ratio[i])
        worst_err = float(err.reshape(-1)[i])
        if worst_ratio > self.result.worst_ratio or not self.result.worst_what:
            self.result.worst_ratio = max(worst_ratio, self.result.worst_ratio)
            self.result.worst_error = worst_err
            self.result.worst_what = what
        if not worst_ratio <= 1.0:
            tol_i = float(tol_t.reshape(-1)[i])
            self._fail_at(
                lambda index: f"{what}: worst error {worst_err:.3g}{unit} > tolerance "
                f"{tol_i:.3g} at batch index {index}",
                err.shape, i, inputs,
            )

    def close(
        self,
        what: str,
        actual: torch.Tensor,
        expected: torch.Tensor,
        *,
        trailing: int,
        scale: torch.Tensor | float = 1.0,
        inputs: dict[str, torch.Tensor] | None = None,
    ) -> None:
        """Relative closeness per batch element: ``max |a - e| / (scale * (1 + max |e|))`` within
        ``tol.value``. ``trailing`` is the number of non-batch dimensions of ``expected``."""
        if tuple(actual.shape) != tuple(expected.shape):
            self.fail(f"{what}: shape {tuple(actual.shape)} != expected {tuple(expected.shape)}")
        a, e = actual.detach().double(), expected.detach().double()
        err = _amax(a - e, trailing) / (magnitude(e, trailing) * scale)
        self.within(what, err, self.tol.value, inputs=inputs, unit=" (relative)")

    def close_elements(
        self,
        what: str,
        actual: torch.Tensor,
        expected: torch.Tensor,
        *,
        scale: torch.Tensor | float = 1.0,
        inputs: dict[str, torch.Tensor] | None = None,
    ) -> None:
        """:meth:`close` for group elements: the difference is the group's
        ``element_difference(actual, expected)``, so a group with several tensors per element
        (unit quaternions, ``q`` and ``-q``) is compared as a group, not entry by entry."""
        if tuple(actual.shape) != tuple(expected.shape):
            self.fail(f"{what}: shape {tuple(actual.shape)} != expected {tuple(expected.shape)}")
        a, e = actual.detach().double(), expected.detach().double()
        ne = len(self.group.element_shape)
        diff = self.group.element_difference(a, e)
        if tuple(diff.shape) != tuple(e.shape):
            self.fail(
                f"element_difference returned shape {tuple(diff.shape)}; expected "
                f"{tuple(e.shape)}, the shape of its arguments"
            )
        err = _amax(diff, ne) / (magnitude(e, ne) * scale)
        self.within(what, err, self.tol.value, inputs=inputs, unit=" (relative)")

    def close_tangent(
        self,
        what: str,
        actual: torch.Tensor,
        expected: torch.Tensor,
        *,
        scale: torch.Tensor | float = 1.0,
        tol: torch.Tensor | float | None = None,
        inputs: dict[str, torch.Tensor] | None = None,
    ) -> None:
        """Like :meth:`close` for tangent vectors, with the angle blocks and the other coordinates
        scaled separately (a large translation must not hide an error in a rotation angle);
        ``tol`` defaults to ``tol.value``."""
        if tuple(actual.shape) != tuple(expected.shape):
            self.fail(f"{what}: shape {tuple(actual.shape)} != expected {tuple(expected.shape)}")
        a, e = actual.detach().double(), expected.detach().double()
        errs = []
        for cols in _tangent_blocks(self.group):
            if cols.any():
                cols = cols.to(a.device)
                errs.append(_amax(a[..., cols] - e[..., cols], 1) / magnitude(e[..., cols], 1))
        err = torch.stack(errs, -1).amax(-1) / scale
        tol = self.tol.value if tol is None else tol
        self.within(what, err, tol, inputs=inputs, unit=" (relative)")
