"""The gain head (``model.gain=true``): the core outputs an offset ``a`` and a gain ``K`` and the
observer's update is ``v = a + K nu``, ``nu`` the innovation it reads. Pinned: the update is that
product, exactly, for a core with known outputs; ``K`` starts at zero in a GRU core; the rollout,
the online step and the exported step agree; the gradient reaches ``K``; the signature records
it; bad settings say what is wrong; the train command trains and reloads it."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from groups import SO3, Euclidean, Product
from manifold_nets.builders import build_observer
from manifold_nets.checkpoint import CheckpointError, check_signature, load_weights, save_checkpoint
from manifold_nets.config import ModelConfig
from manifold_nets.cores import RecurrentCore
from manifold_nets.inputs import ObserverInputs
from manifold_nets.observer import ObserverState, ResidualObserver, core_output_size
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load


def simulate(system, n=4, t=30, sigma=0.0, seed=1):
    return system.simulate(n, t, sigma, torch.Generator().manual_seed(seed))


def rigid_model(**changes) -> ModelConfig:
    base = dict(
        hidden_size=16, num_layers=1, innovation={"R": [0, 9], "p": [9, 12]},
        relative_only=["p"], prior="system", updates={}, gain=True,
    )
    return OmegaConf.structured(ModelConfig(**{**base, **changes}))


def rigid_observer(system=None, seed=0, **changes) -> ResidualObserver:
    system = RigidBody() if system is None else system
    torch.manual_seed(seed)
    return build_observer(system.group, 18, 0, rigid_model(**changes), system=system).double()


class FixedCore(RecurrentCore):
    """A core whose every output is the same given vector (the test's ``(a, K)``)."""

    def __init__(self, input_size: int, out: torch.Tensor):
        super().__init__()
        self.input_size, self.output_size = input_size, out.numel()
        self.out = torch.nn.Parameter(out.clone())

    def initial_hidden(self, batch, device=None, dtype=None):
        return (torch.zeros(batch, 1, dtype=self.out.dtype),)

    def step(self, inp, hidden):
        return self.out.expand(inp.shape[0], -1), hidden


def test_the_core_output_size_is_the_offset_and_the_gain():
    group = Product(SO3(), Euclidean(3), Euclidean(2), names=("R", "p", "b"))
    inputs = ObserverInputs({"R": (0, 9), "p": (9, 12)})
    assert core_output_size(group, inputs) == 8
    assert core_output_size(group, inputs, gain=True) == 8 * (1 + 6)


def test_the_update_is_the_offset_plus_the_gain_times_the_innovation():
    """One step from a known state with a core whose output is a fixed (a, K): the new estimate
    is ``x · exp(a + K nu)`` per factor, ``nu = (log(Rhat^T R^m), p^m - phat)``."""
    group = Product(SO3(), Euclidean(3), names=("R", "p"))
    inputs = ObserverInputs({"R": (0, 9), "p": (9, 12)})
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(6, generator=gen, dtype=torch.float64) * 0.1
    K = torch.randn(6, 6, generator=gen, dtype=torch.float64) * 0.3
    in_size = inputs.core_input_size(group, 12)
    core = FixedCore(in_size, torch.cat([a, K.flatten()]))
    obs = ResidualObserver(group, 12, core=core, inputs=inputs, gain=True)
    x = group.random((5,), generator=gen, dtype=torch.float64)
    m = group.random((5,), generator=gen, dtype=torch.float64)
    y = torch.cat([m[:, :9], m[:, 9:]], dim=-1)  # vec R^m, p^m
    new = obs.step(ObserverState(x, core.initial_hidden(5)), y).estimate
    so3 = SO3()
    nu = torch.cat(
        [so3.rminus(m[:, :9].unflatten(-1, (3, 3)), x[:, :9].unflatten(-1, (3, 3))),
         m[:, 9:] - x[:, 9:]],
        dim=-1,
    )
    v = a + nu @ K.T
    want_R = so3.rplus(x[:, :9].unflatten(-1, (3, 3)), v[:, :3]).flatten(1)
    want_p = x[:, 9:] + v[:, 3:]
    assert torch.allclose(new, torch.cat([want_R, want_p], -1), atol=1e-12)
    # K = 0: the plain additive update by a
    core.out.data[6:] = 0
    new0 = obs.step(ObserverState(x, core.initial_hidden(5)), y).estimate
    assert torch.allclose(new0[:, 9:], x[:, 9:] + a[3:], atol=1e-12)


def test_a_gru_cores_gain_starts_at_zero_and_its_offset_does_not():
    obs = rigid_observer()
    n = 12
    assert obs.core.head.weight.shape[0] == n * 7
    assert torch.count_nonzero(obs.core.head.weight[n:]) == 0
    assert torch.count_nonzero(obs.core.head.bias[n:]) == 0
    assert torch.count_nonzero(obs.core.head.weight[:n]) > 0


def test_a_zero_gain_and_offset_started_at_the_truth_follows_it_exactly():
    system = RigidBody()
    data = simulate(system, t=40, sigma=0.2)
    obs = rigid_observer(system)
    torch.nn.init.zeros_(obs.core.head.weight)
    torch.nn.init.zeros_(obs.core.head.bias)
    start = ObserverState(data.states[:, 0].clone(), obs.init_state(4).hidden)
    with torch.no_grad():
        clean = simulate(system, t=40, sigma=0.0)  # same states, noise-free readings
        est = obs(clean.measurements, state=start)
    assert torch.allclose(est, data.states, atol=1e-12)


@pytest.mark.parametrize("prior", ["system", "none"])
def test_rollout_online_steps_and_the_exported_step_agree(prior):
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.3)
    obs = rigid_observer(system, prior=prior)
    with torch.no_grad():
        for p in obs.core.head.parameters():  # a gain that is not zero
            p.normal_(0, 0.05)
    est = assert_online_matches_rollout(obs, data.measurements)
    system.group.check_member(est)


def test_the_gradient_reaches_the_gain_and_is_finite():
    system = RigidBody()
    data = simulate(system, n=4, t=10, sigma=0.1)
    obs = rigid_observer(system)
    est = obs(data.measurements)
    (est[:, 2:] - data.states[:, 2:]).pow(2).mean().backward()
    grads = [p.grad for p in obs.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    # K's rows start at zero, yet they get a gradient: dL/dK = dL/dv nu^T
    assert float(obs.core.head.weight.grad[12:].abs().sum()) > 0


def test_the_signature_records_the_gain_and_a_checkpoint_needs_it():
    with_gain = rigid_observer().signature()
    without = rigid_observer(gain=False).signature()
    assert with_gain["gain"] is True and "gain" not in without
    check_signature(with_gain, rigid_observer(seed=3).signature())
    with pytest.raises(CheckpointError, match="gain"):
        check_signature(with_gain, without)


def test_bad_gain_settings_say_what_is_wrong():
    system = RigidBody()
    with pytest.raises(ValueError, match="model.innovation is empty"):
        build_observer(
            system.group, 18, 0, rigid_model(innovation={}, relative_only=[]), system=system
        )
    with pytest.raises(ValueError, match="gain=True multiplies a learned gain"):
        ResidualObserver(system.group, 18, hidden_size=4, num_layers=1, gain=True)
    with pytest.raises(TypeError, match="gain must be True or False"):
        ResidualObserver(system.group, 18, hidden_size=4, num_layers=1, gain=1)
    inputs = ObserverInputs({"R": (0, 9)})
    core = FixedCore(inputs.core_input_size(system.group, 18), torch.zeros(12))
    with pytest.raises(ValueError, match=r"-> 48 \(the gain head: tangent_dim x"):
        ResidualObserver(system.group, 18, core=core, inputs=inputs, gain=True)


def test_without_the_offset_the_update_is_the_gain_times_the_innovation():
    group = Product(SO3(), Euclidean(3), names=("R", "p"))
    inputs = ObserverInputs({"R": (0, 9), "p": (9, 12)})
    assert core_output_size(group, inputs, gain=True, offset=False) == 6 * 6
    gen = torch.Generator().manual_seed(3)
    K = torch.randn(6, 6, generator=gen, dtype=torch.float64) * 0.3
    core = FixedCore(inputs.core_input_size(group, 12), K.flatten())
    obs = ResidualObserver(group, 12, core=core, inputs=inputs, gain=True, offset=False)
    x = group.random((4,), generator=gen, dtype=torch.float64)
    m = group.random((4,), generator=gen, dtype=torch.float64)
    new = obs.step(ObserverState(x, core.initial_hidden(4)), m).estimate
    nu = torch.cat(
        [SO3().rminus(m[:, :9].unflatten(-1, (3, 3)), x[:, :9].unflatten(-1, (3, 3))),
         m[:, 9:] - x[:, 9:]],
        dim=-1,
    )
    assert torch.allclose(new[:, 9:], x[:, 9:] + nu @ K[3:].T, atol=1e-12)
    assert obs.signature()["offset"] is False


def test_without_the_offset_the_truth_measured_exactly_is_a_fixed_point():
    """Any gain, a random one here: started at the truth with noise-free readings the prior's
    prediction is exact, the innovation zero, so the estimate stays on the truth (to rounding,
    which a random gain may amplify, hence a small one)."""
    system = RigidBody()
    data = simulate(system, t=60, sigma=0.0)
    obs = rigid_observer(system, gain_offset=False)
    assert torch.count_nonzero(obs.core.head.weight) == 0  # K starts at zero ...
    with torch.no_grad():
        for p in obs.core.head.parameters():  # ... but any K will do
            p.normal_(0, 0.02)
    start = ObserverState(data.states[:, 0].clone(), obs.init_state(4).hidden)
    with torch.no_grad():
        est = obs(data.measurements, state=start)
    assert torch.allclose(est, data.states, atol=1e-10)
    with_offset = rigid_observer(system)  # the offset moves it off
    with torch.no_grad():
        est = with_offset(data.measurements, state=start)
    assert not torch.allclose(est, data.states, atol=1e-6)


def test_no_offset_without_the_gain_head_says_so():
    system = RigidBody()
    with pytest.raises(ValueError, match="set model.gain=true"):
        build_observer(
            system.group, 18, 0, rigid_model(gain=False, gain_offset=False), system=system
        )
    with pytest.raises(ValueError, match="offset=False .* needs gain=True"):
        ResidualObserver(system.group, 18, hidden_size=4, num_layers=1, offset=False)


def save_plain(obs, path):
    return save_checkpoint(
        path, {"model": obs.state_dict(), "signature": obs.signature(), "config": {}, "epoch": 1}
    )


@pytest.mark.parametrize("scale", [1.0, 0.1])
def test_a_plain_observers_weights_start_the_gain_observer_where_it_is(tmp_path, scale):
    """``train.init_from`` a checkpoint without the gain head: the gain observer computes what
    the plain one does (the offset rows rescaled to its output_scale, K = 0)."""
    system = RigidBody()
    plain = rigid_observer(system, gain=False, seed=1)
    path = save_plain(plain, tmp_path / "plain.pt")
    gain = rigid_observer(system, seed=2, output_scale=scale)
    with pytest.raises(CheckpointError, match="gain"):  # only fine-tuning widens
        load_weights(gain, path)
    load_weights(gain, path, widen_gain=True)
    assert torch.count_nonzero(gain.core.head.weight[12:]) == 0
    data = simulate(system, n=3, t=40, sigma=0.2)
    with torch.no_grad():
        assert torch.allclose(gain(data.measurements), plain(data.measurements), atol=1e-10)


def test_only_a_plain_observer_of_the_same_shape_widens(tmp_path):
    system = RigidBody()
    path = save_plain(rigid_observer(system, gain=False, hidden_size=8), tmp_path / "plain.pt")
    with pytest.raises(CheckpointError, match="hidden_size: checkpoint 8, model 16"):
        load_weights(rigid_observer(system), path, widen_gain=True)
    gain_path = save_plain(rigid_observer(system), tmp_path / "gain.pt")
    with pytest.raises(CheckpointError, match="gain"):  # into a plain observer: no
        load_weights(rigid_observer(system, gain=False), gain_path, widen_gain=True)


def test_the_train_command_trains_with_the_gain_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load("paper_cpu_prior_gain", tmp_path)
    assert observer.signature()["gain"] is True and observer.gain
    data = simulate(system, n=2, t=5, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
