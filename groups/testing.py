"""Property-based axiom checks for any :class:`~groups.LieGroup`: ``check_group(MyGroup())``.

The suite every shipped group passes, packaged so that a user's own group gets it with one line::

    from groups.testing import check_group
    check_group(MyGroup())   # raises AssertionError naming the property, dtype, batch shape, error

It checks, in float32 and float64 and over several batch shapes: membership and shapes after every
operation; the identity, inverse and associativity laws; ``exp(log x) = x`` and ``log(exp v) = v``
inside the injectivity radius; ``exp`` against ``torch.linalg.matrix_exp(hat(v))`` for matrix
groups; ``x exp(v) x^-1 = exp(Ad_x v)``; the embedding round trip and ``from_embedding`` rejecting
points off the group; ``rplus``/``rminus`` consistency; finite gradients, also at rotation angles
of exactly 0 and pi; ``torch.autograd.gradcheck`` in float64; batched results equal to per-element
results; broadcasting of batch dimensions. Each check is also a public function
(``check_exp_log``, ``check_adjoint``, ...) with the same arguments, so one property can be run
alone, and the hypothesis strategies (:func:`tangent_vectors`, :func:`elements`,
:func:`batch_shapes`) are public for your own property tests.

Inputs are adversarial on purpose: on every slice in ``group.angle_slices`` the rotation angle is
taken from Theseus' list (0, 1e-8, 1e-5, 3e-3, 1e-2, pi - 1e-7, pi) or uniformly from (0, pi), and
the other tangent coordinates are scaled by a magnitude from (0, 1e-3, 1, 1e3), so a small
rotation with a large translation is tried. Every check runs first, deterministically, on one
batch holding every angle with every magnitude (with oblique and axis-aligned rotation axes),
then on hypothesis-drawn examples of the requested batch shape. Errors are relative: an
element's error is ``max |actual - expected| / scale`` with ``scale >= 1 + max |expected|``
(times the sizes of the factors where rounding is amplified, e.g. ``|x| |x^-1|`` for
``x x^-1 = e``); all tolerances live in :data:`TOLERANCES`.

hypothesis is a *dev* dependency (``pip install -e '.[dev]'``). It is imported here and only
here: ``import groups`` never imports this module, so the library itself runs without it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import torch

try:
    import hypothesis
    from hypothesis import strategies as st
except ImportError as _err:  # pragma: no cover - depends on the environment
    raise ImportError(
        "groups.testing needs hypothesis, a dev dependency of manifold_nets: install it with "
        "`pip install -e '.[dev]'` or `pip install 'hypothesis>=6.100'`."
    ) from _err

from .base import GroupMembershipError, LieGroup, MatrixLieGroup

__all__ = [
    "ADVERSARIAL_ANGLES",
    "MAGNITUDES",
    "BATCH_SHAPES",
    "DEFAULT_MAX_EXAMPLES",
    "GRID_SIZE",
    "TOLERANCES",
    "Tolerances",
    "CheckResult",
    "batch_shapes",
    "tangent_vectors",
    "elements",
    "check_group",
    "CHECKS",
    "check_membership",
    "check_identity",
    "check_inverse",
    "check_associativity",
    "check_exp_log",
    "check_log_exp",
    "check_matrix_exp",
    "check_adjoint",
    "check_embedding",
    "check_rplus_rminus",
    "check_gradients_finite",
    "check_gradcheck",
    "check_batched_vs_looped",
    "check_broadcasting",
]

#: Rotation angles that break careless formulas (Theseus' list): the exact identity, angles below,
#: at and above the Taylor-branch thresholds, and the cut locus pi of the logarithm.
ADVERSARIAL_ANGLES = (0.0, 1e-8, 1e-5, 3e-3, 1e-2, math.pi - 1e-7, math.pi)
#: Scales of the non-angle tangent coordinates (translations, velocities, vector factors).
MAGNITUDES = (0.0, 1e-3, 1.0, 1e3)
#: The batch shapes ``check_group`` uses by default: unbatched, one element, and a 3-D batch.
BATCH_SHAPES = ((), (1,), (3, 1, 2))
#: Examples per property, dtype and batch shape drawn by hypothesis in ``check_group``.
DEFAULT_MAX_EXAMPLES = 6


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


def _tol(dtype: torch.dtype) -> Tolerances:
    if dtype not in TOLERANCES:
        raise ValueError(
            f"groups.testing has tolerances for {sorted(map(str, TOLERANCES))}, not {dtype}."
        )
    return TOLERANCES[dtype]


# ---------------------------------------------------------------------------------- strategies


def batch_shapes(max_dims: int = 3, max_side: int = 3) -> st.SearchStrategy[tuple[int, ...]]:
    """Batch shapes: the defaults ``()``, ``(1,)``, ``(3, 1, 2)`` or small random ones."""
    small = st.lists(st.integers(1, max_side), max_size=max_dims).map(tuple)
    return st.one_of(st.sampled_from(BATCH_SHAPES), small)


def _seed() -> st.SearchStrategy[int]:
    return st.integers(0, 2**31 - 1)


# How a drawn tensor picks its angles and magnitudes: one value for the whole batch (so a failing
# example names it), or "mixed": a value per element chosen by the seeded generator.
_ANGLE_MODES = ("mixed", *ADVERSARIAL_ANGLES, "uniform")


def _make_tangents(
    group: LieGroup,
    n: int,
    dtype: torch.dtype,
    gen: torch.Generator,
    angle_mode: str | float,
    mag_mode: str | float,
    magnitudes: Sequence[float],
    axis_aligned: bool = False,
) -> torch.Tensor:
    """``(n, tangent_dim)`` tangent vectors; see :func:`tangent_vectors`."""
    f64 = torch.float64
    v = torch.randn(n, group.tangent_dim, generator=gen, dtype=f64)
    other = torch.ones(group.tangent_dim, dtype=torch.bool)
    for s in group.angle_slices:
        other[s] = False
    if mag_mode == "mixed":
        pick = torch.randint(len(magnitudes), (n,), generator=gen)
        mags = torch.tensor(tuple(magnitudes), dtype=f64)[pick]
    else:
        mags = torch.full((n,), float(mag_mode), dtype=f64)
    v[:, other] *= mags.unsqueeze(-1)
    table = torch.tensor(ADVERSARIAL_ANGLES, dtype=f64)
    for s in group.angle_slices:
        uniform = torch.rand(n, generator=gen, dtype=f64) * math.pi
        if angle_mode == "mixed":
            pick = torch.randint(len(table) + 1, (n,), generator=gen)
            theta = torch.where(pick < len(table), table[pick.clamp_max(len(table) - 1)], uniform)
        elif angle_mode == "uniform":
            theta = uniform
        else:
            theta = torch.full((n,), float(angle_mode), dtype=f64)
        block = v[:, s]
        if axis_aligned:
            block = torch.zeros_like(block)
            block[:, 0] = 1.0
        v[:, s] = block / torch.linalg.vector_norm(block, dim=-1, keepdim=True) * theta[:, None]
    return v.to(dtype)


@st.composite
def tangent_vectors(
    draw,
    group: LieGroup,
    batch_shape: Sequence[int] = (),
    dtype: torch.dtype = torch.float64,
    magnitudes: Sequence[float] = MAGNITUDES,
) -> torch.Tensor:
    """Tangent vectors ``(*batch_shape, tangent_dim)`` with adversarial angles and magnitudes.

    A Gaussian direction from a hypothesis-drawn seed; for each slice in ``group.angle_slices``
    the block is rescaled to an angle that is either one value for the whole batch, drawn from
    :data:`ADVERSARIAL_ANGLES` (0, 1e-8, 1e-5, 3e-3, 1e-2, pi - 1e-7, pi) or uniform in (0, pi),
    or ("mixed") chosen per element among those. The other coordinates are multiplied by one of
    ``magnitudes`` (again one for the batch, or mixed per element), so small rotations with
    large translations occur. Built in float64 and rounded to ``dtype`` (so ``pi`` in float32 is
    the float32 number nearest to pi, which is slightly larger than pi).
    """
    shape = tuple(batch_shape)
    gen = torch.Generator().manual_seed(draw(_seed(), label="seed"))
    angle_mode = draw(st.sampled_from(_ANGLE_MODES), label="angle") if group.angle_slices else 0
    mag_mode = draw(st.sampled_from(("mixed", *magnitudes)), label="magnitude")
    v = _make_tangents(group, math.prod(shape), dtype, gen, angle_mode, mag_mode, magnitudes)
    return v.reshape(*shape, group.tangent_dim)


def _make_elements(
    group: LieGroup, n: int, dtype: torch.dtype, gen: torch.Generator, use_exp: torch.Tensor,
    v: torch.Tensor | None,
) -> torch.Tensor:
    x = group.random((n,), generator=gen, dtype=dtype)
    if v is not None:
        mask = use_exp.view(n, *([1] * len(group.element_shape)))
        x = torch.where(mask, group.exp(v), x)
    return x


@st.composite
def elements(
    draw,
    group: LieGroup,
    batch_shape: Sequence[int] = (),
    dtype: torch.dtype = torch.float64,
    magnitudes: Sequence[float] = MAGNITUDES,
) -> torch.Tensor:
    """Group elements ``(*batch_shape, *element_shape)``.

    ``group.random`` with a hypothesis-drawn seed (through a ``torch.Generator``), computed in
    ``dtype``; in some examples some or all elements are replaced by ``exp`` of adversarial
    tangent vectors from :func:`tangent_vectors` (angle 0 or pi, a large translation, ...).
    """
    shape = tuple(batch_shape)
    n = math.prod(shape)
    gen = torch.Generator().manual_seed(draw(_seed(), label="seed"))
    mode = draw(st.sampled_from(("random", "mixed", "exp")), label="elements")
    v, use_exp = None, torch.zeros(n, dtype=torch.bool)
    if mode != "random":
        v = draw(tangent_vectors(group, (n,), dtype, magnitudes))
        use_exp = torch.rand(n, generator=gen) < 0.5 if mode == "mixed" else ~use_exp
    x = _make_elements(group, n, dtype, gen, use_exp, v)
    return x.reshape(*shape, *group.element_shape)


#: Size of the deterministic adversarial batch every check runs once before hypothesis' examples.
GRID_SIZE = 2 * (len(ADVERSARIAL_ANGLES) + 2) * len(MAGNITUDES)


def _grid_tangents(
    group: LieGroup, dtype: torch.dtype, magnitudes: Sequence[float], roll: int
) -> torch.Tensor:
    """``(GRID_SIZE, tangent_dim)``: every adversarial angle (and two uniform ones) with every
    magnitude, once with oblique and once with axis-aligned rotation axes. ``roll`` varies the
    directions and the pairing between calls (so x, y and z of one property differ)."""
    f64 = torch.float64
    gen = torch.Generator().manual_seed(1000 + roll)
    angle_list = torch.tensor([*ADVERSARIAL_ANGLES, math.nan, math.nan], dtype=f64)  # nan: uniform
    mags_list = torch.tensor(tuple(magnitudes), dtype=f64)
    aligned, theta, mags = torch.cartesian_prod(
        torch.tensor([0.0, 1.0], dtype=f64), angle_list, mags_list
    ).unbind(-1)
    n = theta.shape[0]
    v = torch.randn(n, group.tangent_dim, generator=gen, dtype=f64)
    other = torch.ones(group.tangent_dim, dtype=torch.bool)
    for s in group.angle_slices:
        other[s] = False
    v[:, other] *= mags.unsqueeze(-1)
    for j, s in enumerate(group.angle_slices):
        th = theta.roll(j * (len(magnitudes) + 1))  # several angle slices: different angles
        th = torch.where(th.isnan(), torch.rand(n, generator=gen, dtype=f64) * math.pi, th)
        block = v[:, s]
        axis = torch.zeros_like(block)
        axis[:, 0] = 1.0
        block = torch.where(aligned.bool().unsqueeze(-1), axis, block)
        v[:, s] = block / torch.linalg.vector_norm(block, dim=-1, keepdim=True) * th[:, None]
    reps = -(-GRID_SIZE // n)
    return v.repeat(reps, 1)[:GRID_SIZE].roll(roll, 0).to(dtype)


# ---------------------------------------------------------------------------------- the case


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


def _fmt(t: torch.Tensor) -> str:
    vals = t.detach().double().reshape(-1).tolist()
    head = ", ".join(f"{a:.9g}" for a in vals[:16])
    return "[" + head + (", ..." if len(vals) > 16 else "") + "]"


@dataclass
class _Case:
    """One property being checked on one group, dtype and batch shape: draws, compares, records.

    With ``grid=True`` the inputs are not drawn by hypothesis but are the deterministic
    adversarial batch of :func:`_grid_tangents` (batch shape ``(GRID_SIZE,)``).
    """

    group: LieGroup
    dtype: torch.dtype
    batch_shape: tuple[int, ...]
    magnitudes: tuple[float, ...]
    result: CheckResult
    grid: bool = False
    tol: Tolerances = field(init=False)
    _draws: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self.tol = _tol(self.dtype)

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

    def x(self, data, label: str, batch_shape=None) -> torch.Tensor:
        if data is None:
            self._draws += 1
            v = _grid_tangents(self.group, self.dtype, self.magnitudes, 7 * self._draws)
            gen = torch.Generator().manual_seed(self._draws)
            use_exp = torch.arange(GRID_SIZE) % 3 != 2
            x = _make_elements(self.group, GRID_SIZE, self.dtype, gen, use_exp, v)
            return self._grid_take(x, batch_shape, tuple(self.group.element_shape))
        bs = self.batch_shape if batch_shape is None else batch_shape
        return data.draw(elements(self.group, bs, self.dtype, self.magnitudes), label=label)

    def v(self, data, label: str, batch_shape=None) -> torch.Tensor:
        if data is None:
            self._draws += 1
            v = _grid_tangents(self.group, self.dtype, self.magnitudes, 5 * self._draws)
            return self._grid_take(v, batch_shape, (self.group.tangent_dim,))
        bs = self.batch_shape if batch_shape is None else batch_shape
        return data.draw(tangent_vectors(self.group, bs, self.dtype, self.magnitudes), label=label)

    def seed(self, data, label: str) -> int:
        if data is None:
            self._draws += 1
            return self._draws
        return data.draw(_seed(), label=label)

    # -- shapes
    def shape(self, what: str, t: torch.Tensor, trailing: tuple[int, ...], batch=None) -> None:
        want = (*(self.batch_shape if batch is None else batch), *trailing)
        if not isinstance(t, torch.Tensor):
            self.fail(f"{what} returned {type(t).__name__}, not a torch.Tensor")
        if tuple(t.shape) != want or t.dtype != self.dtype:
            self.fail(
                f"{what} has shape {tuple(t.shape)} and dtype {t.dtype}; expected shape {want} "
                f"and dtype {self.dtype}"
            )

    # -- comparisons
    def within(
        self,
        what: str,
        err: torch.Tensor,
        tol: torch.Tensor | float,
        inputs: dict[str, torch.Tensor] | None = None,
        unit: str = "",
    ) -> None:
        """Requires ``err <= tol`` per batch element (``err`` and ``tol`` broadcast; NaN fails)."""
        err = err.detach().double()
        tol_t = torch.as_tensor(tol, dtype=torch.float64).expand_as(err)
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
            index = tuple(int(j) for j in torch.unravel_index(torch.tensor(i), err.shape)) if (
                err.dim()
            ) else ()
            lines = [
                f"{what}: worst error {worst_err:.3g}{unit} > tolerance "
                f"{float(tol_t.reshape(-1)[i]):.3g} at batch index {index}"
            ]
            for name, t in (inputs or {}).items():
                lines.append(f"    {name}[{index}] = {_fmt(_at(t, err.shape, index))}")
            self.fail("\n".join(lines))

    def close(
        self,
        what: str,
        actual: torch.Tensor,
        expected: torch.Tensor,
        trailing: int,
        scale: torch.Tensor | float = 1.0,
        tol: torch.Tensor | float | None = None,
        inputs: dict[str, torch.Tensor] | None = None,
    ) -> None:
        """Relative closeness per batch element: ``max |a - e| / (scale * (1 + max |e|))``.

        ``trailing`` is the number of non-batch dimensions of ``expected``.
        """
        if tuple(actual.shape) != tuple(expected.shape):
            self.fail(f"{what}: shape {tuple(actual.shape)} != expected {tuple(expected.shape)}")
        a, e = actual.detach().double(), expected.detach().double()
        err = _amax(a - e, trailing) / (_mag(e, trailing) * scale)
        self.within(what, err, self.tol.value if tol is None else tol, inputs, " (relative)")

    def close_tangent(
        self,
        what: str,
        actual: torch.Tensor,
        expected: torch.Tensor,
        scale: torch.Tensor | float = 1.0,
        tol: torch.Tensor | float | None = None,
        inputs: dict[str, torch.Tensor] | None = None,
    ) -> None:
        """Like :meth:`close` for tangent vectors, with the angle blocks and the other coordinates
        scaled separately (a large translation must not hide an error in a rotation angle)."""
        if tuple(actual.shape) != tuple(expected.shape):
            self.fail(f"{what}: shape {tuple(actual.shape)} != expected {tuple(expected.shape)}")
        a, e = actual.detach().double(), expected.detach().double()
        errs = []
        for cols in _tangent_blocks(self.group):
            if cols.any():
                errs.append(_amax(a[..., cols] - e[..., cols], 1) / _mag(e[..., cols], 1))
        err = torch.stack(errs, -1).amax(-1) / scale
        self.within(what, err, self.tol.value if tol is None else tol, inputs, " (relative)")


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


def _amax(d: torch.Tensor, trailing: int) -> torch.Tensor:
    """``max |d|`` over the last ``trailing`` dimensions (NaN if any entry is NaN)."""
    d = d.abs()
    if trailing == 0:
        return d
    flat = d.flatten(d.dim() - trailing)
    nan = torch.isnan(flat).any(-1)
    out = flat.amax(-1) if flat.shape[-1] else flat.sum(-1)
    return torch.where(nan, torch.nan, out)


def _mag(t: torch.Tensor, trailing: int) -> torch.Tensor:
    """``1 + max |t|`` over the last ``trailing`` dimensions (in float64)."""
    return 1.0 + _amax(t.detach().double(), trailing).nan_to_num(0.0)


def _tangent_blocks(group: LieGroup) -> list[torch.Tensor]:
    """Boolean column masks: one per angle slice, then one for all other coordinates."""
    blocks, other = [], torch.ones(group.tangent_dim, dtype=torch.bool)
    for s in group.angle_slices:
        m = torch.zeros(group.tangent_dim, dtype=torch.bool)
        m[s] = True
        other[s] = False
        blocks.append(m)
    return [*blocks, other]


def _max_angle(group: LieGroup, v: torch.Tensor) -> torch.Tensor:
    """The largest rotation angle of each tangent vector, ``(*batch,)`` in float64 (0 if none)."""
    v = v.detach().double()
    if not group.angle_slices:
        return v.new_zeros(v.shape[:-1])
    norms = [torch.linalg.vector_norm(v[..., s], dim=-1) for s in group.angle_slices]
    return torch.stack(norms, -1).amax(-1)


def _elem_mag(group: LieGroup, x: torch.Tensor) -> torch.Tensor:
    return _mag(x, len(group.element_shape))


def _matvec(m: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return (m @ v.unsqueeze(-1)).squeeze(-1)


# ---------------------------------------------------------------------------------- properties
#
# Each property is ``_prop_*(case, data)``: ``data`` is hypothesis' ``st.data()`` (or None for the
# deterministic checks). Element trailing dims: ``ne = len(group.element_shape)``.


def _prop_membership(c: _Case, data) -> None:
    G, dt, bs, k = c.group, c.dtype, c.batch_shape, c.group.tangent_dim
    x, y, v = c.x(data, "x"), c.x(data, "y"), c.v(data, "v")
    gen = torch.Generator().manual_seed(c.seed(data, "random seed"))
    saved = {"x": x.clone(), "y": y.clone(), "v": v.clone()}
    el = tuple(G.element_shape)
    # name -> (operation, trailing shape of its output, is the output a group element?)
    ops: dict[str, tuple[Callable[[], torch.Tensor], tuple[int, ...], bool]] = {
        "identity(batch_shape)": (lambda: G.identity(bs, dtype=dt), el, True),
        "compose(x, y)": (lambda: G.compose(x, y), el, True),
        "inverse(x)": (lambda: G.inverse(x), el, True),
        "exp(v)": (lambda: G.exp(v), el, True),
        "rplus(x, v)": (lambda: G.rplus(x, v), el, True),
        "random(batch_shape)": (lambda: G.random(bs, generator=gen, dtype=dt), el, True),
        "log(x)": (lambda: G.log(x), (k,), False),
        "rminus(y, x)": (lambda: G.rminus(y, x), (k,), False),
        "between(x, y)": (lambda: G.between(x, y), el, True),
        "embed(x)": (lambda: G.embed(x), (G.embedding_dim,), False),
        "adjoint(x)": (lambda: G.adjoint(x), (k, k), False),
        "distance(x, y)": (lambda: G.distance(x, y), (), False),
    }
    for name, (op, trailing, is_element) in ops.items():
        out = op()
        for arg, before in saved.items():
            now = {"x": x, "y": y, "v": v}[arg]
            if not torch.equal(before, now):
                c.fail(f"{name} modified its input {arg} in place")
        c.shape(name, out, trailing)
        if is_element:
            err = G.membership_error(out)
            c.shape(f"membership_error({name})", err, ())
            c.within(f"membership_error({name})", err, c.tol.member, {"x": x, "y": y, "v": v})


def _prop_identity(c: _Case, data) -> None:
    G, dt, bs, ne = c.group, c.dtype, c.batch_shape, len(c.group.element_shape)
    x = c.x(data, "x")
    e = G.identity(bs, dtype=dt)
    zero = torch.zeros(*bs, G.tangent_dim, dtype=dt)
    c.close("compose(identity, x) == x", G.compose(e, x), x, ne, inputs={"x": x})
    c.close("compose(x, identity) == x", G.compose(x, e), x, ne, inputs={"x": x})
    c.close("inverse(identity) == identity", G.inverse(e), e, ne)
    c.close("exp(0) == identity", G.exp(zero), e, ne)
    c.close_tangent("log(identity) == 0", G.log(e), zero)
    c.close_tangent(
        "rminus(x, x) == 0", G.rminus(x, x), zero, _elem_mag(G, x) ** 2, inputs={"x": x}
    )


def _prop_inverse(c: _Case, data) -> None:
    G, dt, bs, ne = c.group, c.dtype, c.batch_shape, len(c.group.element_shape)
    x, y = c.x(data, "x"), c.x(data, "y")
    e = G.identity(bs, dtype=dt)
    xi, yi = G.inverse(x), G.inverse(y)
    s = _elem_mag(G, x) * _elem_mag(G, xi)
    ins = {"x": x}
    c.close("compose(x, inverse(x)) == identity", G.compose(x, xi), e, ne, s, inputs=ins)
    c.close("compose(inverse(x), x) == identity", G.compose(xi, x), e, ne, s, inputs=ins)
    c.close("inverse(inverse(x)) == x", G.inverse(xi), x, ne, s, inputs=ins)
    s2 = s * _elem_mag(G, y) * _elem_mag(G, yi)
    c.close(
        "inverse(compose(x, y)) == compose(inverse(y), inverse(x))",
        G.inverse(G.compose(x, y)), G.compose(yi, xi), ne, s2, inputs={"x": x, "y": y},
    )  # fmt: skip


def _prop_associativity(c: _Case, data) -> None:
    G, ne = c.group, len(c.group.element_shape)
    x, y, z = c.x(data, "x"), c.x(data, "y"), c.x(data, "z")
    s = _elem_mag(G, x) * _elem_mag(G, y) * _elem_mag(G, z)
    c.close(
        "compose(compose(x, y), z) == compose(x, compose(y, z))",
        G.compose(G.compose(x, y), z), G.compose(x, G.compose(y, z)), ne, s,
        inputs={"x": x, "y": y, "z": z},
    )  # fmt: skip


def _prop_exp_log(c: _Case, data) -> None:
    G, ne = c.group, len(c.group.element_shape)
    x = c.x(data, "x")
    c.close("exp(log(x)) == x", G.exp(G.log(x)), x, ne, inputs={"x": x, "log(x)": G.log(x)})


def _log_exp_tolerance(c: _Case, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(mask, tol)``: where ``log(exp v) = v`` is required, and the tolerance grown near pi."""
    theta = _max_angle(c.group, v)
    gap = math.pi - theta
    mask = gap > c.tol.pi_margin
    gap = torch.where(mask, gap, torch.ones_like(gap))
    return mask, c.tol.value + c.tol.near_pi * c.eps / gap


def _prop_log_exp(c: _Case, data) -> None:
    G = c.group
    v = c.v(data, "v")
    mask, tol = _log_exp_tolerance(c, v)
    got = G.log(G.exp(v))
    got = torch.where(mask.unsqueeze(-1), got, v)  # elements at the cut locus are not compared
    c.close_tangent("log(exp(v)) == v (angles < pi - margin)", got, v, tol=tol, inputs={"v": v})
    # At and beyond the margin the log may pick the other branch, but it must stay on the group.
    c.close(
        "exp(log(exp(v))) == exp(v)", G.exp(G.log(G.exp(v))), G.exp(v), len(G.element_shape),
        inputs={"v": v},
    )  # fmt: skip


def _matrix_exp_reference(a: torch.Tensor) -> torch.Tensor:
    """``torch.linalg.matrix_exp`` of ``(*batch, d, d)``, always called on a batch of >= 2.

    torch's unbatched path (a single matrix) picks a degree-8 Taylor polynomial with a wrong
    coefficient for norms around 0.01-0.1 (errors up to 2e-10 in float64, 5e-5 in float32 in
    torch 2.13; pytorch/pytorch#196592). Padding the batch with a zero matrix takes the accurate
    batched path.
    """
    d = a.shape[-1]
    flat = a.reshape(-1, d, d)
    padded = torch.cat((flat, flat.new_zeros(1, d, d)))
    return torch.linalg.matrix_exp(padded)[:-1].reshape(a.shape)


def _prop_matrix_exp(c: _Case, data) -> None:
    G = c.group
    if not isinstance(G, MatrixLieGroup):
        c.result.skipped = "not a MatrixLieGroup"
        return
    v = c.v(data, "v")
    v64 = v.double()
    ref = _matrix_exp_reference(G.hat(v64))
    c.shape("hat(v)", G.hat(v), G.element_shape)
    c.close(f"exp(v) in {c.dtype} == matrix_exp(hat(v)) in float64", G.exp(v), ref, 2,
            inputs={"v": v})
    c.close_tangent("vee(hat(v)) == v", G.vee(G.hat(v)), v, inputs={"v": v})


def _prop_adjoint(c: _Case, data) -> None:
    G, ne, k = c.group, len(c.group.element_shape), c.group.tangent_dim
    x, y, v = c.x(data, "x"), c.x(data, "y"), c.v(data, "v")
    ad_x = G.adjoint(x)
    c.shape("adjoint(x)", ad_x, (k, k))
    xi, ev = G.inverse(x), G.exp(v)
    lhs = G.compose(G.compose(x, ev), xi)
    rhs = G.exp(_matvec(ad_x, v))
    s = _elem_mag(G, x) * _elem_mag(G, xi) * _elem_mag(G, ev)
    c.close("compose(x, exp(v), inverse(x)) == exp(adjoint(x) v)", rhs, lhs, ne, s,
            inputs={"x": x, "v": v})
    ad_y = G.adjoint(y)
    sa = _mag(ad_x, 2) * _mag(ad_y, 2)
    c.close("adjoint(compose(x, y)) == adjoint(x) adjoint(y)", G.adjoint(G.compose(x, y)),
            ad_x @ ad_y, 2, sa, inputs={"x": x, "y": y})
    eye = torch.eye(k, dtype=c.dtype).expand_as(ad_x)
    c.close("adjoint(x) adjoint(inverse(x)) == I", ad_x @ G.adjoint(xi), eye, 2,
            _mag(ad_x, 2) * _mag(G.adjoint(xi), 2), inputs={"x": x})


def _prop_embedding(c: _Case, data) -> None:
    G, ne = c.group, len(c.group.element_shape)
    x = c.x(data, "x")
    z = G.embed(x)
    c.shape("embed(x)", z, (G.embedding_dim,))
    c.close("unembed(embed(x)) == x", G.unembed(z), x, ne, inputs={"x": x})
    try:
        back = G.from_embedding(z)
    except GroupMembershipError as err:
        c.fail(f"from_embedding(embed(x)) rejected an element of the group: {err}")
    c.close("from_embedding(embed(x)) == x", back, x, ne, inputs={"x": x})
    c.close("embed(unembed(embed(x))) == embed(x)", G.embed(G.unembed(z)), z, 1)
    # Off the group: NaN in one element, and (where the image is a proper submanifold, i.e.
    # embedding_dim > tangent_dim) a random push out of it.
    bad = z.clone().reshape(-1, G.embedding_dim)
    bad[0, 0] = torch.nan
    off = {"NaN in the first element": bad.reshape(z.shape)}
    if G.embedding_dim > G.tangent_dim:
        gen = torch.Generator().manual_seed(c.seed(data, "push seed"))
        push = torch.randn(z.shape, generator=gen, dtype=torch.float64).to(c.dtype)
        off["a random push off the group"] = z + 0.5 * push * (1 + z.abs())
    for what, zb in off.items():
        try:
            G.from_embedding(zb)
        except GroupMembershipError:
            continue
        except Exception as err:  # noqa: BLE001 - the wrong exception type is the failure
            c.fail(
                f"from_embedding with {what} raised {type(err).__name__}, expected "
                f"GroupMembershipError: {err}"
            )
        c.fail(
            f"from_embedding accepted an embedding with {what}; expected GroupMembershipError "
            f"(membership_error {_fmt(G.membership_error(G.unembed(zb)))})"
        )


def _prop_rplus_rminus(c: _Case, data) -> None:
    G, ne = c.group, len(c.group.element_shape)
    x, y, v = c.x(data, "x"), c.x(data, "y"), c.v(data, "v")
    xi = G.inverse(x)
    sx = _elem_mag(G, x) * _elem_mag(G, xi)
    ins = {"x": x, "y": y}
    c.close("rplus(x, v) == compose(x, exp(v))", G.rplus(x, v), G.compose(x, G.exp(v)), ne,
            sx, inputs={"x": x, "v": v})
    c.close("between(x, y) == compose(inverse(x), y)", G.between(x, y), G.compose(xi, y), ne,
            sx, inputs=ins)
    d = G.rminus(y, x)
    c.close("rplus(x, rminus(y, x)) == y", G.rplus(x, d), y, ne, sx * _elem_mag(G, y), inputs=ins)
    mask, tol = _log_exp_tolerance(c, v)
    got = torch.where(mask.unsqueeze(-1), G.rminus(G.rplus(x, v), x), v)
    c.close_tangent("rminus(rplus(x, v), x) == v (angles < pi - margin)", got, v, sx, tol,
                    inputs={"x": x, "v": v})
    dist = G.distance(x, y)
    c.shape("distance(x, y)", dist, ())
    c.within("distance(x, y) >= 0", -dist, 0.0, ins)
    c.close("distance(x, y) == |rminus(y, x)|", dist, torch.linalg.vector_norm(d, dim=-1), 0,
            inputs=ins)


def _prop_gradients_finite(c: _Case, data) -> None:
    G = c.group
    x = c.x(data, "x")
    for where, v in {"v": c.v(data, "v")}.items():
        fns: dict[str, Callable[..., torch.Tensor]] = {
            "sum(exp(v))": lambda x_, v_: G.exp(v_).sum(),
            "sum(log(exp(v)))": lambda x_, v_: G.log(G.exp(v_)).sum(),
            "sum(embed(rplus(x, v)))": lambda x_, v_: G.embed(G.rplus(x_, v_)).sum(),
        }
        for name, fn in fns.items():
            xr = x.detach().clone().requires_grad_(True)
            vr = v.detach().clone().requires_grad_(True)
            out = fn(xr, vr)
            gx, gv = torch.autograd.grad(out, (xr, vr), allow_unused=True)
            for wrt, g in (("v", gv), ("x", gx)):
                if g is None:
                    continue
                bad = ~torch.isfinite(g)
                if bad.any():
                    nb = len(c.batch_shape)
                    first = tuple(int(i) for i in bad.nonzero()[0][:nb])
                    c.fail(
                        f"the gradient of {name} with respect to {wrt} has {int(bad.sum())} "
                        f"non-finite entries; the first at batch index {first}: "
                        f"v = {_fmt(v[first])}, x = {_fmt(x[first])}, grad = {_fmt(g[first])}"
                    )
    c.result.worst_what = "all gradients finite"


def _prop_gradcheck(c: _Case, data) -> None:
    """gradcheck in float64 at generic points (angles in [0.2, pi - 0.2], other coordinates ~1)."""
    G, bs = c.group, c.batch_shape
    if c.dtype != torch.float64:
        c.result.skipped = "gradcheck runs in float64 only"
        return
    gen = torch.Generator().manual_seed(1234)
    n = math.prod(bs)
    v = torch.randn(n, G.tangent_dim, generator=gen, dtype=torch.float64)
    for s in G.angle_slices:
        theta = 0.2 + (math.pi - 0.4) * torch.rand(n, 1, generator=gen, dtype=torch.float64)
        v[:, s] = v[:, s] / torch.linalg.vector_norm(v[:, s], dim=-1, keepdim=True) * theta
    v = v.reshape(*bs, G.tangent_dim).requires_grad_(True)
    x = G.random(bs, generator=gen, dtype=torch.float64).requires_grad_(True)
    checks = {
        "exp(v)": (lambda v_: G.exp(v_), (v,)),
        "log(exp(v))": (lambda v_: G.log(G.exp(v_)), (v,)),
        "embed(rplus(x, v))": (lambda x_, v_: G.embed(G.rplus(x_, v_)), (x, v)),
    }
    first = tuple(0 for _ in bs)
    for name, (fn, args) in checks.items():
        # the full Jacobian of one element, and a random projection (fast mode) of the batch
        runs = [(tuple(a[first].detach().requires_grad_(True) for a in args), False)]
        if n > 1:
            runs.append((args, True))
        for inputs, fast in runs:
            try:
                torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5,
                                         fast_mode=fast)
            except torch.autograd.gradcheck.GradcheckError as err:
                c.fail(f"torch.autograd.gradcheck of {name} at v = {_fmt(inputs[-1])}:\n{err}")
    c.result.worst_what = "gradcheck passed (eps 1e-6, atol 1e-6, rtol 1e-5)"


def _prop_batched_vs_looped(c: _Case, data) -> None:
    G, bs = c.group, c.batch_shape
    x, y, v = c.x(data, "x"), c.x(data, "y"), c.v(data, "v")
    ne = len(G.element_shape)
    ops: dict[str, tuple[Callable[..., torch.Tensor], int]] = {
        "compose(x, y)": (lambda x_, y_, v_: G.compose(x_, y_), ne),
        "inverse(x)": (lambda x_, y_, v_: G.inverse(x_), ne),
        "exp(v)": (lambda x_, y_, v_: G.exp(v_), ne),
        "log(x)": (lambda x_, y_, v_: G.log(x_), 1),
        "rplus(x, v)": (lambda x_, y_, v_: G.rplus(x_, v_), ne),
        "rminus(y, x)": (lambda x_, y_, v_: G.rminus(y_, x_), 1),
        "embed(x)": (lambda x_, y_, v_: G.embed(x_), 1),
        "adjoint(x)": (lambda x_, y_, v_: G.adjoint(x_), 2),
    }
    n = math.prod(bs)
    xs = x.reshape(n, *G.element_shape)
    ys = y.reshape(n, *G.element_shape)
    vs = v.reshape(n, G.tangent_dim)
    # every element of a drawn batch; 12 spread-out elements of the (large) grid
    idx = list(range(n)) if not c.grid else list(range(0, n, max(1, n // 12)))
    s = (_elem_mag(G, x) * _elem_mag(G, y) * _mag(v, 1)).reshape(n)[idx]
    for name, (fn, trailing) in ops.items():
        batched = fn(x, y, v)
        looped = torch.stack([fn(xs[i], ys[i], vs[i]) for i in idx])
        picked = batched.reshape(n, *batched.shape[len(bs):])[idx]
        c.close(f"batched {name} == per-element {name}", picked, looped, trailing, s,
                inputs={"x": xs[idx], "y": ys[idx], "v": vs[idx]})


def _prop_broadcasting(c: _Case, data) -> None:
    G, ne = c.group, len(c.group.element_shape)
    el = tuple(G.element_shape)
    x = c.x(data, "x (3, 1)", (3, 1))
    y = c.x(data, "y (1, 2)", (1, 2))
    v = c.v(data, "v (1, 2)", (1, 2))
    xe, ye, ve = x.expand(3, 2, *el), y.expand(3, 2, *el), v.expand(3, 2, G.tangent_dim)
    s = _elem_mag(G, xe) * _elem_mag(G, ye)
    out = G.compose(x, y)
    c.shape("compose(x (3, 1), y (1, 2))", out, el, batch=(3, 2))
    c.close("compose broadcast (3, 1) x (1, 2)", out, G.compose(xe, ye), ne, s)
    out = G.rplus(x, v)
    c.shape("rplus(x (3, 1), v (1, 2))", out, el, batch=(3, 2))
    c.close("rplus broadcast (3, 1) x (1, 2)", out, G.rplus(xe, ve), ne, s * _mag(ve, 1))
    # an unbatched element against a batch of the case's shape
    x0, yb = c.x(data, "x ()", ()), c.x(data, "y")
    out = G.compose(x0, yb)
    c.shape("compose(x (), y batch)", out, el)
    x0e = x0.expand(*c.batch_shape, *el)
    c.close("compose broadcast () x batch", out, G.compose(x0e, yb), ne,
            _elem_mag(G, x0e) * _elem_mag(G, yb))


# ---------------------------------------------------------------------------------- runners

#: name -> (property, drawn by hypothesis?)
_PROPERTIES: dict[str, tuple[Callable[[_Case, object], None], bool]] = {
    "membership": (_prop_membership, True),
    "identity": (_prop_identity, True),
    "inverse": (_prop_inverse, True),
    "associativity": (_prop_associativity, True),
    "exp_log": (_prop_exp_log, True),
    "log_exp": (_prop_log_exp, True),
    "matrix_exp": (_prop_matrix_exp, True),
    "adjoint": (_prop_adjoint, True),
    "embedding": (_prop_embedding, True),
    "rplus_rminus": (_prop_rplus_rminus, True),
    "gradients_finite": (_prop_gradients_finite, True),
    "gradcheck": (_prop_gradcheck, False),
    "batched_vs_looped": (_prop_batched_vs_looped, True),
    "broadcasting": (_prop_broadcasting, True),
}


def _run(
    prop: str,
    group: LieGroup,
    dtype: torch.dtype = torch.float64,
    batch_shape: Sequence[int] = (),
    max_examples: int = DEFAULT_MAX_EXAMPLES,
    magnitudes: Sequence[float] = MAGNITUDES,
    derandomize: bool = True,
    grid: bool = True,
) -> CheckResult:
    if not isinstance(group, LieGroup):
        raise TypeError(f"check_{prop} needs a LieGroup instance, got {group!r}.")
    bs = tuple(int(b) for b in batch_shape)
    result = CheckResult(prop, repr(group), dtype, bs)
    body, drawn = _PROPERTIES[prop]

    def once(case: _Case, data) -> None:
        try:
            body(case, data)
        except AssertionError:
            raise
        except Exception as err:  # a crash inside the group is a failure of this property
            raise AssertionError(f"{case.header()}: raised {type(err).__name__}: {err}") from err

    if not drawn:
        once(_Case(group, dtype, bs, tuple(magnitudes), result), None)
        return result
    if grid:
        once(_Case(group, dtype, (GRID_SIZE,), tuple(magnitudes), result, grid=True), None)
    if max_examples > 0:
        case = _Case(group, dtype, bs, tuple(magnitudes), result)
        run = hypothesis.settings(
            max_examples=max_examples,
            deadline=None,
            derandomize=derandomize,
            database=None,
            print_blob=False,
            # no shrinking: the message already shows the failing element, and shrinking a
            # failure of several properties costs tens of seconds
            phases=(hypothesis.Phase.explicit, hypothesis.Phase.reuse, hypothesis.Phase.generate),
            suppress_health_check=[
                hypothesis.HealthCheck.too_slow,
                hypothesis.HealthCheck.data_too_large,
                hypothesis.HealthCheck.large_base_example,
            ],
        )(hypothesis.given(st.data())(lambda data: once(case, data)))
        run()
    return result


def _make_check(prop: str, doc: str) -> Callable[..., CheckResult]:
    def check(
        group: LieGroup,
        dtype: torch.dtype = torch.float64,
        batch_shape: Sequence[int] = (),
        max_examples: int = DEFAULT_MAX_EXAMPLES,
        magnitudes: Sequence[float] = MAGNITUDES,
        derandomize: bool = True,
        grid: bool = True,
    ) -> CheckResult:
        return _run(prop, group, dtype, batch_shape, max_examples, magnitudes, derandomize, grid)

    check.__name__ = check.__qualname__ = f"check_{prop}"
    check.__doc__ = (
        f"{doc}\n\n"
        "Runs in one ``dtype``: first (if ``grid``) once on the deterministic adversarial batch "
        "of ``GRID_SIZE`` elements (every adversarial angle with every magnitude), then on "
        "``max_examples`` hypothesis examples of shape ``batch_shape`` (derandomized by default, "
        "so CI is reproducible). Raises AssertionError naming the property, group, dtype, batch "
        "shape, the worst error and the input where it occurred; returns a :class:`CheckResult`."
    )
    return check


check_membership = _make_check(
    "membership",
    "Outputs of identity, compose, inverse, exp, rplus and random are on the group (within "
    "``TOLERANCES[dtype].member``), every output has its documented shape and dtype, and no "
    "operation modifies its inputs.",
)
check_identity = _make_check(
    "identity",
    "``e x = x e = x``, ``e^-1 = e``, ``exp(0) = e``, ``log(e) = 0``, ``rminus(x, x) = 0``.",
)
check_inverse = _make_check(
    "inverse", "``x x^-1 = x^-1 x = e``, ``(x^-1)^-1 = x``, ``(x y)^-1 = y^-1 x^-1``."
)
check_associativity = _make_check("associativity", "``(x y) z = x (y z)``.")
check_exp_log = _make_check("exp_log", "``exp(log(x)) = x`` for every element, angle pi included.")
check_log_exp = _make_check(
    "log_exp",
    "``log(exp(v)) = v`` where every angle is below ``pi - pi_margin`` (tolerance grown by "
    "``near_pi * eps / (pi - angle)``), and ``exp(log(exp(v))) = exp(v)`` everywhere.",
)
check_matrix_exp = _make_check(
    "matrix_exp",
    "For a :class:`MatrixLieGroup`: ``exp(v)`` (in ``dtype``) against "
    "``torch.linalg.matrix_exp(hat(v))`` in float64, and ``vee(hat(v)) = v``. Skipped otherwise.",
)
check_adjoint = _make_check(
    "adjoint",
    "``x exp(v) x^-1 = exp(Ad_x v)``, ``Ad_{xy} = Ad_x Ad_y`` and ``Ad_x Ad_{x^-1} = I``.",
)
check_embedding = _make_check(
    "embedding",
    "``unembed(embed(x)) = x``, ``from_embedding(embed(x)) = x``, and ``from_embedding`` raises "
    "GroupMembershipError for NaN and (if ``embedding_dim > tangent_dim``) off the group.",
)
check_rplus_rminus = _make_check(
    "rplus_rminus",
    "``rplus = compose(x, exp(v))``, ``between``, ``rplus(x, rminus(y, x)) = y``, "
    "``rminus(rplus(x, v), x) = v`` inside the injectivity radius, and ``distance``.",
)
check_gradients_finite = _make_check(
    "gradients_finite",
    "No NaN/Inf in the gradients of ``sum(exp(v))``, ``sum(log(exp(v)))`` and "
    "``sum(embed(rplus(x, v)))``, at drawn points and at angles of exactly 0 and pi.",
)
check_gradcheck = _make_check(
    "gradcheck",
    "``torch.autograd.gradcheck`` of ``exp``, ``log(exp(v))`` and ``embed(rplus(x, v))`` at "
    "generic points in float64 (skipped for other dtypes).",
)
check_batched_vs_looped = _make_check(
    "batched_vs_looped",
    "Batched compose, inverse, exp, log, rplus, rminus, embed and adjoint equal the per-element "
    "results.",
)
check_broadcasting = _make_check(
    "broadcasting",
    "compose and rplus broadcast batch shapes (3, 1) with (1, 2), and () with ``batch_shape``.",
)

#: Every check of :func:`check_group`, by property name.
CHECKS: dict[str, Callable[..., CheckResult]] = {
    name: globals()[f"check_{name}"] for name in _PROPERTIES
}


def check_group(
    group: LieGroup,
    dtypes: Iterable[torch.dtype] = (torch.float32, torch.float64),
    batch_shapes: Iterable[Sequence[int]] = BATCH_SHAPES,
    max_examples: int = DEFAULT_MAX_EXAMPLES,
    magnitudes: Sequence[float] = MAGNITUDES,
    checks: Iterable[str] | None = None,
    derandomize: bool = True,
) -> list[CheckResult]:
    """Runs every axiom check on ``group`` for each dtype and batch shape.

    Args:
        group: the group to check, e.g. ``MyGroup()``.
        dtypes: floating dtypes to run in (tolerances from :data:`TOLERANCES`).
        batch_shapes: batch shapes of the drawn elements and tangent vectors.
        max_examples: hypothesis examples per property, dtype and batch shape.
        magnitudes: scales of the non-angle tangent coordinates; lower the largest one for a
            group whose ``exp`` grows exponentially (e.g. positive reals under multiplication).
        checks: names from :data:`CHECKS` to run (default: all).
        derandomize: fixed hypothesis examples (reproducible); False explores new ones each run.

    Returns:
        One :class:`CheckResult` per property, dtype and batch shape (worst errors seen).

    Raises:
        AssertionError: listing every failing property with its group, dtype, batch shape, the
            worst error and the input where it occurred.
    """
    names = list(CHECKS) if checks is None else list(checks)
    unknown = [n for n in names if n not in CHECKS]
    if unknown:
        raise ValueError(f"unknown checks {unknown}; choose from {list(CHECKS)}.")
    results, failures = [], {}
    for dtype in dtypes:
        for i, bs in enumerate(batch_shapes):
            for name in names:
                if (name, dtype) in failures:  # one failure per property and dtype is enough
                    continue
                try:
                    results.append(
                        CHECKS[name](
                            group, dtype, bs, max_examples, magnitudes, derandomize, grid=i == 0
                        )
                    )
                except AssertionError as err:
                    failures[name, dtype] = str(err)
    if failures:
        raise AssertionError(
            f"check_group({group!r}): {len(failures)} check(s) failed.\n"
            + "\n".join(f"- {f}" for f in failures.values())
        )
    return results
