"""The rigid body on SE(3) (``pose_group="se3"``) against the paper's SO(3) x R^3, and
``apply_noise``: the same motion and measurements for both layouts, accessors, metrics with the
same keys, an observer on SE(3) x R^3 x R^3, the dataset hash of the default, noise-augmented
training."""

from __future__ import annotations

import functools

import pytest
import torch

from manifold_nets_examples.rigid_body import RigidBody
from manifold_nets_examples.rigid_body.system import POSE_GROUPS
from groups import SE3, SO3
from manifold_nets.datasets import dataset_path
from manifold_nets.observer import (
    Embedding, GroupUpdate, Innovation, Measurement, Readings, ResidualObserver,
)
from manifold_nets import GRUCore, MeasurementNoise, TrainSettings
from manifold_nets.training import fit
from tests.observer_checks import randomise_head

F64 = torch.float64
DEFAULT, POSE = RigidBody(), RigidBody(pose_group="se3")
BOTH = pytest.mark.parametrize("system", [DEFAULT, POSE], ids=POSE_GROUPS)
METRIC_KEYS = ["R", "p", "b_omega", "b_v"]


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def parts(system: RigidBody, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return system.rotation(x), system.position(x), system.biases(x)


def convert(x: torch.Tensor, src: RigidBody, dst: RigidBody) -> torch.Tensor:
    return dst.join(*parts(src, x))


def test_groups_and_layouts():
    assert DEFAULT.group.names == ("R", "p", "b_omega", "b_v")
    assert DEFAULT.group.element_shape == (18,)
    assert POSE.group.names == ("T", "b_omega", "b_v") and isinstance(POSE.group.factors[0], SE3)
    assert POSE.group.element_shape == (22,) and POSE.group.embedding_dim == 18
    R = SO3().random((2,), generator=gen(), dtype=F64)
    p, b = torch.randn(2, 3, dtype=F64), torch.randn(2, 6, dtype=F64)
    x = POSE.join(R, p, b)
    T = x[:, :16].unflatten(-1, (4, 4))  # row-major homogeneous [[R, p], [0, 1]]
    assert torch.equal(T[:, :3, :3], R) and torch.equal(T[:, :3, 3], p)
    assert torch.equal(T[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=F64).expand(2, 4))
    assert torch.equal(x[:, 16:], b)
    for system in (DEFAULT, POSE):
        got = parts(system, system.join(R, p, b))
        assert all(torch.equal(g, w) for g, w in zip(got, (R, p, b)))
    # the SE(3) embedding is (vec R, p, b): the default layout
    assert torch.equal(POSE.group.embed(x), DEFAULT.join(R, p, b))


@pytest.mark.parametrize("integrator", ["exact", "rk45"])
@pytest.mark.parametrize("sigma", [0.0, 0.3])
def test_same_simulation_for_both_groups(integrator, sigma):
    n, t = (16, 30) if integrator == "exact" else (2, 4)
    a = RigidBody(integrator=integrator, dt=0.05).simulate(n, t, sigma, gen(3))
    b = RigidBody(integrator=integrator, dt=0.05, pose_group="se3").simulate(n, t, sigma, gen(3))
    assert a.states.shape == (n, t + 1, 18) and b.states.shape == (n, t + 1, 22)
    for pa, pb in zip(parts(DEFAULT, a.states), parts(POSE, b.states)):
        assert torch.equal(pa, pb)
    assert torch.equal(a.measurements, b.measurements)
    assert torch.equal(a.inputs, b.inputs)
    # on SE(3) x R^3 x R^3, bottom row exact
    POSE.group.check_member(b.states)
    bottom = torch.tensor([0.0, 0, 0, 1], dtype=F64)
    assert torch.equal(b.states[..., 12:16], bottom.expand(n, t + 1, 4))
    assert "SE3" in b.meta["group"]


def test_se3_step_is_the_right_action_of_the_body_twist():
    # rollout against step, states on SE(3): tests/test_system_contract.py
    g = gen(4)
    x0 = POSE.sample_initial_state(3, g)
    w = POSE.sample_drive(3, 12, g)
    states = POSE.rollout(x0, w)
    # the step on SE(3) is T exp((v, Omega) dt), the right action of the body twist
    xi = torch.cat((w[:, 0, 3:], w[:, 0, :3]), -1) * POSE.dt
    T1 = x0[:, :16].unflatten(-1, (4, 4)) @ SE3().exp(xi)
    torch.testing.assert_close(states[:, 1, :16], T1.flatten(-2), rtol=0, atol=1e-13)


def _state_pair(n=5, seed=5):
    g = gen(seed)
    x = DEFAULT.sample_initial_state(n, g)
    return x, convert(x, DEFAULT, POSE), DEFAULT.sample_drive(n, 1, g)[:, 0]


def test_step_measure_and_residual_agree_across_layouts():
    x, xs, w = _state_pair()
    noise = 0.2 * torch.randn(5, 12, generator=gen(6), dtype=F64)
    torch.testing.assert_close(
        convert(POSE.step(xs, w), POSE, DEFAULT), DEFAULT.step(x, w), rtol=0, atol=1e-15
    )
    assert torch.equal(POSE.measure(xs, w), DEFAULT.measure(x, w))
    assert torch.equal(POSE.measure(xs, w, noise), DEFAULT.measure(x, w, noise))
    with pytest.raises(ValueError, match=r"\(\*batch, 22\)"):
        POSE.measure(x, w)  # a default-layout state given to the se3 system
    with pytest.raises(ValueError, match=r"\(\*batch, 18\)"):
        DEFAULT.rotation(xs)


@BOTH
def test_state_from_measurement_round_trip(system):
    g = gen(7)
    x = system.sample_initial_state(4, g)
    w = system.sample_drive(4, 1, g)[:, 0]
    y = system.measure(x, w)
    xm = system.state_from_measurement(y)
    system.group.check_member(xm)
    R, p, b = parts(system, xm)
    assert torch.equal(R, system.rotation(x)) and torch.equal(p, system.position(x))
    assert torch.equal(b, torch.zeros_like(b))
    # the measured pose (with zero biases and rates = the biases of x) measures the same pose
    assert torch.equal(system.measure(xm, w)[:, :12], y[:, :12])
    assert system.state_from_measurement(y[None]).shape == (1, 4, *system.group.element_shape)


def test_metrics_and_measurement_errors_agree_across_layouts():
    a = DEFAULT.simulate(6, 10, 0.2, gen(8))
    b = POSE.simulate(6, 10, 0.2, gen(8))
    # estimates off the group (an unconstrained ablation): no membership check
    est_a = a.states + 0.1 * torch.randn(a.states.shape, generator=gen(9), dtype=F64)
    est_b = convert(est_a, DEFAULT, POSE)
    est_b[..., 12:16] += 0.3  # the bottom row of T does not count
    for ea, eb in ((est_a, est_b), (est_a[:, 1:], est_b[:, 1:])):
        ma, mb = DEFAULT.metrics(ea, a), POSE.metrics(eb, b)
        assert list(ma) == METRIC_KEYS and list(mb) == METRIC_KEYS
        for k in METRIC_KEYS:
            assert ma[k].shape == ea.shape[:2]
            torch.testing.assert_close(mb[k], ma[k], rtol=0, atol=1e-15)
    # R is the Frobenius norm of the rotation error, p the position error
    want = torch.linalg.matrix_norm(DEFAULT.rotation(est_a) - DEFAULT.rotation(a.states))
    torch.testing.assert_close(POSE.metrics(est_b, b)["R"], want, rtol=1e-14, atol=0)
    ea, eb = DEFAULT.measurement_errors(a), POSE.measurement_errors(b)
    assert list(ea) == list(eb) == ["R", "p"]
    for k in ea:
        assert torch.equal(ea[k], eb[k]) and bool((ea[k] > 0).all())
    with pytest.raises(ValueError, match="estimates must be"):
        POSE.metrics(est_a, b)  # the default layout given to the se3 system


@BOTH
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_apply_noise_perturbs_the_rotation_on_so3_and_adds_the_rest(system, dtype):
    # measure(x, w, noise) = apply_noise(observe(x, w), noise), zero noise, dtypes and batches of
    # measure: manifold_nets.system.System and tests/test_system_contract.py
    g = gen(10)
    x = system.sample_initial_state(3, g)[:, None].expand(3, 4, -1).to(dtype)
    w = system.sample_drive(3, 4, g).to(dtype)
    noise = (0.5 * torch.randn(3, 4, 12, generator=g, dtype=F64)).to(dtype)
    clean = system.measure(x, w)
    noisy = system.apply_noise(clean, noise)
    assert noisy.dtype == dtype and noisy.shape == (3, 4, 18)
    tol = 1e-12 if dtype == F64 else 1e-6
    # the formula: (vec(R^m exp([w1]x)), p^m + w2, Omega^m + w3, v^m + w4)
    Rm = clean[..., :9].unflatten(-1, (3, 3)) @ SO3().exp(noise[..., :3])
    torch.testing.assert_close(noisy[..., :9], Rm.flatten(-2), rtol=0, atol=tol)
    torch.testing.assert_close(noisy[..., 9:], clean[..., 9:] + noise[..., 3:], rtol=0, atol=tol)
    assert float(SO3().membership_error(noisy[..., :9].unflatten(-1, (3, 3))).max()) < 10 * tol
    # one noise draw broadcast over the batch
    assert system.apply_noise(clean, noise[0, 0]).shape == (3, 4, 18)


def test_apply_noise_checks_shapes():
    # finite gradients at zero noise: tests/test_system_contract.py
    assert DEFAULT.noise_dim == 12
    y = torch.zeros(2, 18, dtype=F64)
    with pytest.raises(ValueError, match=r"noise \(w1, w2, w3, w4\) of shape \(\*batch, 12\)"):
        DEFAULT.apply_noise(y, torch.zeros(2, 6, dtype=F64))
    with pytest.raises(ValueError, match=r"measurements of shape \(\*batch, 18\)"):
        DEFAULT.apply_noise(y[:, :12], torch.zeros(2, 12, dtype=F64))


def test_observer_on_se3_stays_on_the_group():
    data = POSE.simulate(3, 15, 0.1, gen(12))
    torch.manual_seed(0)
    obs = ResidualObserver(
        POSE.group, Measurement(18, factors={"T": (0, 12)}),
        functools.partial(GRUCore, hidden_size=8, num_layers=1),
        update=GroupUpdate({"b_omega": "absolute", "b_v": "absolute"}),
        features=[Embedding(), Readings(), Innovation()],
    )  # fmt: skip
    assert obs.core.input_size == 18 + 18 + 6  # embed(xhat), y, log(That^-1 T^m)
    randomise_head(obs)  # a core made by the observer starts with its output layer at zero
    with torch.no_grad():
        obs.core.head.weight.mul_(5.0)  # steps of about a radian stress the update
        est = obs(data.measurements)
    assert est.shape == data.states.shape and est.dtype == F64
    POSE.group.check_member(est)
    assert float(POSE.group.membership_error(est).max()) < 1e-12
    m = POSE.metrics(est, data)
    assert list(m) == METRIC_KEYS
    assert all(v.shape == (3, 16) and bool(torch.isfinite(v).all()) for v in m.values())


@pytest.mark.parametrize("pose_group", POSE_GROUPS)
def test_noise_augmented_fit_runs(tmp_path, pose_group):
    system = RigidBody(pose_group=pose_group)
    train, val = system.simulate(8, 6, 0.0, gen(13)), system.simulate(4, 6, 0.0, gen(14))
    torch.manual_seed(0)
    model = ResidualObserver(
        system.group, 18, functools.partial(GRUCore, hidden_size=8, num_layers=1)
    )
    settings = TrainSettings(epochs=1, batch_size=4, progress=False)
    noise = MeasurementNoise(system, 0.0, 0.3)
    res = fit(model, train, val, settings, out_dir=tmp_path, transform=noise)
    assert len(res.history) == 2
    assert all(torch.isfinite(torch.tensor(h["val_loss"])) for h in res.history)


def test_config_and_the_dataset_hash_of_the_default():
    keys = {"dt", "integrator", "position_range", "bias_range", "omega_range", "velocity_range"}
    assert set(RigidBody().config()) == keys  # no pose_group: cached datasets keep their hash
    assert set(RigidBody(pose_group="so3_r3").config()) == keys
    assert set(RigidBody(integrator="rk45").config()) == keys | {"rtol", "atol"}
    cfg = POSE.config()
    assert set(cfg) == keys | {"pose_group"} and cfg["pose_group"] == "se3"
    assert RigidBody(**cfg).config() == cfg and "pose_group='se3'" in repr(POSE)
    req = ("cache", 10, 5, 0.1, 0, {"all": 1.0})
    assert dataset_path(RigidBody(pose_group="so3_r3"), *req) == dataset_path(RigidBody(), *req)
    assert dataset_path(POSE, *req) != dataset_path(RigidBody(), *req)


def test_config_file_and_bad_pose_group():
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    system = instantiate(OmegaConf.load("configs/system/rigid_body.yaml"))
    assert system.pose_group == "so3_r3" and system.config() == RigidBody().config()
    for bad in ("SE3", "so3", None):
        with pytest.raises(ValueError, match=r"pose_group must be one of \('so3_r3', 'se3'\)"):
            RigidBody(pose_group=bad)
