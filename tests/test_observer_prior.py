"""The observer's kinematic prior (``KinematicPrior``), world-frame vectors (the ``Rotated``
feature), the ``left`` update rule and the output scale (``OutputScale``): an AHRS-shaped
observer on SO(3) x R^3 reading (acc, mag) and a gyro."""

from __future__ import annotations

import functools

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.builders import build_piece
from manifold_nets.cores import GRUCore
from manifold_nets.observer import (
    Embedding,
    GroupUpdate,
    KinematicPrior,
    Measurement,
    OutputScale,
    Readings,
    ResidualObserver,
    Rotated,
)

G = Product(SO3(), Euclidean(3), names=("R", "b"))
DT = 0.01
VECTORS = {"R": [(0, 3), (3, 6)]}
GYRO = {"R": (6, 9)}


def model(rule="residual", prior=True, rotated=True, zero=True, seed=0, scales=()):
    """The AHRS observer, y = (acc, mag), u = gyro, a 1 x 8 GRU core; ``zero``: the core's
    output layer at zero, where a core the observer makes starts (only the prior moves the
    estimate), else random."""
    torch.manual_seed(seed)
    obs = ResidualObserver(
        G, Measurement(6, 3), functools.partial(GRUCore, hidden_size=8, num_layers=1),
        update=GroupUpdate({"R": rule}), prior=KinematicPrior(GYRO, DT) if prior else None,
        features=[Embedding(), Readings()] + ([Rotated(VECTORS)] if rotated else []),
        scales=scales,
    ).double()
    assert torch.count_nonzero(obs.core.head.weight) == 0
    if not zero:
        with torch.no_grad():
            obs.core.head.reset_parameters()
    return obs


def data(n=3, t=20, seed=1):
    g = torch.Generator().manual_seed(seed)
    y = torch.randn(n, t, 6, generator=g, dtype=torch.float64)
    u = torch.randn(n, t, 3, generator=g, dtype=torch.float64)
    return y, u


def test_a_zero_correction_integrates_the_measured_velocity_exactly():
    y, u = data()
    est = model()(y, u)
    R = torch.eye(3, dtype=torch.float64).expand(3, 3, 3)
    for k in range(y.shape[1]):
        R = R @ SO3().exp(u[:, k] * DT)
        assert torch.allclose(est[:, k + 1, :9].unflatten(-1, (3, 3)), R, atol=1e-12)
    assert bool((est[..., 9:] == 0).all())  # b has no prior: it stays


@pytest.mark.parametrize("rule", ["residual", "left"])
def test_rollout_and_online_steps_agree_and_stay_on_the_group(rule):
    y, u = data()
    obs = model(rule, zero=False)
    est = obs(y, u)
    state = obs.init_state(3)
    for k in range(y.shape[1]):
        state = obs.step(state, y[:, k], u[:, k])
        assert torch.allclose(state.estimate, est[:, k + 1], atol=1e-12)
    G.check_member(est[:, -1].detach())
    step = obs.online_step_module()
    x, *hidden = step.initial_state(3)
    for k in range(y.shape[1]):
        x, *hidden = step(x, *hidden, y[:, k], u[:, k])
    assert torch.allclose(x, est[:, -1].reshape(3, -1), atol=1e-12)


def test_left_and_residual_updates_differ_by_the_frame_of_the_correction():
    x = G.random((4,), dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    v = 0.1 * torch.randn(4, 6, dtype=torch.float64)
    left, right = model("left"), model("residual")
    R, w = x[:, :9].unflatten(-1, (3, 3)), v[:, :3]
    assert left.update.rules == ("left", "residual")
    assert torch.allclose(
        left.update(x, v)[:, :9].unflatten(-1, (3, 3)), SO3().exp(w) @ R, atol=1e-12
    )
    assert torch.allclose(
        right.update(x, v)[:, :9].unflatten(-1, (3, 3)), R @ SO3().exp(w), atol=1e-12
    )


def test_the_core_reads_the_vectors_rotated_by_the_prediction():
    y, u = data(n=2, t=1)
    obs = model()
    seen = []
    obs.core.step = lambda inp, h: (seen.append(inp) or torch.zeros(2, 6, dtype=inp.dtype), h)
    obs(y, u)
    inp = seen[0]
    R = SO3().exp(u[:, 0] * DT)  # the prediction from the identity
    assert inp.shape[-1] == 12 + 9 + 6
    assert [f.width for f in obs.features] == [12, 9, 6]
    assert torch.allclose(inp[:, :9], R.flatten(-2))  # embed of the prediction (b = 0 after)
    assert torch.allclose(inp[:, -6:-3], (R @ y[:, 0, :3, None])[..., 0])
    assert torch.allclose(inp[:, -3:], (R @ y[:, 0, 3:6, None])[..., 0])


def test_the_signature_records_the_prior_and_the_feature():
    sig = model().signature()
    assert sig["prior"] == {"type": "kinematic", "velocities": {"R": [6, 9]}, "dt": DT}
    assert sig["features"][-1] == {"type": "rotated", "vectors": {"R": [[0, 3], [3, 6]]}}
    plain = model(prior=False, rotated=False).signature()
    assert plain["prior"] == {"type": "none"}
    assert plain["features"] == [{"type": "embedding"}, {"type": "readings"}]


def _build(prior=None, features=()):
    return ResidualObserver(G, Measurement(6, 3), prior=prior,
                            features=[Embedding(), Readings(), *features])


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: KinematicPrior(GYRO, 0), r"kinematic prior: dt must be a number .* \(the step "
                                          "length in seconds"),
        (lambda: KinematicPrior(GYRO, -0.1), "kinematic prior: dt must be a number"),
        (lambda: KinematicPrior({}, 0.1), "kinematic prior: name at least one factor"),
        (lambda: KinematicPrior({"R": 6}, 0.1),
         r"kinematic prior: velocities\['R'\] must be \(start, stop\) in \(y, u\)"),
        (lambda: _build(KinematicPrior({"R": (6, 8)}, 0.1)),
         r"kinematic prior: velocities\['R'\] = \(6, 8\) must be a span"),
        (lambda: _build(KinematicPrior({"R": (7, 10)}, 0.1)),
         r"velocities\['R'\] = \(7, 10\) must be a span of \(y, u\) \(size 9\)"),
        (lambda: _build(KinematicPrior({"q": (6, 9)}, 0.1)),
         "kinematic prior: velocities names a factor 'q'"),
        (lambda: _build(features=[Rotated({"b": [(0, 3)]})]),
         r"rotated: vectors\['b'\]: the factor must be a rotation of R\^3"),
        (lambda: _build(features=[Rotated({"R": [(0, 4)]})]),
         r"rotated: span \(0, 4\) must be 3 entries"),
        (lambda: _build(features=[Rotated({"R": [(6, 9), (7, 10)]})]),
         r"rotated: span \(7, 10\) must be 3 entries of \(y, u\) \(size 9\)"),
        (lambda: Rotated({"R": (0, 3)}), r"rotated: vectors\['R'\]: 0 is not \(start, stop\)"),
        (lambda: Rotated({}), "rotated: name a rotation factor and its vectors' spans"),
        (lambda: _build(features=[Rotated({"q": [(0, 3)]})]),
         "rotated: vectors names a factor 'q'"),
    ],
)
def test_bad_prior_or_rotated_settings_say_what_is_wrong(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_bad_blocks_name_where_they_are():
    with pytest.raises(ValueError, match=r"model.prior \(kinematic\): needs \['dt'\]"):
        build_piece("prior", {"type": "kinematic", "velocities": {"R": [6, 9]}}, "model.prior")
    with pytest.raises(ValueError, match=r"model.features\[2\] \(rotated\): rotated: name a "
                                         "rotation factor"):
        build_piece("feature", {"type": "rotated", "vectors": {}}, "model.features[2]")
    prior = build_piece("prior", {"type": "kinematic", "velocities": {"R": [6, 9]}},
                        "model.prior", {"dt": 0.1})
    assert prior.settings() == {"velocities": {"R": [6, 9]}, "dt": 0.1}


def test_the_train_command_builds_and_load_observer_rebuilds_the_prior(tmp_path):
    """Through the config: an attitude observer (gyro in y[6:9]) with the kinematic prior,
    world-frame directions and left updates trains, and its run folder loads into the same
    observer."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    import manifold_nets_examples.attitude  # noqa: F401  (registers Attitude)
    from manifold_nets import load_observer
    from manifold_nets.cli.train import run

    root = Path(__file__).resolve().parents[1]
    overrides = [
        "experiment=attitude", "debug=tiny", f"dataset.cache_dir={tmp_path / 'data'}",
        "++model.prior={type:kinematic,velocities:{R:[6,9]}}",
        "++model.features=[embedding,readings,{type:rotated,vectors:{R:[[0,3],[3,6]]}}]",
        "+model.updates.R=left",
    ]
    with initialize_config_dir(config_dir=str(root / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    run(cfg, tmp_path / "run")
    observer, system, _ = load_observer(tmp_path / "run")
    sig = observer.signature()
    assert sig["prior"] == {"type": "kinematic", "velocities": {"R": [6, 9]}, "dt": 0.1}
    assert system.dt == 0.1
    assert sig["features"][-1] == {"type": "rotated", "vectors": {"R": [[0, 3], [3, 6]]}}
    assert sig["update"] == ["left", "absolute"]
    data = system.simulate(2, 5, 0.1, torch.Generator().manual_seed(0))
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)


def test_output_scale_multiplies_the_cores_output_and_is_checked():
    y = torch.zeros(2, 6, dtype=torch.float64)
    u = torch.zeros(2, 3, dtype=torch.float64)
    a = model(prior=False, rotated=False, zero=False)
    b = model(prior=False, rotated=False, zero=False, scales=[OutputScale(0.5)])
    b.load_state_dict(a.state_dict())
    step_a = a.step(a.init_state(2), y, u).estimate
    step_b = b.step(b.init_state(2), y, u).estimate
    # the R^3 factor starts at 0 and is residual: after one step it holds v itself
    assert bool(step_a[:, 9:].abs().min() > 0)
    assert torch.allclose(step_b[:, 9:], step_a[:, 9:] / 2)
    assert b.signature()["scales"] == [{"type": "output", "scale": 0.5}]
    assert a.signature()["scales"] == []
    for bad in (0, -1.0, True, "0.5"):
        with pytest.raises(ValueError, match=r"output scale must be a number .*\(> 0\)"):
            OutputScale(bad)
    with pytest.raises(ValueError, match=r"model.scales\[0\] \(output\): output scale must be"):
        build_piece("scale", {"type": "output", "scale": 0}, "model.scales[0]")
