"""SO(3), the group of 3D rotations, as ``(*batch, 3, 3)`` rotation matrices.

Tangent vectors are rotation vectors ``w`` (axis times angle, ``(*batch, 3)``), with
``hat(w) @ u = w x u``. The embedding is the row-major ``vec R`` in ``R^9``.

``exp`` is Rodrigues' formula written entrywise; ``log`` goes through a unit quaternion chosen by
the largest pivot (Shepperd's method) and ``atan2``, so it is accurate up to and at ``theta = pi``
(no ``acos`` of the trace) and its gradient is finite everywhere.
"""

from __future__ import annotations

import math

import torch

from . import numerics as nx
from . import so3_kernels as kernels
from .base import MatrixLieGroup

__all__ = ["SO3", "skew", "unskew", "left_jacobian", "left_jacobian_inverse"]


def skew(w: torch.Tensor) -> torch.Tensor:
    """``(*batch, 3) -> (*batch, 3, 3)``, the matrix with ``skew(w) @ u == cross(w, u)``."""
    x, y, z = w.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((o, -z, y, z, o, -x, -y, x, o), dim=-1).unflatten(-1, (3, 3))


def unskew(m: torch.Tensor) -> torch.Tensor:
    """``(*batch, 3, 3) -> (*batch, 3)``, the inverse of ``skew`` (reads the antisymmetric part)."""
    return 0.5 * torch.stack(
        (m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]),
        dim=-1,
    )


def _quadratic_form(w: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """``I + b K + c K^2`` with ``K = skew(w)``, for per-batch scalars ``b, c`` (``(*batch,)``).

    ``K^2 = w w^T - |w|^2 I``. The diagonal ``1 - c (|w|^2 - w_i^2)`` is rounded once, next to 1,
    not through a rounded ``1 - c |w|^2`` (a systematic error that float32 chains accumulate).
    """
    sq = w * w
    outer = (c.unsqueeze(-1) * w).unsqueeze(-1) * w.unsqueeze(-2)
    diag = 1.0 - c.unsqueeze(-1) * (sq.sum(-1, keepdim=True) - sq)
    on_diagonal = torch.eye(3, dtype=torch.bool, device=w.device)
    return torch.where(on_diagonal, torch.diag_embed(diag), outer + skew(b.unsqueeze(-1) * w))


def left_jacobian(w: torch.Tensor) -> torch.Tensor:
    """The left Jacobian ``J_l(w) = I + B K + C K^2`` of SO(3), ``(*batch, 3) -> (*batch, 3, 3)``.

    ``int_0^1 exp(s K) ds`` with ``K = skew(w)``: the V matrix of SE(3)'s exponential and the
    factor that maps a body velocity held over a step into the displacement.
    """
    t2 = (w * w).sum(-1)
    b = nx.one_minus_cos_over_t2(t2)
    c = nx.t_minus_sin_over_t3(t2)
    return _quadratic_form(w, b, c)


def left_jacobian_inverse(w: torch.Tensor) -> torch.Tensor:
    """``J_l(w)^-1 = I - K/2 + D K^2``, finite on the whole log domain ``|w| <= pi``."""
    t2 = (w * w).sum(-1)
    d = nx.inv_left_jacobian_coeff(t2)
    return _quadratic_form(w, torch.full_like(t2, -0.5), d)


def _quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion ``(w, x, y, z)`` to rotation matrix."""
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    m = (
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    )  # fmt: skip
    return torch.stack(m, dim=-1).unflatten(-1, (3, 3))


class SO3(MatrixLieGroup):
    """Rotations of R^3 as ``(*batch, 3, 3)`` matrices; tangent: rotation vectors ``(*batch, 3)``."""

    matrix_dim = 3
    tangent_dim = 3
    embedding_dim = 9
    embedding_is_flat = True
    angle_slices = (slice(0, 3),)

    @staticmethod
    def exp_max_norm(dtype: torch.dtype) -> float:
        """The bound on ``|v|`` from which :meth:`exp` takes the angle as a whole number of
        turns (its square overflows): ``sqrt(finfo(dtype).max)``."""
        return math.sqrt(torch.finfo(dtype).max)

    def hat(self, v: torch.Tensor) -> torch.Tensor:
        self.check_tangent(v, "hat")
        return skew(v)

    def vee(self, m: torch.Tensor) -> torch.Tensor:
        self.check_element(m, "vee")
        return unskew(m)

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "inverse")
        return x.transpose(-1, -2)

    def exp(self, v: torch.Tensor) -> torch.Tensor:
        """Rodrigues: ``R = I + sinc(t) K + (1 - cos t) / t^2 K^2``, ``K = hat(v)``, ``t = |v|``.

        The diagonal ``1 - c (v_j^2 + v_k^2)`` is rounded once, next to 1, not through a rounded
        ``cos t``: with a fixed step size that rounding error is the same at every step, and
        float32 chains ``R <- R exp(v)`` (1000 steps of norm 0.1) ended ten times further off
        the group through it (``benchmarks/bench_so3.py``).

        Domain (no value checks here: ``exp`` runs in the observer's exported rollout): NaN in
        any entry of ``v`` gives NaN in its matrix (NaN in, NaN out, never an error; so does
        an infinite entry). A finite angle whose square overflows, ``|v| >=
        sqrt(finfo(dtype).max)`` (about 1.8e19 in float32, 1.3e154 in float64;
        ``SO3.exp_max_norm(dtype)``), is taken as a whole number of turns: the result is the
        identity (the float spacing there is beyond ``2 pi`` by many orders, so the angle
        modulo ``2 pi`` is not in the input), and the gradient is 0. Every finite input gives a
        rotation. Check data from outside with ``torch.isfinite`` or :meth:`check_member`.

        Layout, for speed on the CPU: the batch is transposed into rows ``x, y, z`` of length
        ``N`` once, the nine terms are computed row by row, and ``R`` is assembled by one
        matrix product with a table of 0 and +-1: each entry of ``R`` is a sum of at most two
        nonzero terms, so the product rounds it once, like the plain sum. While autograd records,
        it is one node with an analytic backward (:mod:`groups.so3_kernels`).
        """
        self.check_tangent(v, "exp")
        return kernels.exp(v)

    def log(self, x: torch.Tensor) -> torch.Tensor:
        """Rotation vector with angle in ``[0, pi]``, through a quaternion and ``atan2``.

        ``2 atan2(s, |w|) / s * sign(w) (x, y, z)`` with ``s = |(x, y, z)|``: the quaternion
        ``(w, x, y, z)`` of Shepperd's method may be any nonzero multiple of the unit one (atan2
        and the ratio do not see the scale), and the sign picks the one with ``w >= 0``.
        The sign is taken from ``1 / w`` (the sign bit of ``w``, as ``copysign`` would), so the
        logarithm exports with ``torch.export`` and to ONNX.

        ``x`` must be a rotation. The logarithm of anything else (a reflection, ``det = -1``; a
        non-orthogonal matrix) is undefined: it returns some finite vector without an error (no
        value checks in this hot path; a reflection such as ``diag(1, 1, -1)`` gives 0). Data
        from outside goes through :meth:`from_embedding` or :meth:`check_member`, which raise
        :class:`~groups.GroupMembershipError` for such input and name the determinant.
        """
        self.check_element(x, "log")
        return kernels.log(x)

    def rplus(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """``x exp(v)``; one fused operation (one autograd node) when the batch shapes agree."""
        self.check_element(x, "rplus")
        self.check_tangent(v, "rplus")
        if x.shape[:-2] != v.shape[:-1] or x.dtype != v.dtype:
            return super().rplus(x, v)
        return kernels.rplus(x, v)

    def rminus(self, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log(x^T y)``; one fused operation (one autograd node) when the batch shapes agree."""
        if y.shape != x.shape:
            return super().rminus(y, x)
        self.check_pair(x, y, "rminus")
        return kernels.rminus(y, x)

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "embed")
        return x.flatten(-2)

    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        self.check_shape(z, (9,), "unembed", "an embedded element")
        return z.unflatten(-1, (3, 3))

    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """``max(||R R^T - I||_F, |det R - 1|)`` (the determinant catches reflections)."""
        self.check_element(x, "membership_error")
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        orth = torch.linalg.matrix_norm(x @ x.transpose(-1, -2) - eye)
        return torch.maximum(orth, (torch.linalg.det(x) - 1).abs())

    def _membership_detail(self, x: torch.Tensor, err: torch.Tensor) -> str:
        worst = x.reshape(-1, 3, 3)[int(err.reshape(-1).argmax())]
        det = float(torch.linalg.det(worst))
        what = " (a reflection: log and exp are undefined for it)" if det < 0 else ""
        return f" The worst has det {det:.3g}{what}."

    def adjoint(self, x: torch.Tensor) -> torch.Tensor:
        """``Ad_R = R`` for rotation vectors."""
        self.check_element(x, "adjoint")
        return x

    def random(self, batch_shape=(), generator=None, dtype=torch.float32, device=None):
        """Uniform (Haar) rotations, from normalised Gaussian quaternions."""
        self.check_dtype(dtype, "random")
        q = torch.randn(*batch_shape, 4, generator=generator, dtype=dtype, device=device)
        return _quaternion_to_matrix(q / torch.linalg.vector_norm(q, dim=-1, keepdim=True))

    def left_jacobian(self, v: torch.Tensor) -> torch.Tensor:
        """See :func:`left_jacobian`."""
        self.check_tangent(v, "left_jacobian")
        return left_jacobian(v)

    def left_jacobian_inverse(self, v: torch.Tensor) -> torch.Tensor:
        """See :func:`left_jacobian_inverse`."""
        self.check_tangent(v, "left_jacobian_inverse")
        return left_jacobian_inverse(v)
