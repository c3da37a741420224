"""The BROAD metric on cases computed by hand, and the quaternion helpers against scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from manifold_nets_examples.broad.metric import (
    errors,
    matrix_to_quat,
    quat_multiply,
    quat_to_matrix,
    rmse,
)


def _axis_angle(axis, deg) -> np.ndarray:
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    h = math.radians(deg) / 2
    return np.array([math.cos(h), *(math.sin(h) * axis)])


def _rand_quats(n, seed=0) -> np.ndarray:
    xyzw = Rotation.random(n, random_state=seed).as_quat()
    return np.concatenate((xyzw[:, 3:], xyzw[:, :3]), axis=1)


def _deg(err):
    return {k: math.degrees(float(v[0])) for k, v in err.items()}


@pytest.mark.parametrize("seed", [0, 1])
def test_pure_heading_error(seed):
    ref = _rand_quats(1, seed)
    est = quat_multiply(_axis_angle([0, 0, 1], 10), ref)  # error in the reference frame
    e = _deg(errors(est, ref))
    assert e["total"] == pytest.approx(10) and e["heading"] == pytest.approx(10)
    assert e["inclination"] == pytest.approx(0, abs=1e-6)


def test_pure_tilt_error():
    ref = _rand_quats(1, 2)
    est = quat_multiply(_axis_angle([1, 0, 0], 5), ref)
    e = _deg(errors(est, ref))
    assert e["total"] == pytest.approx(5) and e["inclination"] == pytest.approx(5)
    assert e["heading"] == pytest.approx(0, abs=1e-6)


def test_combined_heading_then_tilt():
    # q_e = tilt(x, 4) * heading(z, 3): w = cos2 cos1.5, z = cos2 sin1.5, so the heading is 3
    # and the inclination 4 exactly; the total is the angle of the product
    qe = quat_multiply(_axis_angle([1, 0, 0], 4), _axis_angle([0, 0, 1], 3))
    ref = _rand_quats(1, 3)
    e = _deg(errors(quat_multiply(qe, ref), ref))
    assert e["heading"] == pytest.approx(3) and e["inclination"] == pytest.approx(4)
    total = 2 * math.degrees(math.acos(math.cos(math.radians(2)) * math.cos(math.radians(1.5))))
    assert e["total"] == pytest.approx(total)


def test_half_turn_heading_and_sign():
    ref = _rand_quats(4, 4)
    est = quat_multiply(_axis_angle([0, 0, 1], 180), ref)
    e = errors(est, ref)
    assert np.allclose(e["heading"], math.pi) and np.allclose(e["total"], math.pi)
    e1, e2 = errors(est, ref), errors(-est, ref)
    for k in e1:
        assert np.allclose(e1[k], e2[k])
    same = errors(ref, -ref)
    assert all(np.allclose(v, 0, atol=1e-7) for v in same.values())


def test_rmse_skips_nan_and_respects_movement():
    ref = _rand_quats(4, 5)
    angles = [10, 20, 30, 40]
    est = np.stack([quat_multiply(_axis_angle([0, 0, 1], a), r) for a, r in zip(angles, ref)])
    ref[1] = np.nan
    movement = np.array([1, 1, 0, 1])
    r = rmse(est, ref, movement)
    want = math.sqrt((10**2 + 40**2) / 2)
    assert r["total"] == pytest.approx(want) and r["heading"] == pytest.approx(want)
    assert r["inclination"] == pytest.approx(0, abs=1e-5)
    with pytest.raises(ValueError, match="nothing to score"):
        rmse(est, ref, np.array([0, 1, 0, 0]))
    est[0] = np.nan
    assert math.isnan(rmse(est, ref, movement)["total"])


def test_quaternion_helpers_match_scipy():
    q = _rand_quats(200, 6)
    R = quat_to_matrix(q)
    xyzw = np.concatenate((q[:, 1:], q[:, :1]), axis=1)
    assert np.allclose(R, Rotation.from_quat(xyzw).as_matrix(), atol=1e-12)
    back = matrix_to_quat(R)
    assert np.allclose(np.abs((back * q).sum(1)), 1.0, atol=1e-12)
    assert (back[:, 0] >= 0).all()
    # near-pi rotations (small w) use another pivot
    for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]):
        qq = _axis_angle(axis, 179.999)
        assert abs(abs(np.dot(matrix_to_quat(quat_to_matrix(qq)), qq)) - 1) < 1e-12
