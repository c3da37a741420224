"""The BROAD benchmark's error metric, and quaternion helpers (numpy, float64).

With unit quaternions ``q_est``, ``q_ref`` ``(T, 4)`` (w, x, y, z) of the IMU in the reference
(East-North-Up) frame, the error in the reference frame is ``q_e = q_est * conj(q_ref)`` and, per
sample (Laidig et al., BROAD, Data 2021)::

    total        2 arccos(|w_e|)
    heading      2 arctan(|z_e / w_e|)          (about the vertical axis; pi where w_e = 0)
    inclination  2 arccos(sqrt(w_e^2 + z_e^2))

each reported as a root mean square in degrees over the samples with ``movement == 1`` and a
known (finite) reference, per trial; the benchmark then averages the per-trial values.
``q`` and ``-q`` give the same errors. Arguments clip into the functions' domains, the heading
is computed as ``2 arctan2(|z_e|, |w_e|)``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "errors",
    "rmse",
    "quat_multiply",
    "quat_conj",
    "quat_to_matrix",
    "matrix_to_quat",
]

_DEG = 180.0 / np.pi


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The Hamilton product ``p * q`` of ``(..., 4)`` quaternions (w, x, y, z), broadcasting."""
    p, q = np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        (
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ),
        axis=-1,
    )


def quat_conj(q: np.ndarray) -> np.ndarray:
    """The conjugate ``(w, -x, -y, -z)`` of ``(..., 4)`` quaternions."""
    return np.asarray(q, dtype=np.float64) * np.array([1.0, -1.0, -1.0, -1.0])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """``R(q)`` ``(..., 3, 3)`` of unit quaternions ``(..., 4)``: ``v_world = R v_body``."""
    from .data import quat_to_matrix as _q2m

    return _q2m(q)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (w, x, y, z; ``w >= 0``) of rotation matrices ``(..., 3, 3)``.

    The largest-pivot method (Shepperd): of ``4w^2, 4x^2, 4y^2, 4z^2`` (each from the trace and
    diagonal) the largest is the divisor, so no division by a small number.
    """
    R = np.asarray(R, dtype=np.float64)
    d0, d1, d2 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    pivots = np.stack((1 + d0 + d1 + d2, 1 + d0 - d1 - d2, 1 - d0 + d1 - d2, 1 - d0 - d1 + d2), -1)
    k = np.argmax(pivots, axis=-1)
    s = np.sqrt(np.maximum(np.take_along_axis(pivots, k[..., None], -1)[..., 0], 1e-300))
    a = R[..., 2, 1] - R[..., 1, 2]
    b = R[..., 0, 2] - R[..., 2, 0]
    c = R[..., 1, 0] - R[..., 0, 1]
    e = R[..., 0, 1] + R[..., 1, 0]
    f = R[..., 0, 2] + R[..., 2, 0]
    g = R[..., 1, 2] + R[..., 2, 1]
    # 4 * (w, x, y, z) * (the pivot component), for each choice of pivot
    cand = np.stack(
        (
            np.stack((s * s, a, b, c), -1),
            np.stack((a, s * s, e, f), -1),
            np.stack((b, e, s * s, g), -1),
            np.stack((c, f, g, s * s), -1),
        ),
        -2,
    )
    q = np.take_along_axis(cand, k[..., None, None], -2)[..., 0, :] / (2 * s[..., None])
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def errors(q_est: np.ndarray, q_ref: np.ndarray) -> dict[str, np.ndarray]:
    """Per-sample errors in radians, ``{"total", "heading", "inclination"}`` each ``(T,)``.

    ``q_est``, ``q_ref`` ``(T, 4)`` (w, x, y, z; normalised here). NaN rows give NaN errors.
    """
    q_est, q_ref = np.asarray(q_est, dtype=np.float64), np.asarray(q_ref, dtype=np.float64)
    if q_est.shape != q_ref.shape or q_est.shape[-1:] != (4,):
        raise ValueError(
            f"q_est and q_ref must both be (T, 4) quaternions (w, x, y, z), got {q_est.shape} "
            f"and {q_ref.shape}."
        )
    q_est = q_est / np.linalg.norm(q_est, axis=-1, keepdims=True)
    q_ref = q_ref / np.linalg.norm(q_ref, axis=-1, keepdims=True)
    qe = quat_multiply(q_est, quat_conj(q_ref))
    w, z = np.abs(qe[..., 0]), np.abs(qe[..., 3])
    return {
        "total": 2 * np.arccos(np.clip(w, 0.0, 1.0)),
        "heading": 2 * np.arctan2(z, w),
        "inclination": 2 * np.arccos(np.clip(np.sqrt(w * w + z * z), 0.0, 1.0)),
    }


def rmse(q_est: np.ndarray, q_ref: np.ndarray, movement: np.ndarray) -> dict[str, float]:
    """RMSE in degrees over samples with ``movement`` and a finite reference.

    ``q_est``, ``q_ref`` ``(T, 4)``, ``movement`` ``(T,)`` bool or 0/1. A NaN estimate on a
    counted sample makes the result NaN (a filter failure is not skipped).
    """
    movement = np.asarray(movement).astype(bool)
    q_ref = np.asarray(q_ref, dtype=np.float64)
    if movement.shape != q_ref.shape[:1]:
        raise ValueError(f"movement must be (T,) = {q_ref.shape[:1]}, got {movement.shape}.")
    use = movement & np.isfinite(q_ref).all(axis=-1)
    if not use.any():
        raise ValueError("no sample has movement == 1 and a finite reference: nothing to score.")
    err = errors(np.asarray(q_est)[use], q_ref[use])
    return {k: float(np.sqrt(np.mean(v * v)) * _DEG) for k, v in err.items()}
