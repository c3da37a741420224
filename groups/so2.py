"""SO(2), the group of planar rotations, as ``(*batch, 2, 2)`` rotation matrices.

Tangent vectors are angles ``theta`` of shape ``(*batch, 1)``, with
``hat(theta) = [[0, -theta], [theta, 0]]``. The embedding is the row-major ``vec R`` in ``R^4``.

``exp`` is ``[[cos, -sin], [sin, cos]]``; ``log`` is ``atan2(R_10, R_00)``, an angle in
``(-pi, pi]``, accurate at and near ``pi`` and with a finite gradient everywhere on the group.
SO(2) is abelian, so its adjoint is the ``1 x 1`` identity.
"""

from __future__ import annotations

import math

import torch

from .base import MatrixLieGroup

__all__ = ["SO2", "rotation_2d", "so2_membership_error"]


def rotation_2d(theta: torch.Tensor) -> torch.Tensor:
    """``(*batch,) -> (*batch, 2, 2)``, the rotation matrix by the angle ``theta``."""
    c, s = torch.cos(theta), torch.sin(theta)
    return torch.stack((c, -s, s, c), dim=-1).unflatten(-1, (2, 2))


def so2_membership_error(r: torch.Tensor) -> torch.Tensor:
    """``max(||R R^T - I||_F, |det R - 1|)`` of ``(*batch, 2, 2)`` matrices, shape ``(*batch,)``."""
    eye = torch.eye(2, dtype=r.dtype, device=r.device)
    orth = torch.linalg.matrix_norm(r @ r.transpose(-1, -2) - eye)
    det = r[..., 0, 0] * r[..., 1, 1] - r[..., 0, 1] * r[..., 1, 0]
    return torch.maximum(orth, (det - 1).abs())


class SO2(MatrixLieGroup):
    """Rotations of R^2 as ``(*batch, 2, 2)`` matrices; tangent: angles ``(*batch, 1)``."""

    matrix_dim = 2
    tangent_dim = 1
    embedding_dim = 4
    embedding_is_flat = True
    angle_slices = (slice(0, 1),)

    def hat(self, v: torch.Tensor) -> torch.Tensor:
        """``(*batch, 1) -> (*batch, 2, 2)``, ``[[0, -theta], [theta, 0]]``."""
        self.check_tangent(v, "hat")
        t = v[..., 0]
        o = torch.zeros_like(t)
        return torch.stack((o, -t, t, o), dim=-1).unflatten(-1, (2, 2))

    def vee(self, m: torch.Tensor) -> torch.Tensor:
        """``(*batch, 2, 2) -> (*batch, 1)``, reads the antisymmetric part of ``m``."""
        self.check_element(m, "vee")
        return 0.5 * (m[..., 1, 0] - m[..., 0, 1]).unsqueeze(-1)

    def exp(self, v: torch.Tensor) -> torch.Tensor:
        """``(*batch, 1) -> (*batch, 2, 2)``, ``[[cos t, -sin t], [sin t, cos t]]``."""
        self.check_tangent(v, "exp")
        return rotation_2d(v[..., 0])

    def log(self, x: torch.Tensor) -> torch.Tensor:
        """``(*batch, 2, 2) -> (*batch, 1)``, the angle ``atan2(R_10, R_00)`` in ``(-pi, pi]``."""
        self.check_element(x, "log")
        return torch.atan2(x[..., 1, 0], x[..., 0, 0]).unsqueeze(-1)

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        """The transpose."""
        self.check_element(x, "inverse")
        return x.transpose(-1, -2)

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """``(*batch, 2, 2) -> (*batch, 4)``, row-major ``vec R``."""
        self.check_element(x, "embed")
        return x.flatten(-2)

    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        self.check_shape(z, (4,), "unembed", "an embedded element")
        return z.unflatten(-1, (2, 2))

    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """``max(||R R^T - I||_F, |det R - 1|)`` (the determinant catches reflections)."""
        self.check_element(x, "membership_error")
        return so2_membership_error(x)

    def adjoint(self, x: torch.Tensor) -> torch.Tensor:
        """``Ad_R = 1`` (SO(2) is abelian), shape ``(*batch, 1, 1)``."""
        self.check_element(x, "adjoint")
        return torch.ones_like(x[..., :1, :1])

    def random(self, batch_shape=(), generator=None, dtype=torch.float32, device=None):
        """Uniform (Haar) rotations: the angle is uniform on ``[-pi, pi)``."""
        self.check_dtype(dtype, "random")
        u = torch.rand(tuple(batch_shape), generator=generator, dtype=dtype, device=device)
        return rotation_2d((2.0 * u - 1.0) * math.pi)
