"""The inputs of the axiom suite: hypothesis strategies and the deterministic adversarial grid.

Tangent vectors put an angle from Theseus' list (:data:`ADVERSARIAL_ANGLES`) or a uniform one on
every slice of ``group.angle_slices`` and scale the other coordinates by one of
:data:`MAGNITUDES`, so a small rotation with a large translation occurs; elements are
``group.random`` or ``exp`` of such vectors. :func:`tangent_vectors`, :func:`elements` and
:func:`batch_shapes` are public for your own property tests; :func:`grid_tangents` and
:func:`grid_elements` build the fixed batch of :data:`GRID_SIZE` every check runs on first.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from hypothesis import strategies as st

from ..base import LieGroup

__all__ = [
    "ADVERSARIAL_ANGLES",
    "MAGNITUDES",
    "BATCH_SHAPES",
    "GRID_SIZE",
    "batch_shapes",
    "seeds",
    "tangent_vectors",
    "elements",
    "grid_tangents",
    "grid_elements",
]

#: Rotation angles that break careless formulas (Theseus' list): the exact identity, angles below,
#: at and above the Taylor-branch thresholds, and the cut locus pi of the logarithm.
ADVERSARIAL_ANGLES = (0.0, 1e-8, 1e-5, 3e-3, 1e-2, math.pi - 1e-7, math.pi)
#: Scales of the non-angle tangent coordinates (translations, velocities, vector factors).
MAGNITUDES = (0.0, 1e-3, 1.0, 1e3)
#: The batch shapes ``check_group`` uses by default: unbatched, one element, and a 3-D batch.
BATCH_SHAPES = ((), (1,), (3, 1, 2))
#: Size of the deterministic adversarial batch every check runs once before hypothesis' examples.
GRID_SIZE = 2 * (len(ADVERSARIAL_ANGLES) + 2) * len(MAGNITUDES)

# How a drawn tensor picks its angles and magnitudes: one value for the whole batch (so a failing
# example names it), or "mixed": a value per element chosen by the seeded generator.
_ANGLE_MODES = ("mixed", *ADVERSARIAL_ANGLES, "uniform")


def batch_shapes(max_dims: int = 3, max_side: int = 3) -> st.SearchStrategy[tuple[int, ...]]:
    """Batch shapes: the defaults ``()``, ``(1,)``, ``(3, 1, 2)`` or small random ones."""
    small = st.lists(st.integers(1, max_side), max_size=max_dims).map(tuple)
    return st.one_of(st.sampled_from(BATCH_SHAPES), small)


def seeds() -> st.SearchStrategy[int]:
    """Seeds for a ``torch.Generator``: the drawn tensors are functions of a hypothesis draw."""
    return st.integers(0, 2**31 - 1)


def _angle_free_columns(group: LieGroup) -> torch.Tensor:
    """Boolean mask of the tangent coordinates outside every angle slice."""
    other = torch.ones(group.tangent_dim, dtype=torch.bool)
    for s in group.angle_slices:
        other[s] = False
    return other


def _make_tangents(
    group: LieGroup,
    n: int,
    dtype: torch.dtype,
    generator: torch.Generator,
    angle_mode: str | float,
    magnitude_mode: str | float,
    magnitudes: Sequence[float],
) -> torch.Tensor:
    """``(n, tangent_dim)`` tangent vectors; see :func:`tangent_vectors`."""
    f64 = torch.float64
    v = torch.randn(n, group.tangent_dim, generator=generator, dtype=f64)
    if magnitude_mode == "mixed":
        pick = torch.randint(len(magnitudes), (n,), generator=generator)
        mags = torch.tensor(tuple(magnitudes), dtype=f64)[pick]
    else:
        mags = torch.full((n,), float(magnitude_mode), dtype=f64)
    v[:, _angle_free_columns(group)] *= mags.unsqueeze(-1)
    table = torch.tensor(ADVERSARIAL_ANGLES, dtype=f64)
    for s in group.angle_slices:
        uniform = torch.rand(n, generator=generator, dtype=f64) * math.pi
        if angle_mode == "mixed":
            pick = torch.randint(len(table) + 1, (n,), generator=generator)
            theta = torch.where(pick < len(table), table[pick.clamp_max(len(table) - 1)], uniform)
        elif angle_mode == "uniform":
            theta = uniform
        else:
            theta = torch.full((n,), float(angle_mode), dtype=f64)
        block = v[:, s]
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
    generator = torch.Generator().manual_seed(draw(seeds(), label="seed"))
    angle_mode = draw(st.sampled_from(_ANGLE_MODES), label="angle") if group.angle_slices else 0
    magnitude_mode = draw(st.sampled_from(("mixed", *magnitudes)), label="magnitude")
    v = _make_tangents(
        group,
        n=math.prod(shape),
        dtype=dtype,
        generator=generator,
        angle_mode=angle_mode,
        magnitude_mode=magnitude_mode,
        magnitudes=magnitudes,
    )
    return v.reshape(*shape, group.tangent_dim)


def _make_elements(
    group: LieGroup,
    n: int,
    dtype: torch.dtype,
    generator: torch.Generator,
    use_exp: torch.Tensor,
    v: torch.Tensor | None,
) -> torch.Tensor:
    """``(n, *element_shape)``: ``group.random``, replaced by ``exp(v)`` where ``use_exp``."""
    x = group.random((n,), generator=generator, dtype=dtype)
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
    generator = torch.Generator().manual_seed(draw(seeds(), label="seed"))
    mode = draw(st.sampled_from(("random", "mixed", "exp")), label="elements")
    v, use_exp = None, torch.zeros(n, dtype=torch.bool)
    if mode != "random":
        v = draw(tangent_vectors(group, batch_shape=(n,), dtype=dtype, magnitudes=magnitudes))
        use_exp = torch.rand(n, generator=generator) < 0.5 if mode == "mixed" else ~use_exp
    x = _make_elements(group, n=n, dtype=dtype, generator=generator, use_exp=use_exp, v=v)
    return x.reshape(*shape, *group.element_shape)


def grid_tangents(
    group: LieGroup, dtype: torch.dtype, magnitudes: Sequence[float], roll: int
) -> torch.Tensor:
    """``(GRID_SIZE, tangent_dim)``: every adversarial angle (and two uniform ones) with every
    magnitude, once with oblique and once with axis-aligned rotation axes. ``roll`` varies the
    directions and the pairing between calls (so x, y and z of one property differ)."""
    f64 = torch.float64
    generator = torch.Generator().manual_seed(1000 + roll)
    angle_list = torch.tensor([*ADVERSARIAL_ANGLES, math.nan, math.nan], dtype=f64)  # nan: uniform
    mags_list = torch.tensor(tuple(magnitudes), dtype=f64)
    aligned, theta, mags = torch.cartesian_prod(
        torch.tensor([0.0, 1.0], dtype=f64), angle_list, mags_list
    ).unbind(-1)
    n = theta.shape[0]
    v = torch.randn(n, group.tangent_dim, generator=generator, dtype=f64)
    v[:, _angle_free_columns(group)] *= mags.unsqueeze(-1)
    for j, s in enumerate(group.angle_slices):
        th = theta.roll(j * (len(magnitudes) + 1))  # several angle slices: different angles
        th = torch.where(th.isnan(), torch.rand(n, generator=generator, dtype=f64) * math.pi, th)
        block = v[:, s]
        axis = torch.zeros_like(block)
        axis[:, 0] = 1.0
        block = torch.where(aligned.bool().unsqueeze(-1), axis, block)
        v[:, s] = block / torch.linalg.vector_norm(block, dim=-1, keepdim=True) * th[:, None]
    reps = -(-GRID_SIZE // n)
    return v.repeat(reps, 1)[:GRID_SIZE].roll(roll, 0).to(dtype)


def grid_elements(
    group: LieGroup, dtype: torch.dtype, magnitudes: Sequence[float], draw: int
) -> torch.Tensor:
    """``(GRID_SIZE, *element_shape)``: ``exp`` of :func:`grid_tangents` for two elements in
    three, ``group.random`` for the third. ``draw`` (1, 2, ...) makes each call of a property
    different."""
    v = grid_tangents(group, dtype=dtype, magnitudes=magnitudes, roll=7 * draw)
    use_exp = torch.arange(GRID_SIZE) % 3 != 2
    generator = torch.Generator().manual_seed(draw)
    return _make_elements(
        group, n=GRID_SIZE, dtype=dtype, generator=generator, use_exp=use_exp, v=v
    )
