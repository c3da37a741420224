"""SE(3), the group of rigid motions of R^3, as ``(*batch, 4, 4)`` homogeneous matrices.

An element is ``[[R, t], [0, 1]]`` with ``R`` in SO(3) and ``t`` in R^3. Tangent vectors are
``(rho, omega)``, shape ``(*batch, 6)``: translation first, rotation last, as in manif, jaxlie
and Theseus; ``hat(rho, omega) = [[skew(omega), rho], [0, 0]]``. The embedding is
``(vec R, t)`` in ``R^12``: the row-major rotation block followed by the translation.

``exp(rho, omega) = [[exp(omega), J_l(omega) rho], [0, 1]]`` with the SO(3) left Jacobian
``J_l = I + (1 - cos t)/t^2 K + (t - sin t)/t^3 K^2`` (``V`` in the SE(3) literature). Near
``omega = 0`` the numerics module evaluates it as ``I + K/2 + K^2/6 + ...``, not as ``R``, so a
small rotation with a large translation stays exact. ``log`` is SO(3)'s (a quaternion and
``atan2``, accurate at ``pi``) and ``rho = J_l(omega)^-1 t``. Inverse and adjoint are closed forms.

The helpers :func:`homogeneous`, :func:`affine_rows_error` and :func:`rotation_and_left_jacobian`
are shared with SE_2(3).
"""

from __future__ import annotations

import torch

from . import numerics as nx
from .base import MatrixLieGroup
from .so3 import SO3, _quadratic_form, left_jacobian_inverse, skew, unskew

__all__ = ["SE3", "homogeneous", "affine_rows_error", "rotation_and_left_jacobian"]


def rotation_and_left_jacobian(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(*batch, 3) -> (R, J_l)``, both ``(*batch, 3, 3)``: ``SO3().exp(w)`` and
    ``so3.left_jacobian(w)`` computed together, sharing ``|w|^2`` and ``(1 - cos t)/t^2``.

    ``R = I + A K + B K^2`` and ``J_l = I + B K + C K^2`` with ``K = skew(w)``, both through
    SO(3)'s ``_quadratic_form``. Used by every pose ``exp``.

    An angle whose square overflows (``|w| >= sqrt(finfo.max)``) is a whole number of turns, as
    in ``SO3.exp``: ``R = I`` and ``J_l = n n^T`` (``n = w / |w|``; at ``t = 2 pi m``,
    ``J_l = I + K^2 / t^2``), so a pose keeps the translation along its axis.
    """
    t2 = (w * w).sum(-1)
    a = nx.sin_over_t(t2)
    b = nx.one_minus_cos_over_t2(t2)
    c = nx.t_minus_sin_over_t3(t2)
    # where t2 overflowed: w scaled by its largest entry (|w| then in [1, sqrt 3]), a = b = 0
    # (R = I) and c = 1 / |w|^2 (J_l = I + K^2 / |w|^2 = n n^T); elsewhere w / 1 and the same
    # coefficients, bitwise
    over = torch.isinf(t2)
    w = w / torch.where(over, w.abs().amax(-1), 1.0).unsqueeze(-1)
    a, b = torch.where(over, 0.0, a), torch.where(over, 0.0, b)
    c = torch.where(over, torch.reciprocal(torch.where(over, (w * w).sum(-1), 1.0)), c)
    return _quadratic_form(w, a, b), _quadratic_form(w, b, c)


def homogeneous(top: torch.Tensor, algebra: bool = False) -> torch.Tensor:
    """Completes the top ``k`` rows ``(*batch, k, d)`` to a ``(*batch, d, d)`` matrix.

    The missing ``d - k`` rows are those of the ``d x d`` identity (a group element), or zero
    with ``algebra=True`` (a Lie algebra element).
    """
    k, d = top.shape[-2:]
    rows = torch.eye(d, dtype=top.dtype, device=top.device)[k:]
    if algebra:
        rows = torch.zeros_like(rows)
    return torch.cat((top, rows.expand(*top.shape[:-2], d - k, d)), dim=-2)


def affine_rows_error(x: torch.Tensor, k: int) -> torch.Tensor:
    """``||x[k:, :] - I[k:, :]||_F``: how far the bottom rows of ``(*batch, d, d)`` are from the
    identity's (``(0, ..., 0, 1)`` patterns), shape ``(*batch,)``."""
    d = x.shape[-1]
    rows = torch.eye(d, dtype=x.dtype, device=x.device)[k:]
    return torch.linalg.matrix_norm(x[..., k:, :] - rows)


class SE3(MatrixLieGroup):
    """Rigid motions as ``(*batch, 4, 4)`` matrices; tangent: ``(rho, omega)``, ``(*batch, 6)``."""

    matrix_dim = 4
    tangent_dim = 6
    embedding_dim = 12
    angle_slices = (slice(3, 6),)

    def hat(self, v: torch.Tensor) -> torch.Tensor:
        """``(*batch, 6) -> (*batch, 4, 4)``, ``[[skew(omega), rho], [0, 0]]``."""
        self.check_tangent(v, "hat")
        top = torch.cat((skew(v[..., 3:]), v[..., :3].unsqueeze(-1)), dim=-1)
        return homogeneous(top, algebra=True)

    def vee(self, m: torch.Tensor) -> torch.Tensor:
        """``(*batch, 4, 4) -> (*batch, 6)``, the inverse of ``hat``."""
        self.check_element(m, "vee")
        return torch.cat((m[..., :3, 3], unskew(m[..., :3, :3])), dim=-1)

    def exp(self, v: torch.Tensor) -> torch.Tensor:
        """``(*batch, 6) -> (*batch, 4, 4)``, ``[[exp(omega), J_l(omega) rho], [0, 1]]``."""
        self.check_tangent(v, "exp")
        r, jac = rotation_and_left_jacobian(v[..., 3:])
        t = jac @ v[..., :3].unsqueeze(-1)
        return homogeneous(torch.cat((r, t), dim=-1))

    def log(self, x: torch.Tensor) -> torch.Tensor:
        """``(*batch, 4, 4) -> (*batch, 6)``, ``omega = log R`` and ``rho = J_l(omega)^-1 t``."""
        self.check_element(x, "log")
        w = SO3().log(x[..., :3, :3])
        rho = (left_jacobian_inverse(w) @ x[..., :3, 3:]).squeeze(-1)
        return torch.cat((rho, w), dim=-1)

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        """``[[R^T, -R^T t], [0, 1]]``."""
        self.check_element(x, "inverse")
        rt = x[..., :3, :3].transpose(-1, -2)
        return homogeneous(torch.cat((rt, -(rt @ x[..., :3, 3:])), dim=-1))

    def adjoint(self, x: torch.Tensor) -> torch.Tensor:
        """``Ad = [[R, skew(t) R], [0, R]]`` for ``(rho, omega)``, shape ``(*batch, 6, 6)``."""
        self.check_element(x, "adjoint")
        r = x[..., :3, :3]
        top = torch.cat((r, skew(x[..., :3, 3]) @ r), dim=-1)
        bottom = torch.cat((torch.zeros_like(r), r), dim=-1)
        return torch.cat((top, bottom), dim=-2)

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """``(*batch, 4, 4) -> (*batch, 12)``, ``(vec R, t)`` with ``vec`` row-major."""
        self.check_element(x, "embed")
        return torch.cat((x[..., :3, :3].flatten(-2), x[..., :3, 3]), dim=-1)

    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        """``(*batch, 12) -> (*batch, 4, 4)``, the homogeneous matrix (no membership check)."""
        self.check_shape(z, (12,), "unembed", "an embedded element")
        r = z[..., :9].unflatten(-1, (3, 3))
        return homogeneous(torch.cat((r, z[..., 9:].unsqueeze(-1)), dim=-1))

    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """The largest of SO(3)'s error of ``R`` and ``||bottom row - (0, 0, 0, 1)||``."""
        self.check_element(x, "membership_error")
        return torch.maximum(SO3().membership_error(x[..., :3, :3]), affine_rows_error(x, 3))

    def random(self, batch_shape=(), generator=None, dtype=torch.float32, device=None):
        """Uniform (Haar) rotation and standard normal translation."""
        self.check_dtype(dtype, "random")
        r = SO3().random(batch_shape, generator, dtype, device)
        t = torch.randn(*batch_shape, 3, 1, generator=generator, dtype=dtype, device=device)
        return homogeneous(torch.cat((r, t), dim=-1))
