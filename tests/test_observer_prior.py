"""The observer's kinematic prior (``propagate``), world-frame vectors (``rotated``) and the
``left`` update rule: an AHRS-shaped observer on SO(3) x R^3 reading (acc, mag) and a gyro."""

from __future__ import annotations

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.inputs import ObserverInputs
from manifold_nets.observer import ResidualObserver

G = Product(SO3(), Euclidean(3), names=("R", "b"))
DT = 0.01
INPUTS = ObserverInputs(rotated={"R": [(0, 3), (3, 6)]}, propagate={"R": (6, 9)}, dt=DT)


def model(rule="residual", inputs=INPUTS, zero=True, seed=0):
    torch.manual_seed(seed)
    obs = ResidualObserver(
        G, 6, 3, hidden_size=8, num_layers=1, inputs=inputs, update={"R": rule}
    ).double()
    if zero:  # the core outputs 0: only the prior moves the estimate
        torch.nn.init.zeros_(obs.core.head.weight)
        torch.nn.init.zeros_(obs.core.head.bias)
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
    assert torch.allclose(
        left._update(x, v)[:, :9].unflatten(-1, (3, 3)), SO3().exp(w) @ R, atol=1e-12
    )
    assert torch.allclose(
        right._update(x, v)[:, :9].unflatten(-1, (3, 3)), R @ SO3().exp(w), atol=1e-12
    )


def test_the_core_reads_the_vectors_rotated_by_the_prediction():
    y, u = data(n=2, t=1)
    obs = model()
    seen = []
    obs.core.register_forward_hook(lambda m, args, out: seen.append(args[0]))
    obs.core.step = lambda inp, h: (seen.append(inp) or torch.zeros(2, 6, dtype=inp.dtype), h)
    obs(y, u)
    inp = seen[0]
    R = SO3().exp(u[:, 0] * DT)  # the prediction from the identity
    assert inp.shape[-1] == 12 + 9 + 6
    assert torch.allclose(inp[:, :9], R.flatten(-2))  # embed of the prediction (b = 0 after)
    assert torch.allclose(inp[:, -6:-3], (R @ y[:, 0, :3, None])[..., 0])
    assert torch.allclose(inp[:, -3:], (R @ y[:, 0, 3:6, None])[..., 0])


def test_the_signature_records_the_prior_and_old_signatures_are_unchanged():
    sig = model().signature()
    assert sig["propagate"] == {"R": [6, 9]} and sig["dt"] == DT
    assert sig["rotated"] == {"R": [[0, 3], [3, 6]]}
    plain = ResidualObserver(G, 6, 3, hidden_size=8, num_layers=1).signature()
    assert "propagate" not in plain and "rotated" not in plain


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"propagate": {"R": (6, 9)}}, "propagate needs dt, the step length in seconds"),
        ({"propagate": {"R": (6, 8)}, "dt": 0.1}, r"propagate\['R'\] = \(6, 8\) must be a span"),
        ({"propagate": {"q": (6, 9)}, "dt": 0.1}, "propagate names a factor 'q'"),
        ({"rotated": {"b": [(0, 3)]}}, r"rotated\['b'\]: the factor must be a rotation of R\^3"),
        ({"rotated": {"R": [(0, 4)]}}, r"rotated\['R'\] span \(0, 4\) must be 3 entries"),
        ({"rotated": {"R": (0, 3)}}, r"must be \(start, stop\) in \(y, u\)"),
    ],
)
def test_bad_prior_or_rotated_settings_say_what_is_wrong(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ResidualObserver(G, 6, 3, hidden_size=8, num_layers=1, inputs=ObserverInputs(**kwargs))


def test_the_train_command_builds_and_load_observer_rebuilds_the_prior(tmp_path):
    """Through the config: an attitude observer (gyro in y[6:9]) with the prior, world-frame
    directions and left updates trains, and its run folder loads into the same observer."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    import manifold_nets_examples.attitude  # noqa: F401  (registers Attitude)
    from manifold_nets import load_observer
    from manifold_nets.cli.train import run

    root = Path(__file__).resolve().parents[1]
    overrides = [
        "experiment=attitude", "debug=tiny", f"dataset.cache_dir={tmp_path / 'data'}",
        "+model.propagate.R=[6,9]", "+model.rotated.R=[[0,3],[3,6]]", "+model.updates.R=left",
    ]
    with initialize_config_dir(config_dir=str(root / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    run(cfg, tmp_path / "run")
    observer, system, _ = load_observer(tmp_path / "run")
    sig = observer.signature()
    assert sig["propagate"] == {"R": [6, 9]} and sig["dt"] == system.dt == 0.1
    assert sig["update"] == ["left", "absolute"]
    data = system.simulate(2, 5, 0.1, torch.Generator().manual_seed(0))
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)


def test_output_scale_multiplies_the_cores_output_and_is_checked():
    y, u = data(n=2, t=3)
    a = model(zero=False, inputs=ObserverInputs())
    torch.manual_seed(0)
    b = ResidualObserver(
        G, 6, 3, hidden_size=8, num_layers=1, update={"R": "residual"}, output_scale=0.5
    ).double()
    b.load_state_dict(a.state_dict())
    x0 = G.identity((2,), dtype=torch.float64)
    step_a = a._step(x0, a.core.initial_hidden(2, dtype=torch.float64),
                     a._context(torch.zeros(2, 9, dtype=torch.float64)))[0]
    step_b = b._step(x0, b.core.initial_hidden(2, dtype=torch.float64),
                     b._context(torch.zeros(2, 9, dtype=torch.float64)))[0]
    # the R^3 factor starts at 0 and is residual: after one step it holds v itself
    assert bool(step_a[:, 9:].abs().min() > 0)
    assert torch.allclose(step_b[:, 9:], step_a[:, 9:] / 2)
    assert b.signature()["output_scale"] == 0.5 and "output_scale" not in a.signature()
    with pytest.raises(ValueError, match="output_scale must be a positive number, got 0"):
        ResidualObserver(G, 6, 3, hidden_size=8, num_layers=1, output_scale=0)
