"""Rigid-body kinematics ``dR/dt = R [Omega]x``, ``dp/dt = R v``: exact steps, an RK45 reference.

With the body-frame angular velocity ``Omega`` and linear velocity ``v`` held over a step of
length ``dt`` (a zero-order hold), the solution is closed form:

    R_{k+1} = R_k exp(Omega dt),        p_{k+1} = p_k + R_k J_l(Omega dt) v dt,

where ``J_l(phi) = int_0^1 exp(s [phi]x) ds`` is the left Jacobian of SO(3) (so
``int_0^dt exp(s [Omega]x) ds = dt J_l(Omega dt)``). This is the exponential of SE(3) applied to
the twist ``(Omega, v) dt``; it is exact to rounding and every ``R`` stays a rotation.

:func:`rk45_rollout` integrates the same ODE with scipy's ``solve_ivp(method="RK45")``, one call
per step per sequence, as the paper did; it is the reference the exact step is tested against.

Shapes: ``R`` is ``(*batch, 3, 3)``, ``p``, ``Omega``, ``v`` are ``(*batch, 3)``; rollouts take
``(N, T, 3)`` velocities and return ``(N, T+1, 3, 3)`` rotations and ``(N, T+1, 3)`` positions.
The fast path (:func:`exact_rollout_time_major`) works time- and component-major,
``(T, 3, N)``, so that each operation of the time loop runs over ``N`` contiguous values.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.integrate import solve_ivp

from groups import numerics as nx

from manifold_nets.progress import progress

__all__ = [
    "increments",
    "exact_step",
    "exact_rollout",
    "exact_rollout_time_major",
    "time_major",
    "sequence_major_into",
    "rk45_step",
    "rk45_rollout",
]

_SEQ_BLOCK = 512  # sequences per block of a transposing copy


def _increments_cm(
    omega: torch.Tensor, v: torch.Tensor, dt: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`increments`, component-major: ``(3, *b)`` in, ``(3, 3, *b)`` and ``(3, *b)`` out.

    Every operation acts on whole rows of contiguous components (structure of arrays), which is
    several times faster on CPU than tiny ``3 x 3`` batched products or stacking on the last axis.
    """
    phi = omega * dt
    x, y, z = phi.unbind(0)
    vx, vy, vz = v.unbind(0)
    t2 = x * x + y * y + z * z
    a, b, c = nx.sin_over_t(t2), nx.one_minus_cos_over_t2(t2), nx.t_minus_sin_over_t3(t2)
    cos = 1.0 - b * t2
    bx, by, bz = b * x, b * y, b * z
    ax, ay, az = a * x, a * y, a * z
    bxy, bxz, byz = bx * y, bx * z, by * z
    rot = torch.stack(
        (cos + bx * x, bxy - az, bxz + ay,
         bxy + az, cos + by * y, byz - ax,
         bxz - ay, byz + ax, cos + bz * z),
    ).unflatten(0, (3, 3))  # fmt: skip
    # J_l(phi) v = v + B phi x v + C phi x (phi x v),  phi x (phi x v) = phi (phi . v) - t2 v
    cd = c * (x * vx + y * vy + z * vz)
    ct = 1.0 - c * t2
    disp = torch.stack(
        (ct * vx + b * (y * vz - z * vy) + cd * x,
         ct * vy + b * (z * vx - x * vz) + cd * y,
         ct * vz + b * (x * vy - y * vx) + cd * z),
    )
    return rot, disp * dt


def increments(
    omega: torch.Tensor, v: torch.Tensor, dt: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The body-frame motion over one step: ``exp(Omega dt)`` ``(*batch, 3, 3)`` and
    ``J_l(Omega dt) v dt`` ``(*batch, 3)``.

    The same values as ``SO3().exp(phi)`` and ``left_jacobian(phi) @ v * dt`` with
    ``phi = Omega dt``, from the same safe coefficient functions of ``groups.numerics``, written
    out entrywise: Rodrigues ``exp(phi) = cos t I + A [phi]x + B phi phi^T`` and
    ``J_l(phi) v = (1 - C t^2) v + B phi x v + C (phi . v) phi`` with ``A = sin t / t``,
    ``B = (1 - cos t) / t^2``, ``C = (t - sin t) / t^3``. Data generation is this function in a
    loop, so it is fused by hand.
    """
    omega, v = torch.broadcast_tensors(omega, v)
    rot, disp = _increments_cm(omega.movedim(-1, 0), v.movedim(-1, 0), dt)
    return rot.movedim(0, -1).movedim(0, -1), disp.movedim(0, -1)


def exact_step(
    R: torch.Tensor, p: torch.Tensor, omega: torch.Tensor, v: torch.Tensor, dt: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """One exact step from ``(R_k, p_k)`` with ``(Omega_k, v_k)`` held for ``dt``."""
    rot, disp = increments(omega, v, dt)
    return R @ rot, p + (R @ disp.unsqueeze(-1)).squeeze(-1)


def time_major(x: torch.Tensor) -> torch.Tensor:
    """``(N, T, *rest)`` -> a contiguous ``(T, *rest, N)`` copy, ``_SEQ_BLOCK`` sequences at a time.

    A blocked transpose touches few memory pages at once; a plain ``permute().contiguous()``
    of a large tensor is several times slower.
    """
    n = x.shape[0]
    out = x.new_empty(*x.shape[1:], n)
    for s in range(0, n, _SEQ_BLOCK):
        out[..., s : s + _SEQ_BLOCK] = x[s : s + _SEQ_BLOCK].movedim(0, -1)
    return out


def sequence_major_into(src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """``dst (N, T, *rest) <- src (T, *rest, N)``, the inverse of :func:`time_major`, blocked."""
    n = dst.shape[0]
    for s in range(0, n, _SEQ_BLOCK):
        dst[s : s + _SEQ_BLOCK] = src[..., s : s + _SEQ_BLOCK].movedim(-1, 0)
    return dst


def exact_rollout_time_major(
    omega: torch.Tensor,
    v: torch.Tensor,
    dt: float,
    R: torch.Tensor,
    p: torch.Tensor,
    show_progress: bool = False,
) -> None:
    """The exact rollout in time- and component-major layout, in place.

    ``omega``, ``v``: ``(T, 3, N)``; ``R``: ``(T+1, 3, 3, N)`` and ``p``: ``(T+1, 3, N)`` with
    ``R[0]``, ``p[0]`` set; fills ``R[1:]``, ``p[1:]`` with ``p_{k+1} = p_k + R_k J_l(Omega_k dt)
    v_k dt`` and ``R_{k+1} = R_k exp(Omega_k dt)``. One loop over time; every operation runs
    over long contiguous rows of ``N`` values (several times faster on CPU than batched
    ``3 x 3`` products).
    """
    for k in progress(range(omega.shape[0]), desc="exact steps", enabled=show_progress):
        rot, disp = _increments_cm(omega[k], v[k], dt)
        Rk, pk = R[k], p[k]
        torch.addcmul(pk, Rk[:, 0], disp[0], out=p[k + 1])
        p[k + 1].addcmul_(Rk[:, 1], disp[1]).addcmul_(Rk[:, 2], disp[2])
        torch.mul(Rk[:, 0:1], rot[0:1], out=R[k + 1])
        R[k + 1].addcmul_(Rk[:, 1:2], rot[1:2]).addcmul_(Rk[:, 2:3], rot[2:3])


def exact_rollout(
    R0: torch.Tensor, p0: torch.Tensor, omega: torch.Tensor, v: torch.Tensor, dt: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact rollout of ``N`` sequences: ``(N, T+1, 3, 3)`` rotations, ``(N, T+1, 3)`` positions.

    ``R0`` ``(N, 3, 3)``, ``p0`` ``(N, 3)``, ``omega``, ``v`` ``(N, T, 3)``. Transposes to the
    layout of :func:`exact_rollout_time_major` and back.
    """
    n, t = omega.shape[:2]
    R = R0.new_empty(t + 1, 3, 3, n)
    p = p0.new_empty(t + 1, 3, n)
    R[0], p[0] = R0.permute(1, 2, 0), p0.transpose(0, 1)
    exact_rollout_time_major(time_major(omega), time_major(v), dt, R, p)
    return (
        sequence_major_into(R, R0.new_empty(n, t + 1, 3, 3)),
        sequence_major_into(p, p0.new_empty(n, t + 1, 3)),
    )


def _rhs(omega: np.ndarray, v: np.ndarray):
    wx = np.array(
        [[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]]
    )

    def f(_t: float, y: np.ndarray) -> np.ndarray:
        R = y[:9].reshape(3, 3)
        return np.concatenate(((R @ wx).ravel(), R @ v))

    return f


def _project_to_so3(R: np.ndarray) -> np.ndarray:
    """The closest rotation (polar factor through the SVD)."""
    u, _, vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rk45_step(
    R: np.ndarray, p: np.ndarray, omega: np.ndarray, v: np.ndarray, dt: float,
    rtol: float = 1e-10, atol: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray]:
    """One ``solve_ivp(RK45)`` call over ``[0, dt]`` for one sequence (numpy, ``(3, 3)``, ``(3,)``).

    The state is ``(vec R, p)`` in ``R^12``; ``Omega`` and ``v`` are held over the step.
    """
    y0 = np.concatenate((R.ravel(), p))
    sol = solve_ivp(_rhs(omega, v), (0.0, dt), y0, method="RK45", rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(f"solve_ivp(RK45) failed: {sol.message}")
    y = sol.y[:, -1]
    return y[:9].reshape(3, 3), y[9:]


def rk45_rollout(
    R0: torch.Tensor, p0: torch.Tensor, omega: torch.Tensor, v: torch.Tensor, dt: float,
    rtol: float = 1e-10, atol: float = 1e-10, project: bool = False, show_progress: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The paper's way: one RK45 call per step per sequence. Same shapes as :func:`exact_rollout`.

    RK45 leaves ``R`` off SO(3) by about the tolerance per step; ``project=True`` replaces ``R``
    by its closest rotation after every step so that a dataset made this way is on the group.
    """
    n, t = omega.shape[:2]
    Rn, pn = R0.detach().cpu().double().numpy(), p0.detach().cpu().double().numpy()
    wn, vn = omega.detach().cpu().double().numpy(), v.detach().cpu().double().numpy()
    R = np.empty((n, t + 1, 3, 3))
    p = np.empty((n, t + 1, 3))
    R[:, 0], p[:, 0] = Rn, pn
    for i in progress(range(n), desc="RK45 sequences", enabled=show_progress):
        for k in range(t):
            Rk, pk = rk45_step(R[i, k], p[i, k], wn[i, k], vn[i, k], dt, rtol, atol)
            R[i, k + 1] = _project_to_so3(Rk) if project else Rk
            p[i, k + 1] = pk
    as_t = dict(dtype=omega.dtype, device=omega.device)
    return torch.as_tensor(R, **as_t), torch.as_tensor(p, **as_t)
