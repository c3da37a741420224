"""TRIAD: the attitude from two vector observations, the raw baseline of the AHRS.

Given two directions known in the world frame, ``r1`` and ``r2`` (gravity and the magnetic
field), and their observations in the body frame, ``b1 ~ R^T r1`` and ``b2 ~ R^T r2``, TRIAD
(Black, 1964) builds an orthonormal triad from each pair::

    t1 = u1,   t2 = (u1 x u2) / |u1 x u2|,   t3 = t1 x t2      (u1, u2: the normalised vectors)

and returns the rotation that maps the body triad onto the world triad,
``R = [t1 t2 t3]_world [t1 t2 t3]_body^T``. The first vector is matched exactly in direction
(use the more accurate sensor, here gravity), the second only fixes the rotation about it.
Noise-free observations give the true ``R``; the result is always a rotation (orthonormal
columns, ``det = +1``), even from noisy observations.

Shapes: ``(*batch, 3)`` vectors in, ``(*batch, 3, 3)`` rotations out; batch dimensions broadcast.
"""

from __future__ import annotations

import torch

__all__ = ["triad", "triad_frame"]


def _unit(v: torch.Tensor) -> torch.Tensor:
    # the clamp only guards an exactly zero vector (probability 0 for noisy data)
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-300)


def triad_frame(first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
    """The orthonormal triad ``[t1 t2 t3]`` (as columns) of two non-collinear vectors.

    ``(*batch, 3), (*batch, 3) -> (*batch, 3, 3)``, a rotation matrix.
    """
    t1 = _unit(first)
    t2 = _unit(torch.linalg.cross(*torch.broadcast_tensors(t1, second)))
    t3 = torch.linalg.cross(t1.expand_as(t2), t2)
    return torch.stack((t1.expand_as(t2), t2, t3), dim=-1)


def triad(
    body_first: torch.Tensor,
    body_second: torch.Tensor,
    world_first: torch.Tensor,
    world_second: torch.Tensor,
) -> torch.Tensor:
    """The rotation ``R`` (body to world) with ``R b1 ~ r1`` and ``R b2 ~ r2``, ``(*batch, 3, 3)``.

    ``body_*`` are the body-frame observations, ``world_*`` the known world-frame directions
    (any positive lengths; only the directions matter).
    """
    world = triad_frame(world_first.to(body_first), world_second.to(body_first))
    return world @ triad_frame(body_first, body_second).transpose(-1, -2)
