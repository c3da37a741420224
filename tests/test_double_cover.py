"""A group with a double cover passes ``groups.testing`` by declaring when two tensors are one
element.

``QuaternionSO3`` is a user's own group, written here by subclassing :class:`~groups.LieGroup`:
SO(3) as unit quaternions ``(w, x, y, z)``, where ``q`` and ``-q`` are the same rotation. Its
``exp`` returns either sign (``w < 0`` beyond an angle of pi), its ``random`` both, its ``log``
picks ``w >= 0``; so ``exp(log(x))`` is ``-x`` for half the elements. It overrides
:meth:`~groups.LieGroup.element_difference` to compare ``q`` with ``-q`` as equal and passes the
whole suite; without that override (the entrywise default) the suite fails it, and a broken
compose still fails with the override in place.
"""

from __future__ import annotations

import pytest
import torch

from groups import LieGroup
from groups.testing import check_group


def _small(dtype: torch.dtype) -> float:
    """Below this angle the Taylor branches are used (float32: 1e-2, float64: 5e-3)."""
    return 1e-2 if dtype == torch.float32 else 5e-3


def _quaternion_product(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    pw, pv, qw, qv = p[..., :1], p[..., 1:], q[..., :1], q[..., 1:]
    pv, qv = torch.broadcast_tensors(pv, qv)
    w = pw * qw - (pv * qv).sum(-1, keepdim=True)
    v = pw * qv + qw * pv + torch.linalg.cross(pv, qv, dim=-1)
    return torch.cat((w, v), -1)


def _to_matrix(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = q.unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def _from_matrix(m: torch.Tensor) -> torch.Tensor:
    """Largest-pivot (Shepperd); not normalised, so a matrix off SO(3) gives a non-unit q."""
    m = m.reshape(*m.shape[:-1], 3, 3)
    d0, d1, d2 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    t = torch.stack((1 + d0 + d1 + d2, 1 + d0 - d1 - d2, 1 - d0 + d1 - d2, 1 - d0 - d1 + d2), -1)
    a, b, c = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    e, f, g = m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] + m[..., 1, 2]
    cand = torch.stack((
        torch.stack((t[..., 0], a, b, c), -1),
        torch.stack((a, t[..., 1], e, f), -1),
        torch.stack((b, e, t[..., 2], g), -1),
        torch.stack((c, f, g, t[..., 3]), -1),
    ), -2)  # fmt: skip
    i = t.argmax(-1, keepdim=True)
    row = cand.gather(-2, i[..., None].expand(*i.shape, 4)).squeeze(-2)
    return row / (2 * t.gather(-1, i).clamp_min(0).sqrt())


class QuaternionSO3(LieGroup):
    """SO(3) as unit quaternions ``(w, x, y, z)``: a double cover (``q`` and ``-q`` are one
    rotation), embedded as the rotation matrix (9 entries, one per element)."""

    element_shape = (4,)
    tangent_dim = 3
    embedding_dim = 9
    angle_slices = (slice(0, 3),)

    def identity(self, batch_shape=(), dtype=torch.float32, device=None):
        self.check_dtype(dtype, "identity")
        e = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype, device=device)
        return e.expand(*batch_shape, 4).clone()

    def compose(self, x, y):
        self.check_pair(x, y, "compose")
        return _quaternion_product(x, y)

    def inverse(self, x):
        self.check_element(x, "inverse")
        return x * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=x.dtype)

    def exp(self, v):
        """``(cos(t/2), sin(t/2) v/t)``: ``w < 0`` for angles beyond pi (the other sign)."""
        self.check_tangent(v, "exp")
        t2 = (v * v).sum(-1, keepdim=True)
        small = t2 < _small(v.dtype) ** 2
        t = torch.where(small, torch.ones_like(t2), t2).sqrt()  # the double-where trick
        w = torch.where(small, 1 - t2 / 8 + t2 * t2 / 384, torch.cos(t / 2))
        s = torch.where(small, 0.5 - t2 / 48 + t2 * t2 / 3840, torch.sin(t / 2) / t)
        return torch.cat((w, s * v), -1)

    def log(self, x):
        """Reads the sign with ``w >= 0`` (angle in ``[0, pi]``), through ``atan2``."""
        self.check_element(x, "log")
        x = torch.where(x[..., :1] < 0, -x, x)
        w, u = x[..., :1], x[..., 1:]
        n2 = (u * u).sum(-1, keepdim=True)
        small = n2 < _small(x.dtype) ** 2
        n = torch.where(small, torch.ones_like(n2), n2).sqrt()
        w_safe = torch.where(small, w, torch.ones_like(w))
        r2 = n2 / (w_safe * w_safe)  # atan(r) / r = 1 - r^2/3 + r^4/5
        series = 2 / w_safe * (1 - r2 / 3 + r2 * r2 / 5)
        return torch.where(small, series, 2 * torch.atan2(n, w) / n) * u

    def embed(self, x):
        self.check_element(x, "embed")
        return _to_matrix(x).flatten(-2)

    def unembed(self, z):
        self.check_shape(z, (9,), "unembed", "an embedded element")
        return _from_matrix(z)

    def membership_error(self, x):
        self.check_element(x, "membership_error")
        return (torch.linalg.vector_norm(x, dim=-1) - 1).abs()

    def adjoint(self, x):
        self.check_element(x, "adjoint")
        return _to_matrix(x)

    def random(self, batch_shape=(), generator=None, dtype=torch.float32, device=None):
        """Haar: a normalised Gaussian quaternion, of either sign."""
        self.check_dtype(dtype, "random")
        q = torch.randn(*batch_shape, 4, generator=generator, dtype=dtype, device=device)
        return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)

    def element_difference(self, x, y):
        """``x - s y`` with ``s = +-1`` the sign of ``<x, y>``: ``q`` and ``-q`` are equal."""
        s = torch.where((x * y).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(x.dtype)
        return x - s * y


class EntrywiseQuaternionSO3(QuaternionSO3):
    """The same group without the override: elements compared entry by entry (the default)."""

    def element_difference(self, x, y):
        return LieGroup.element_difference(self, x, y)


class WrongComposeQuaternionSO3(QuaternionSO3):
    """A sign typo in the scalar part of the product."""

    def compose(self, x, y):
        self.check_pair(x, y, "compose")
        good = _quaternion_product(x, y)
        wrong_w = x[..., :1] * y[..., :1] + (x[..., 1:] * y[..., 1:]).sum(-1, keepdim=True)
        return torch.cat((wrong_w, good[..., 1:]), -1)


def test_the_quaternion_group_passes_the_whole_suite() -> None:
    results = check_group(QuaternionSO3(), max_examples=5)
    assert results and all(r.worst_ratio <= 1.0 for r in results if not r.skipped)


def test_exp_returns_either_sign_and_the_suite_still_compares_rotations() -> None:
    G = QuaternionSO3()
    v = torch.tensor([[0.0, 0.0, 4.0]], dtype=torch.float64)  # beyond pi: w < 0
    q = G.exp(v)
    assert q[0, 0] < 0
    back = G.exp(G.log(q))
    assert torch.allclose(back, -q)  # the other sign of the same rotation
    assert G.element_difference(back, q).abs().max() < 1e-12
    assert torch.allclose(G.embed(back), G.embed(q))


def test_without_the_override_the_suite_fails_the_correct_group() -> None:
    """The control: compared entry by entry, ``exp(log(x))`` is ``-x`` for half the elements.
    Message: ``property 'exp_log' fails for EntrywiseQuaternionSO3() in torch.float32 ...:
    exp(log(x)) == x: worst error ... (relative) > tolerance 5e-06 at batch index ...``"""
    with pytest.raises(AssertionError) as info:
        check_group(EntrywiseQuaternionSO3(), checks=["exp_log"], max_examples=5)
    assert "property 'exp_log' fails for EntrywiseQuaternionSO3() in torch.float32" in str(
        info.value
    )
    assert "exp(log(x)) == x: worst error" in str(info.value)


def test_a_wrong_compose_still_fails_with_the_override() -> None:
    """Message: ``check_group(WrongComposeQuaternionSO3()): 10 check(s) failed. ...
    - property 'associativity' fails for WrongComposeQuaternionSO3() in torch.float32 on the
    adversarial grid (batch shape (72,)): compose(compose(x, y), z) == compose(x, compose(y,
    z)): worst error 0.124 (relative) > tolerance 5e-06 at batch index (50,)``, followed by
    x, y and z there."""
    with pytest.raises(AssertionError) as info:
        check_group(WrongComposeQuaternionSO3(), max_examples=3)
    msg = str(info.value)
    assert msg.startswith("check_group(WrongComposeQuaternionSO3()): ")
    assert (
        "- property 'associativity' fails for WrongComposeQuaternionSO3() in torch.float32 on "
        "the adversarial grid (batch shape (72,)): compose(compose(x, y), z) == compose(x, "
        "compose(y, z)): worst error 0.124 (relative) > tolerance 5e-06 at batch index (50,)"
    ) in msg
    assert "compose(x, inverse(x)) == identity: worst error" in msg
