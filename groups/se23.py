"""SE_2(3), the group of extended poses (inertial navigation), as ``(*batch, 5, 5)`` matrices.

An element is ``[[R, v, p], [0, 1, 0], [0, 0, 1]]``: attitude ``R`` in SO(3), velocity ``v`` and
position ``p`` in R^3 (Barrau and Bonnabel's group of the invariant EKF). Tangent vectors are
``(nu, rho, omega)``, shape ``(*batch, 9)``: the velocity part, the position part, then the
rotation, translations first as in SE(3). ``hat = [[skew(omega), nu, rho], [0, 0, 0], [0, 0, 0]]``.
The embedding is ``(vec R, v, p)`` in ``R^15`` with ``vec`` row-major.

``exp(nu, rho, omega) = [[exp(omega), J_l nu, J_l rho], [0, 1, 0], [0, 0, 1]]`` with the SO(3)
left Jacobian ``J_l(omega)``; ``log`` is SO(3)'s log and ``J_l^-1`` applied to ``v`` and ``p``.
Inverse and adjoint are closed forms.
"""

from __future__ import annotations

import torch

from .base import MatrixLieGroup
from .se3 import affine_rows_error, homogeneous, rotation_and_left_jacobian
from .so3 import SO3, left_jacobian_inverse, skew, unskew

__all__ = ["SE23"]


class SE23(MatrixLieGroup):
    """Extended poses ``(R, v, p)`` as ``(*batch, 5, 5)`` matrices; tangent ``(nu, rho, omega)``."""

    matrix_dim = 5
    tangent_dim = 9
    embedding_dim = 15
    angle_slices = (slice(6, 9),)

    def hat(self, v: torch.Tensor) -> torch.Tensor:
        """``(*batch, 9) -> (*batch, 5, 5)``, ``[[skew(omega), nu, rho], [0, 0, 0], [0, 0, 0]]``."""
        self.check_tangent(v, "hat")
        top = torch.cat((skew(v[..., 6:]), v[..., :6].unflatten(-1, (2, 3)).transpose(-1, -2)), -1)
        return homogeneous(top, algebra=True)

    def vee(self, m: torch.Tensor) -> torch.Tensor:
        """``(*batch, 5, 5) -> (*batch, 9)``, the inverse of ``hat``."""
        self.check_element(m, "vee")
        return torch.cat((m[..., :3, 3], m[..., :3, 4], unskew(m[..., :3, :3])), dim=-1)

    def exp(self, v: torch.Tensor) -> torch.Tensor:
        """``(*batch, 9) -> (*batch, 5, 5)``: ``R = exp(omega)``, ``(v, p) = J_l (nu, rho)``."""
        self.check_tangent(v, "exp")
        r, jac = rotation_and_left_jacobian(v[..., 6:])
        vp = jac @ v[..., :6].unflatten(-1, (2, 3)).transpose(-1, -2)
        return homogeneous(torch.cat((r, vp), dim=-1))

    def log(self, x: torch.Tensor) -> torch.Tensor:
        """``(*batch, 5, 5) -> (*batch, 9)``, ``omega = log R``, ``(nu, rho) = J_l^-1 (v, p)``."""
        self.check_element(x, "log")
        w = SO3().log(x[..., :3, :3])
        nu_rho = left_jacobian_inverse(w) @ x[..., :3, 3:]  # (*batch, 3, 2)
        return torch.cat((nu_rho.transpose(-1, -2).flatten(-2), w), dim=-1)

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        """``[[R^T, -R^T v, -R^T p], [0, 1, 0], [0, 0, 1]]``."""
        self.check_element(x, "inverse")
        rt = x[..., :3, :3].transpose(-1, -2)
        return homogeneous(torch.cat((rt, -(rt @ x[..., :3, 3:])), dim=-1))

    def adjoint(self, x: torch.Tensor) -> torch.Tensor:
        """``[[R, 0, skew(v) R], [0, R, skew(p) R], [0, 0, R]]``, shape ``(*batch, 9, 9)``."""
        self.check_element(x, "adjoint")
        r = x[..., :3, :3]
        o = torch.zeros_like(r)
        rows = (
            torch.cat((r, o, skew(x[..., :3, 3]) @ r), dim=-1),
            torch.cat((o, r, skew(x[..., :3, 4]) @ r), dim=-1),
            torch.cat((o, o, r), dim=-1),
        )
        return torch.cat(rows, dim=-2)

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """``(*batch, 5, 5) -> (*batch, 15)``, ``(vec R, v, p)`` with ``vec`` row-major."""
        self.check_element(x, "embed")
        return torch.cat((x[..., :3, :3].flatten(-2), x[..., :3, 3], x[..., :3, 4]), dim=-1)

    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        """``(*batch, 15) -> (*batch, 5, 5)``, the matrix (no membership check)."""
        self.check_shape(z, (15,), "unembed", "an embedded element")
        r = z[..., :9].unflatten(-1, (3, 3))
        vp = z[..., 9:].unflatten(-1, (2, 3)).transpose(-1, -2)
        return homogeneous(torch.cat((r, vp), dim=-1))

    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """The largest of SO(3)'s error of ``R`` and the bottom rows' distance to
        ``[[0, 0, 0, 1, 0], [0, 0, 0, 0, 1]]`` (Frobenius)."""
        self.check_element(x, "membership_error")
        return torch.maximum(SO3().membership_error(x[..., :3, :3]), affine_rows_error(x, 3))

    def random(self, batch_shape=(), generator=None, dtype=torch.float32, device=None):
        """Uniform (Haar) attitude; velocity and position standard normal."""
        self.check_dtype(dtype, "random")
        r = SO3().random(batch_shape, generator, dtype, device)
        vp = torch.randn(*batch_shape, 3, 2, generator=generator, dtype=dtype, device=device)
        return homogeneous(torch.cat((r, vp), dim=-1))
