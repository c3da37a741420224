"""SO(3) for the models of a multiplicative EKF, in few operations: ``exp(phi)`` and ``J_l(phi)``
together, and the coefficients they share.

A filter's time loop calls these every step on small batches, where the cost is the number of
torch operations, not the arithmetic. The groups' own ``SO3().exp``, ``left_jacobian`` and
:mod:`groups.numerics` compute each coefficient on its own (about a dozen operations each, for
autograd-safe values and gradients); here the five coefficients come from one evaluation
(:func:`so3_coefficients`), and ``exp`` and ``J_l`` from one product with them
(:func:`exp_and_left_jacobian`). The values are the same to rounding (tested against the groups'
functions); they are meant for the EKF's forward pass (``torch.no_grad``), not for autograd.

With ``t = |phi|``, ``K = [phi]x``::

    A = sin t / t,   B = (1 - cos t) / t^2,   C = (t - sin t) / t^3,
    B' = dB / d(t^2),   C' = dC / d(t^2),
    exp(phi) = I + A K + B K^2,      J_l(phi) = I + B K + C K^2,      J_r(phi) = J_l(phi)^T.

Up to ``t = 3.2`` (past pi, so every rotation vector of a logarithm and every turn of a step
the examples allow) the five come from their Taylor series in ``t^2`` to ``t^30``: one power and
one product for all five, the truncation below 1e-20 and the rounding within a few units of
1e-16 (the series alternate; the sum of their terms' sizes stays below 4 there). A batch with
a larger angle takes the closed forms for those (``1 - cos t`` as ``2 sin^2(t/2)``); under
``torch.compile`` both are computed and selected, with no data-dependent branch.
"""

from __future__ import annotations

import math

import torch

__all__ = ["exp_and_left_jacobian", "matmul", "so3_coefficients", "so3_log", "skew_matrix"]

_TERMS = 16  # series terms in t^2: t^0 .. t^30
_SERIES_LIMIT = 3.2**2  # t^2 up to which the series alone serves
_CACHE: dict = {}


def _series_table() -> list[list[float]]:
    """``(_TERMS, 5)``: the coefficient of ``t2^j`` in ``A, B, C, B', C'``."""
    f = math.factorial
    rows = []
    for j in range(_TERMS):
        s, s1 = (-1.0) ** j, (-1.0) ** (j + 1)
        rows.append([s / f(2 * j + 1), s / f(2 * j + 2), s / f(2 * j + 3),
                     s1 * (j + 1) / f(2 * j + 4), s1 * (j + 1) / f(2 * j + 5)])  # fmt: skip
    return rows


# closed forms as (basis (st, sh2, t, t st, t sh2)) @ _NUMERATOR / (t, t^2, t^3, t^4, t^5),
# st = sin t, sh2 = sin(t/2)^2:  A = st / t,  B = 2 sh2 / t^2,  C = (t - st) / t^3,
# B' = (t st - 4 sh2) / (2 t^4),  C' = (3 st - 2 t - t cos t) / (2 t^5) = (3 st - 3 t + 2 t sh2) / (2 t^5)
_NUMERATOR = [
    # A  B   C   B'   C'
    [1, 0, -1, 0, 1.5],  # st
    [0, 2, 0, -2, 0],  # sh2
    [0, 0, 1, 0, -1.5],  # t
    [0, 0, 0, 0.5, 0],  # t st
    [0, 0, 0, 0, 1],  # t sh2
]
# skew(phi) flattened row-major = phi @ _SKEW: (0, -z, y, z, 0, -x, -y, x, 0)
_SKEW = [
    [0, 0, 0, 0, 0, -1, 0, 1, 0],
    [0, 0, 1, 0, 0, 0, -1, 0, 0],
    [0, -1, 0, 1, 0, 0, 0, 0, 0],
]


# Shepperd's method (as groups.so3's): ten affine functions of vec R (plus the offset), the
# four diagonal ones 4 q_k^2 (k = w, x, y, z), then 4 w x, 4 w y, 4 w z, 4 x y, 4 x z, 4 y z
_SHEPPERD = [
    [1, 0, 0, 0, 1, 0, 0, 0, 1],
    [1, 0, 0, 0, -1, 0, 0, 0, -1],
    [-1, 0, 0, 0, 1, 0, 0, 0, -1],
    [-1, 0, 0, 0, -1, 0, 0, 0, 1],
    [0, 0, 0, 0, 0, -1, 0, 1, 0],
    [0, 0, 1, 0, 0, 0, -1, 0, 0],
    [0, -1, 0, 1, 0, 0, 0, 0, 0],
    [0, 1, 0, 1, 0, 0, 0, 0, 0],
    [0, 0, 1, 0, 0, 0, 1, 0, 0],
    [0, 0, 0, 0, 0, 1, 0, 1, 0],
]
# the candidate 4 q_k (w, x, y, z) for the pivot k, as indices into those ten
_CANDIDATES = [[0, 4, 5, 6], [4, 1, 7, 8], [5, 7, 2, 9], [6, 8, 9, 3]]


def _constants(dtype: torch.dtype, device) -> dict[str, torch.Tensor]:
    """The tables above as tensors, made once per dtype and device."""
    key = (dtype, device)
    c = _CACHE.get(key)
    if c is None:
        def t(v):
            return torch.tensor(v, dtype=dtype, device=device)

        c = {
            "series": t(_series_table()),
            "numerator": t(_NUMERATOR),
            "halves": t([1.0, 0.5]),
            "one_two": t([1.0, 2.0]),
            "t_powers": t([1.0, 2.0, 3.0, 4.0, 5.0]),
            "skew": t(_SKEW),
            "eye9": torch.eye(3, dtype=dtype, device=device).flatten(),
            "pick": torch.tensor([0, 1, 1, 2], device=device),
            "shepperd_t": t(_SHEPPERD).T.contiguous(),
            "shepperd_offset": t([1.0] * 4 + [0.0] * 6),
            "candidates": torch.tensor(_CANDIDATES, device=device),
        }
        _CACHE[key] = c
    return c


def matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b``, by ``torch.bmm`` where both are 3-D (less dispatch than ``@``: it counts in a
    filter's loop of small products)."""
    if a.dim() == 3 and b.dim() == 3:
        return torch.bmm(a, b)
    return a @ b


def so3_coefficients(t2: torch.Tensor) -> torch.Tensor:
    """``(A, B, C, B', C')`` ``(*batch, 5)`` of ``t2 = |phi|^2`` ``(*batch,)``; see the module."""
    c = _constants(t2.dtype, t2.device)
    flat = t2 if t2.dim() == 1 else t2.reshape(-1)
    series = torch.vander(flat, _TERMS, increasing=True) @ c["series"]  # (1, t2, ...) @ table
    if t2.dim() != 1:
        series = series.view(*t2.shape, 5)
    compiling = torch.compiler.is_compiling()  # a graph has no data-dependent branch
    if not compiling and (t2.numel() == 0 or float(t2.max()) <= _SERIES_LIMIT):
        return series
    large = t2 > _SERIES_LIMIT
    t = torch.where(large, t2, 1.0).sqrt().unsqueeze(-1)  # (*batch, 1), 1 on the series' side
    q = torch.sin(t * c["halves"]).pow(c["one_two"])  # (sin t, sin(t/2)^2)
    basis = torch.cat((q, t, q * t), -1)
    exact = (basis @ c["numerator"]) / t.pow(c["t_powers"])
    return torch.where(large.unsqueeze(-1), exact, series)


def skew_matrix(phi: torch.Tensor) -> torch.Tensor:
    """``[phi]x`` ``(*batch, 3, 3)`` from ``phi`` ``(*batch, 3)`` (one product, exact)."""
    return (phi @ _constants(phi.dtype, phi.device)["skew"]).unflatten(-1, (3, 3))


def exp_and_left_jacobian(
    phi: torch.Tensor, coefficients: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(exp(phi), J_l(phi), K, coefficients)`` for ``phi`` ``(*batch, 3)``: the two
    ``(*batch, 3, 3)`` matrices, ``K = [phi]x`` and :func:`so3_coefficients` of ``|phi|^2``
    (pass them if already computed). ``J_r(phi) = J_l(-phi) = J_l(phi)^T``."""
    c = _constants(phi.dtype, phi.device)
    if coefficients is None:
        coefficients = so3_coefficients((phi * phi).sum(-1))
    flat, coefficients_flat = phi, coefficients
    if phi.dim() != 2:
        flat, coefficients_flat = phi.reshape(-1, 3), coefficients.reshape(-1, 5)
    Kf = flat @ c["skew"]
    K = Kf.view(-1, 3, 3)
    basis = torch.stack((Kf, torch.bmm(K, K).view(-1, 9)), 1)  # (N, 2, 9)
    weights = coefficients_flat.index_select(-1, c["pick"]).view(-1, 2, 2)
    E, Jl = torch.baddbmm(c["eye9"], weights, basis).view(-1, 2, 3, 3).unbind(1)  # [[A, B], [B, C]]
    batch = phi.shape[:-1]
    if len(batch) != 1:
        E, Jl, K = (m.reshape(*batch, 3, 3) for m in (E, Jl, K))
    return E, Jl, K, coefficients


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """The rotation vector ``(*batch, 3)`` of rotations ``R`` ``(*batch, 3, 3)``, angle in
    ``[0, pi]``: ``SO3().log``'s method (Shepperd's largest pivot, then ``atan2``), in a fifth of
    its operations (the pivot by ``argmax``, the candidate by one ``gather``; for the forward
    pass only: no series branch, so no safe gradient at 0)."""
    c = _constants(R.dtype, R.device)
    f = torch.addmm(c["shepperd_offset"], R.reshape(-1, 9), c["shepperd_t"])  # (N, 10)
    pivot = f[:, :4].argmax(-1)
    q = f.gather(1, c["candidates"][pivot])  # (N, 4): 4 q_k (w, x, y, z), any sign
    w, v = q[:, 0], q[:, 1:]
    s, c = torch.linalg.vector_norm(v, dim=-1), w.abs()
    # atan2(s, c) / s is exact to rounding down to the smallest s; its limit 1 / c where s is 0
    # (or its square underflowed)
    k = torch.copysign(torch.where(s > 0, torch.atan2(s, c) / s, c.reciprocal()), w)
    return (k.unsqueeze(-1) * v).mul_(2.0).reshape(*R.shape[:-2], 3)  # angle = 2 atan2(s, c)
