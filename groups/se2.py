"""SE(2), the group of planar rigid motions, as ``(*batch, 3, 3)`` homogeneous matrices.

An element is ``[[R, t], [0, 1]]`` with ``R`` in SO(2) and ``t`` in R^2. Tangent vectors are
``(rho_x, rho_y, theta)``, shape ``(*batch, 3)``: translation first, rotation last, as in manif,
jaxlie and Theseus. ``hat(rho, theta) = [[0, -theta, rho_x], [theta, 0, rho_y], [0, 0, 0]]``.

The embedding is ``(vec R, t)`` in ``R^6``: the row-major rotation block ``(R00, R01, R10, R11)``
followed by ``(t_x, t_y)`` (the same layout as SE(3)'s, and as ``Product(SO2(), Euclidean(2))``).

``exp(rho, theta) = [[R(theta), V rho], [0, 1]]`` with ``V = [[A, -B], [B, A]]``,
``A = sin(theta)/theta`` and ``B = (1 - cos theta)/theta``. ``log`` inverts it with the half-angle
form ``V^-1 = [[h cot h, h], [-h, h cot h]]``, ``h = theta / 2``, which is finite on the whole
log domain ``|theta| <= pi``. Inverse and adjoint are closed forms.
"""

from __future__ import annotations

import torch

from . import numerics as nx
from .base import MatrixLieGroup
from .so2 import SO2, so2_membership_error

__all__ = ["SE2"]


def _matrix(entries: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """Nine ``(*batch,)`` entries in row-major order to a ``(*batch, 3, 3)`` matrix."""
    entries = torch.broadcast_tensors(*entries)
    return torch.stack(entries, dim=-1).unflatten(-1, (3, 3))


class SE2(MatrixLieGroup):
    """Planar poses as ``(*batch, 3, 3)`` matrices; tangent: ``(rho_x, rho_y, theta)``."""

    matrix_dim = 3
    tangent_dim = 3
    embedding_dim = 6
    angle_slices = (slice(2, 3),)

    def hat(self, v: torch.Tensor) -> torch.Tensor:
        """``(*batch, 3) -> (*batch, 3, 3)``, the Lie algebra matrix of ``(rho, theta)``."""
        self.check_tangent(v, "hat")
        rx, ry, th = v.unbind(-1)
        o = torch.zeros_like(th)
        return _matrix((o, -th, rx, th, o, ry, o, o, o))

    def vee(self, m: torch.Tensor) -> torch.Tensor:
        """``(*batch, 3, 3) -> (*batch, 3)``, the inverse of ``hat`` (theta: antisymmetric part)."""
        self.check_element(m, "vee")
        th = 0.5 * (m[..., 1, 0] - m[..., 0, 1])
        return torch.stack((m[..., 0, 2], m[..., 1, 2], th), dim=-1)

    def exp(self, v: torch.Tensor) -> torch.Tensor:
        """``(*batch, 3) -> (*batch, 3, 3)``, ``[[R(theta), V(theta) rho], [0, 1]]``."""
        self.check_tangent(v, "exp")
        rx, ry, th = v.unbind(-1)
        t2 = th * th
        # an angle whose square overflows (|theta| >= sqrt(finfo.max)): A = sin(t)/t and
        # B = (1 - cos t)/t, both within 2/|theta| of 0, are 0 (the rotation is exact)
        over = torch.isinf(t2)
        a = torch.where(over, 0.0, nx.sin_over_t(t2))
        b = torch.where(over, 0.0, th * nx.one_minus_cos_over_t2(t2))
        c, s = torch.cos(th), torch.sin(th)
        o, i = torch.zeros_like(th), torch.ones_like(th)
        return _matrix((c, -s, a * rx - b * ry, s, c, b * rx + a * ry, o, o, i))

    def log(self, x: torch.Tensor) -> torch.Tensor:
        """``(*batch, 3, 3) -> (*batch, 3)``, ``theta = atan2(R_10, R_00)`` and ``rho = V^-1 t``."""
        self.check_element(x, "log")
        th = torch.atan2(x[..., 1, 0], x[..., 0, 0])
        d = nx.half_t_cot_half_t(th * th)
        h = 0.5 * th
        tx, ty = x[..., 0, 2], x[..., 1, 2]
        return torch.stack((d * tx + h * ty, d * ty - h * tx, th), dim=-1)

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        """``[[R^T, -R^T t], [0, 1]]``."""
        self.check_element(x, "inverse")
        r00, r01, tx, r10, r11, ty = x[..., :2, :].flatten(-2).unbind(-1)
        o, i = torch.zeros_like(tx), torch.ones_like(tx)
        ux = -(r00 * tx + r10 * ty)
        uy = -(r01 * tx + r11 * ty)
        return _matrix((r00, r10, ux, r01, r11, uy, o, o, i))

    def adjoint(self, x: torch.Tensor) -> torch.Tensor:
        """``Ad = [[R, (t_y, -t_x)^T], [0, 1]]`` for the ``(rho, theta)`` ordering."""
        self.check_element(x, "adjoint")
        r00, r01, tx, r10, r11, ty = x[..., :2, :].flatten(-2).unbind(-1)
        o, i = torch.zeros_like(tx), torch.ones_like(tx)
        return _matrix((r00, r01, ty, r10, r11, -tx, o, o, i))

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """``(*batch, 3, 3) -> (*batch, 6)``, ``(R00, R01, R10, R11, t_x, t_y)``."""
        self.check_element(x, "embed")
        return torch.cat((x[..., :2, :2].flatten(-2), x[..., :2, 2]), dim=-1)

    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        """``(*batch, 6) -> (*batch, 3, 3)``, the homogeneous matrix (no membership check)."""
        self.check_shape(z, (6,), "unembed", "an embedded element")
        r00, r01, r10, r11, tx, ty = z.unbind(-1)
        o, i = torch.zeros_like(tx), torch.ones_like(tx)
        return _matrix((r00, r01, tx, r10, r11, ty, o, o, i))

    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """The largest of ``||R R^T - I||_F``, ``|det R - 1|``, ``||bottom row - (0, 0, 1)||``."""
        self.check_element(x, "membership_error")
        unit = torch.tensor([0.0, 0.0, 1.0], dtype=x.dtype, device=x.device)
        bottom = torch.linalg.vector_norm(x[..., 2, :] - unit, dim=-1)
        return torch.maximum(so2_membership_error(x[..., :2, :2]), bottom)

    def random(self, batch_shape=(), generator=None, dtype=torch.float32, device=None):
        """Uniform (Haar) rotation and standard normal translation."""
        self.check_dtype(dtype, "random")
        r = SO2().random(batch_shape, generator, dtype, device)
        t = torch.randn(*batch_shape, 2, generator=generator, dtype=dtype, device=device)
        return self.unembed(torch.cat((r.flatten(-2), t), dim=-1))
