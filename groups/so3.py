"""SO(3), the group of 3D rotations, as ``(*batch, 3, 3)`` rotation matrices.

Tangent vectors are rotation vectors ``w`` (axis times angle, ``(*batch, 3)``), with
``hat(w) @ u = w x u``. The embedding is the row-major ``vec R`` in ``R^9``.

``exp`` is Rodrigues' formula written entrywise; ``log`` goes through a unit quaternion chosen by
the largest pivot (Shepperd's method) and ``atan2``, so it is accurate up to and at ``theta = pi``
(no ``acos`` of the trace) and its gradient is finite everywhere.
"""

from __future__ import annotations

import torch

from . import _numerics as nx
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


def _quadratic_form(w: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor):
    """``a I + skew(b w) + c w w^T`` for per-batch scalars ``a, b, c`` (shape ``(*batch,)``)."""
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    outer = (c.unsqueeze(-1) * w).unsqueeze(-1) * w.unsqueeze(-2)
    return outer + skew(b.unsqueeze(-1) * w) + a[..., None, None] * eye


def left_jacobian(w: torch.Tensor) -> torch.Tensor:
    """The left Jacobian ``J_l(w) = I + B K + C K^2`` of SO(3), ``(*batch, 3) -> (*batch, 3, 3)``.

    ``int_0^1 exp(s K) ds`` with ``K = skew(w)``: the V matrix of SE(3)'s exponential and the
    factor that maps a body velocity held over a step into the displacement.
    """
    t2 = (w * w).sum(-1)
    b = nx.one_minus_cos_over_t2(t2)
    c = nx.t_minus_sin_over_t3(t2)
    return _quadratic_form(w, 1.0 - c * t2, b, c)


def left_jacobian_inverse(w: torch.Tensor) -> torch.Tensor:
    """``J_l(w)^-1 = I - K/2 + D K^2``, finite on the whole log domain ``|w| <= pi``."""
    t2 = (w * w).sum(-1)
    d = nx.inv_left_jacobian_coeff(t2)
    return _quadratic_form(w, 1.0 - d * t2, torch.full_like(t2, -0.5), d)


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


def _matrix_to_quaternion(r: torch.Tensor) -> torch.Tensor:
    """Rotation matrix to the unit quaternion ``(w, x, y, z)`` with ``w >= 0`` (Shepperd).

    Each of the four candidate rows equals ``4 q_k q`` for one component ``q_k``; the row with
    the largest ``q_k`` (its pivot ``4 q_k^2 >= 1``) is normalised, so no square root of a small
    number is ever taken and the gradient stays finite.
    """
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = r.flatten(-2).unbind(-1)
    d0 = 1 + m00 + m11 + m22
    d1 = 1 + m00 - m11 - m22
    d2 = 1 - m00 + m11 - m22
    d3 = 1 - m00 - m11 + m22
    a, b, c = m21 - m12, m02 - m20, m10 - m01
    e, f, g = m10 + m01, m02 + m20, m21 + m12
    rows = torch.stack(
        (d0, a, b, c,
         a, d1, e, f,
         b, e, d2, g,
         c, f, g, d3),
        dim=-1,
    ).unflatten(-1, (4, 4))  # fmt: skip
    pivot = torch.stack((d0, d1, d2, d3), dim=-1).argmax(dim=-1, keepdim=True)
    q = torch.take_along_dim(rows, pivot.unsqueeze(-1), dim=-2).squeeze(-2)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


class SO3(MatrixLieGroup):
    """Rotations of R^3 as ``(*batch, 3, 3)`` matrices; tangent: rotation vectors ``(*batch, 3)``."""

    matrix_dim = 3
    tangent_dim = 3
    embedding_dim = 9
    angle_slices = (slice(0, 3),)

    def hat(self, v: torch.Tensor) -> torch.Tensor:
        self._check_tangent(v, "hat")
        return skew(v)

    def vee(self, m: torch.Tensor) -> torch.Tensor:
        self._check_element(m, "vee")
        return unskew(m)

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        self._check_element(x, "inverse")
        return x.transpose(-1, -2)

    def exp(self, v: torch.Tensor) -> torch.Tensor:
        """Rodrigues: ``R = cos(t) I + sinc(t) K + (1 - cos t)/t^2 w w^T``."""
        self._check_tangent(v, "exp")
        t2 = (v * v).sum(-1)
        a = nx.sin_over_t(t2)
        b = nx.one_minus_cos_over_t2(t2)
        return _quadratic_form(v, 1.0 - b * t2, a, b)

    def log(self, x: torch.Tensor) -> torch.Tensor:
        """Rotation vector with angle in ``[0, pi]``, through a unit quaternion and ``atan2``."""
        self._check_element(x, "log")
        q = _matrix_to_quaternion(x)
        qw, qv = q[..., 0], q[..., 1:]
        return (2.0 * nx.atan2_over_s((qv * qv).sum(-1), qw)).unsqueeze(-1) * qv

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        self._check_element(x, "embed")
        return x.flatten(-2)

    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        self._check_shape(z, (9,), "unembed", "an embedded element")
        return z.unflatten(-1, (3, 3))

    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """``max(||R R^T - I||_F, |det R - 1|)`` (the determinant catches reflections)."""
        self._check_element(x, "membership_error")
        eye = torch.eye(3, dtype=x.dtype, device=x.device)
        orth = torch.linalg.matrix_norm(x @ x.transpose(-1, -2) - eye)
        return torch.maximum(orth, (torch.linalg.det(x) - 1).abs())

    def adjoint(self, x: torch.Tensor) -> torch.Tensor:
        """``Ad_R = R`` for rotation vectors."""
        self._check_element(x, "adjoint")
        return x

    def random(self, batch_shape=(), generator=None, dtype=torch.float32, device=None):
        """Uniform (Haar) rotations, from normalised Gaussian quaternions."""
        q = torch.randn(*batch_shape, 4, generator=generator, dtype=dtype, device=device)
        return _quaternion_to_matrix(q / torch.linalg.vector_norm(q, dim=-1, keepdim=True))

    def left_jacobian(self, v: torch.Tensor) -> torch.Tensor:
        """See :func:`left_jacobian`."""
        self._check_tangent(v, "left_jacobian")
        return left_jacobian(v)

    def left_jacobian_inverse(self, v: torch.Tensor) -> torch.Tensor:
        """See :func:`left_jacobian_inverse`."""
        self._check_tangent(v, "left_jacobian_inverse")
        return left_jacobian_inverse(v)
