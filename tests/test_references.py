"""The shipped matrix groups against independent references, not against themselves.

* SO(3) ``exp``/``log`` against ``scipy.spatial.transform.Rotation``.
* ``exp`` of SO(2), SO(3), SE(2), SE(3), SE_2(3) against ``torch.linalg.matrix_exp(hat(v))`` in
  float64, including a small rotation with a large translation (where a wrong ``V ~ R`` Taylor
  branch would be off by ``|omega| |rho| / 2``).
* Closed-form ``inverse`` against ``torch.linalg.inv``; closed-form ``adjoint`` against the
  generic autograd adjoint of :class:`groups.LieGroup` and against ``vee(x hat(v) x^-1)``.
* ``torch.autograd.gradcheck`` of ``exp`` and ``log``; float32 gradients against float64 ones;
  finite gradients at exactly ``theta = 0`` and ``theta = pi``.

Rotation angles are placed on each group's ``angle_slices`` at Theseus' adversarial list
(0, 1e-8, 1e-5, 3e-3, 1e-2, pi - 1e-7, pi) and at random.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from groups import (
    SE2,
    SE3,
    SE23,
    SO2,
    SO3,
    GroupMembershipError,
    LieGroup,
    MatrixLieGroup,
)
from groups.se3 import rotation_and_left_jacobian
from groups.so3 import left_jacobian, left_jacobian_inverse

ADVERSARIAL = (0.0, 1e-8, 1e-5, 3e-3, 1e-2, math.pi - 1e-7, math.pi)
GROUPS = [SO2(), SO3(), SE2(), SE3(), SE23()]
POSES = [SE2(), SE3(), SE23()]
DTYPES = [torch.float32, torch.float64]
ids = repr


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _tangent(
    group: MatrixLieGroup,
    angles,
    translation: float = 1.0,
    dtype: torch.dtype = torch.float64,
    seed: int = 0,
) -> torch.Tensor:
    """Tangent vectors ``(len(angles), tangent_dim)``: rotation of norm ``angles[i]`` about a
    random axis, every other coordinate standard normal times ``translation``."""
    g = _gen(seed)
    angles = torch.as_tensor(angles, dtype=torch.float64)
    v = translation * torch.randn(len(angles), group.tangent_dim, generator=g, dtype=torch.float64)
    for s in group.angle_slices:
        axis = torch.randn(len(angles), s.stop - s.start, generator=g, dtype=torch.float64)
        if s.stop - s.start == 1:
            axis = axis.sign()
        axis = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
        v[:, s] = angles.unsqueeze(-1) * axis
    return v.to(dtype)


def _random_angles(n: int, high: float, seed: int = 1) -> list[float]:
    return (high * torch.rand(n, generator=_gen(seed), dtype=torch.float64)).tolist()


def _with_rotation(group: MatrixLieGroup, rot: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """An element whose rotation block is ``rot`` (``(*batch, k, k)``), translations random.

    Every group here embeds as ``(vec R, translations...)``, so the element is ``unembed`` of
    that concatenation; built this way an exactly-pi rotation stays exact.
    """
    extra = group.embedding_dim - rot.shape[-1] ** 2
    t = torch.randn(*rot.shape[:-2], extra, generator=_gen(seed), dtype=torch.float64)
    return group.unembed(torch.cat((rot.flatten(-2), t.to(rot.dtype)), dim=-1))


def _rotation_side(group: MatrixLieGroup) -> int:
    """Side of the rotation block: 2 for SO(2) and SE(2), 3 otherwise."""
    return 2 if isinstance(group, (SO2, SE2)) else 3


def _exact_rotations(group: MatrixLieGroup, dtype: torch.dtype) -> torch.Tensor:
    """Rotation blocks at exactly 0 and exactly pi (about the coordinate axes), ``(n, k, k)``."""
    if _rotation_side(group) == 2:
        diags = [(1.0, 1.0), (-1.0, -1.0)]
    else:
        diags = [(1.0, 1.0, 1.0), (1.0, -1.0, -1.0), (-1.0, 1.0, -1.0), (-1.0, -1.0, 1.0)]
    return torch.diag_embed(torch.tensor(diags, dtype=dtype))


# --------------------------------------------------------------------------- SO(3) vs scipy


def test_so3_exp_matches_scipy():
    angles = list(ADVERSARIAL) + _random_angles(64, math.pi)
    w = _tangent(SO3(), angles)
    ref = Rotation.from_rotvec(w.numpy()).as_matrix()
    np.testing.assert_allclose(SO3().exp(w).numpy(), ref, rtol=0, atol=1e-14)


def test_so3_log_matches_scipy():
    angles = list(ADVERSARIAL[:-1]) + _random_angles(64, math.pi)
    mats = Rotation.from_rotvec(_tangent(SO3(), angles).numpy()).as_matrix()
    mats = np.concatenate((mats, Rotation.random(64, random_state=3).as_matrix()))
    ref = Rotation.from_matrix(mats).as_rotvec()
    np.testing.assert_allclose(SO3().log(torch.from_numpy(mats)).numpy(), ref, rtol=0, atol=1e-12)


def test_so3_log_at_pi_is_a_valid_preimage():
    """At pi the sign of the axis is ambiguous: check exp(log R) == R and |log R| == pi."""
    mats = Rotation.from_rotvec(_tangent(SO3(), [math.pi] * 16).numpy()).as_matrix()
    r = torch.cat((torch.from_numpy(mats), _exact_rotations(SO3(), torch.float64)[1:]))
    w = SO3().log(r)
    torch.testing.assert_close(SO3().exp(w), r, rtol=0, atol=1e-12)
    torch.testing.assert_close(
        torch.linalg.vector_norm(w, dim=-1), torch.full((len(r),), math.pi, dtype=r.dtype)
    )


def test_pose_rotation_and_left_jacobian_match_so3():
    """The pose exps share coefficients between R and J_l; they must equal SO(3)'s own."""
    w = _tangent(SO3(), list(ADVERSARIAL) + _random_angles(16, math.pi))
    r, jac = rotation_and_left_jacobian(w)
    torch.testing.assert_close(r, SO3().exp(w), rtol=0, atol=1e-15)
    torch.testing.assert_close(jac, left_jacobian(w), rtol=0, atol=1e-15)
    torch.testing.assert_close(jac @ left_jacobian_inverse(w), torch.eye(3).double().expand_as(jac))


# --------------------------------------------------------------------------- exp vs matrix_exp


@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_exp_matches_matrix_exp(group):
    v = _tangent(group, list(ADVERSARIAL) + _random_angles(32, math.pi))
    ref = torch.linalg.matrix_exp(group.hat(v))
    torch.testing.assert_close(group.exp(v), ref, rtol=0, atol=1e-13)


@pytest.mark.parametrize("group", POSES, ids=ids)
@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-6, 1e-5, 1e-4, 1e-3, 3e-3, 1e-2, 0.3])
def test_exp_small_rotation_large_translation(group, angle):
    """|omega| small, |rho| = 1e3. The reference uses that the translation column of
    ``exp`` is linear in ``rho``: ``matrix_exp`` of ``hat(rho / s, omega)`` (well scaled, so
    ``matrix_exp`` is accurate), with its translation columns multiplied by ``s`` afterwards."""
    s = 1e3
    k = group.angle_slices[0].start  # translations come first
    v = _tangent(group, [angle] * 16)
    v[:, :k] *= s / torch.linalg.vector_norm(v[:, :k], dim=-1, keepdim=True)
    unit = v.clone()
    unit[:, :k] /= s
    ref = torch.linalg.matrix_exp(group.hat(unit))
    r = _rotation_side(group)
    ref[:, :r, r:] *= s
    x = group.exp(v)
    torch.testing.assert_close(x, ref, rtol=0, atol=1e-12 * s)
    # A Taylor branch using R in place of V would miss |omega| |rho| / 2 here.
    torch.testing.assert_close(group.log(x), v, rtol=0, atol=1e-12 * s)


@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_float32_matches_float64(group):
    """The float32 series/closed-form switch is accurate to float32 rounding on both sides."""
    v = _tangent(group, list(ADVERSARIAL[:-1]) + _random_angles(16, math.pi - 1e-3))
    x64 = group.exp(v)
    x32 = group.exp(v.float())
    torch.testing.assert_close(x32.double(), x64, rtol=0, atol=1e-5)
    torch.testing.assert_close(group.log(x64.float()).double(), group.log(x64), rtol=0, atol=1e-5)


# --------------------------------------------------------------------------- log inside the radius


@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_log_inverts_exp_inside_injectivity_radius(group):
    v = _tangent(group, list(ADVERSARIAL[:-1]) + _random_angles(64, math.pi))
    torch.testing.assert_close(group.log(group.exp(v)), v, rtol=0, atol=1e-12)


@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_exp_log_at_pi(group):
    """At exactly pi, log is a preimage (the sign is ambiguous): exp(log x) == x."""
    x = _with_rotation(group, _exact_rotations(group, torch.float64)[1:])
    x = torch.cat((x, group.exp(_tangent(group, [math.pi] * 8))))
    w = group.log(x)
    torch.testing.assert_close(group.exp(w), x, rtol=0, atol=1e-12)
    for s in group.angle_slices:
        norm = torch.linalg.vector_norm(w[:, s], dim=-1)
        torch.testing.assert_close(norm, torch.full_like(norm, math.pi), rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- inverse and adjoint


@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_inverse_matches_linalg_inv(group):
    x = group.random((4, 8), generator=_gen(), dtype=torch.float64)
    x_inv = group.inverse(x)
    torch.testing.assert_close(x_inv, torch.linalg.inv(x), rtol=0, atol=1e-12)
    torch.testing.assert_close(group.compose(x, x_inv), group.identity((4, 8), torch.float64))


@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_adjoint_matches_generic_and_conjugation(group):
    x = group.random((3, 4), generator=_gen(), dtype=torch.float64)
    ad = group.adjoint(x)
    assert ad.shape == (3, 4, group.tangent_dim, group.tangent_dim)
    torch.testing.assert_close(ad, LieGroup.adjoint(group, x), rtol=0, atol=1e-12)
    torch.testing.assert_close(ad, MatrixLieGroup.adjoint(group, x), rtol=0, atol=1e-12)
    # x exp(v) x^-1 == exp(Ad_x v), for v of any size (not only near 0).
    v = _tangent(group, _random_angles(12, 3.0)).unflatten(0, (3, 4))
    lhs = group.compose(group.compose(x, group.exp(v)), group.inverse(x))
    rhs = group.exp((ad @ v.unsqueeze(-1)).squeeze(-1))
    torch.testing.assert_close(lhs, rhs, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- gradients

GRAD_ANGLES = [0.0, 1e-3, 0.5, 2.0, 3.0]  # 1e-3 lies in the float64 series branch


@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_gradcheck_exp(group):
    v = _tangent(group, GRAD_ANGLES).requires_grad_()
    assert torch.autograd.gradcheck(group.exp, (v,))


@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_gradcheck_log(group):
    """Finite differences move off the group; log is a smooth function of the entries there."""
    x = group.exp(_tangent(group, GRAD_ANGLES)).requires_grad_()
    assert torch.autograd.gradcheck(group.log, (x,))


def _grad(fn, inp: torch.Tensor, seed: int = 5) -> torch.Tensor:
    inp = inp.detach().clone().requires_grad_()
    out = fn(inp)
    weights = torch.randn(out.shape, generator=_gen(seed), dtype=torch.float64).to(out.dtype)
    (grad,) = torch.autograd.grad((out * weights).sum(), inp)
    return grad


@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_float32_gradients_match_float64(group):
    """Near the series thresholds float32 autograd of a closed form goes wrong; ours must not."""
    angles = [1e-5, 1e-3, 3e-3, 9e-3, 1.1e-2, 0.1, 0.26, 1.0]
    v = _tangent(group, angles)
    g64 = _grad(group.exp, v)
    g32 = _grad(group.exp, v.float())
    torch.testing.assert_close(g32.double(), g64, rtol=0, atol=1e-4)
    x = group.exp(v)
    torch.testing.assert_close(
        _grad(group.log, x.float()).double(), _grad(group.log, x), rtol=0, atol=1e-4
    )


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_gradients_finite_at_zero_and_pi(group, dtype):
    v = _tangent(group, [0.0, math.pi], dtype=dtype)
    v[:, group.angle_slices[0]] = 0.0
    v[1, group.angle_slices[0].start] = math.pi  # exactly pi (in dtype) about a coordinate axis
    for fn, inp in (
        (group.exp, v),
        (lambda t: group.log(group.exp(t)), v),
        (group.log, _with_rotation(group, _exact_rotations(group, dtype))),
    ):
        grad = _grad(fn, inp)
        assert torch.isfinite(grad).all(), (group, dtype, grad)


# ------------------------------------------------------------------ random, membership, errors


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_random_is_haar_rotation_and_normal_translation(group, dtype):
    for shape in [(), (2, 3)]:
        x = group.random(shape, generator=_gen(), dtype=dtype)
        assert x.shape == (*shape, *group.element_shape) and x.dtype == dtype
        group.check_member(x)
    z = group.embed(group.random((20000,), generator=_gen(), dtype=dtype)).double()
    r2 = _rotation_side(group) ** 2
    # Under the Haar measure of SO(n) the mean rotation matrix is 0 (an exp of a standard normal
    # tangent vector would concentrate near I: mean diagonal ~0.2 to 0.4).
    assert z[:, :r2].mean(0).abs().max() < 0.03
    if group.embedding_dim > r2:
        t = z[:, r2:]
        torch.testing.assert_close(t.mean(0), torch.zeros_like(t[0]), rtol=0, atol=0.04)
        torch.testing.assert_close(t.std(0), torch.ones_like(t[0]), rtol=0, atol=0.04)



@pytest.mark.parametrize("group", POSES, ids=ids)
def test_membership_error_sees_rotation_and_bottom_rows(group):
    x = group.random((5,), generator=_gen(), dtype=torch.float64)
    assert group.membership_error(x).max() < 1e-12
    group.check_member(x)
    bad_row = x.clone()
    bad_row[:, -1, 0] = 0.1
    reflected = x.clone()
    reflected[:, 0, : _rotation_side(group)] *= -1  # a reflection: R R^T = I but det R = -1
    for bad in (bad_row, reflected):
        assert (group.membership_error(bad) > 0.09).all()
        with pytest.raises(GroupMembershipError):
            group.check_member(bad)
    with pytest.raises(GroupMembershipError):
        group.from_embedding(torch.full((group.embedding_dim,), float("nan"), dtype=torch.float64))


@pytest.mark.parametrize("group", GROUPS, ids=ids)
def test_bad_shapes_name_the_expected_shape(group):
    d, k = group.matrix_dim, group.tangent_dim
    with pytest.raises(ValueError, match=rf"\(\*batch, {k}\)"):
        group.exp(torch.zeros(2, k + 1))
    with pytest.raises(ValueError, match=rf"\(\*batch, {d}, {d}\)"):
        group.log(torch.zeros(2, d + 1, d + 1))
    with pytest.raises(TypeError, match="floating-point"):
        group.exp(torch.zeros(2, k, dtype=torch.int64))
