"""The centred update (``model.centering=c``): ``v = T(z) - c T(z^0)``, ``z^0`` the core's input
with each innovation factor measured exactly at its prediction. Pinned: the update is that
difference, exactly, for a core with known outputs; at ``c = 1`` the truth measured exactly is a
fixed point whatever the weights and the hidden state, and at ``c = 0`` it is not; ``c = 0`` is
the plain observer; the update is affine in ``c``; the rollout and the online step agree; the
gradient is finite; weights load across centerings only for fine-tuning; bad settings say what
is wrong; the train command trains and reloads it."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from groups import SO3, Euclidean, Product
from manifold_nets.builders import build_observer
from manifold_nets.checkpoint import CheckpointError, load_weights, save_checkpoint
from manifold_nets.config import ModelConfig
from manifold_nets.cores import RecurrentCore
from manifold_nets.inputs import ObserverInputs
from manifold_nets.observer import ObserverState, ResidualObserver
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load


def simulate(system, n=4, t=30, sigma=0.0, seed=1):
    return system.simulate(n, t, sigma, torch.Generator().manual_seed(seed))


def rigid_observer(system=None, seed=0, **changes) -> ResidualObserver:
    system = RigidBody() if system is None else system
    base = dict(
        hidden_size=16, num_layers=1, innovation={"R": [0, 9], "p": [9, 12]},
        relative_only=["p"], prior="system", updates={}, centering=1.0,
    )
    torch.manual_seed(seed)
    model = OmegaConf.structured(ModelConfig(**{**base, **changes}))
    return build_observer(system.group, 18, 0, model, system=system).double()


class ReadingCore(RecurrentCore):
    """A core whose output is a fixed linear map of what it reads (so ``T(z) - T(z^0)`` is that
    map applied to the difference of the two inputs)."""

    def __init__(self, input_size: int, weight: torch.Tensor):
        super().__init__()
        self.input_size, self.output_size = input_size, weight.shape[0]
        self.weight = torch.nn.Parameter(weight.clone())

    def initial_hidden(self, batch, device=None, dtype=None):
        return (torch.zeros(batch, 1, dtype=self.weight.dtype),)

    def step(self, inp, hidden):
        return inp @ self.weight.T, hidden


def test_the_update_is_the_core_less_its_output_at_the_predicted_measurement():
    """SO(3) x R^3, both measured, R also read as measured (not relative-only): ``z`` holds
    ``(embed(x), R^m, p^m, nu_R, nu_p)`` and ``z^0`` the same with ``R^m``, ``p^m`` replaced by
    ``x``'s own and ``nu = 0``; the step must move ``x`` by ``W z - c W z^0``."""
    group = Product(SO3(), Euclidean(3), names=("R", "p"))
    inputs = ObserverInputs({"R": (0, 9), "p": (9, 12)})
    gen = torch.Generator().manual_seed(0)
    in_size = inputs.core_input_size(group, 12)
    assert in_size == 12 + 12 + 6
    W = torch.randn(6, in_size, generator=gen, dtype=torch.float64) * 0.05
    x = group.random((5,), generator=gen, dtype=torch.float64)
    m = group.random((5,), generator=gen, dtype=torch.float64)
    so3 = SO3()
    nu = torch.cat(
        [so3.rminus(m[:, :9].unflatten(-1, (3, 3)), x[:, :9].unflatten(-1, (3, 3))),
         m[:, 9:] - x[:, 9:]],
        dim=-1,
    )
    z = torch.cat([x, m, nu], dim=-1)
    z0 = torch.cat([x, x, torch.zeros_like(nu)], dim=-1)
    for c in (1.0, 0.3):
        core = ReadingCore(in_size, W)
        obs = ResidualObserver(  # a prior that predicts no motion: the innovation is against x
            group, 12, core=core, inputs=inputs, centering=c, prior=lambda x, y, u: x
        )
        new = obs.step(ObserverState(x, core.initial_hidden(5)), m).estimate
        v = z @ W.T - c * (z0 @ W.T)
        want_R = so3.rplus(x[:, :9].unflatten(-1, (3, 3)), v[:, :3]).flatten(1)
        assert torch.allclose(new, torch.cat([want_R, x[:, 9:] + v[:, 3:]], -1), atol=1e-12)


@pytest.mark.parametrize("gain", [False, True])
def test_the_truth_measured_exactly_is_a_fixed_point_at_full_centering(gain):
    """Random weights, a random hidden state: started at the truth with noise-free readings the
    prior's prediction is exact and the innovation zero, so the estimate stays on the truth (to
    rounding, which a random gain amplifies, hence a small one). The same weights at centering 0
    move it off."""
    system = RigidBody()
    data = simulate(system, t=60, sigma=0.0)
    obs = rigid_observer(system, gain=gain)
    with torch.no_grad():
        for p in obs.core.head.parameters():  # a gain that is not zero, with the gain head
            p.normal_(0, 0.02)
    hidden = tuple(torch.randn_like(h) for h in obs.init_state(4).hidden)
    start = ObserverState(data.states[:, 0].clone(), hidden)
    with torch.no_grad():
        est = obs(data.measurements, state=start)
    assert torch.allclose(est, data.states, atol=1e-10)
    plain = rigid_observer(system, gain=gain, centering=0.0)
    plain.load_state_dict(obs.state_dict())
    with torch.no_grad():
        est = plain(data.measurements, state=start)
    assert not torch.allclose(est, data.states, atol=1e-6)


def test_centering_zero_is_the_plain_observer_and_the_update_is_affine_in_it():
    system = RigidBody()
    data = simulate(system, n=3, t=1, sigma=0.3)
    steps = {}
    for c in (0.0, 0.5, 1.0):
        obs = rigid_observer(system, seed=4, centering=c)
        steps[c] = obs(data.measurements)[:, 1].detach()
    plain = rigid_observer(system, seed=4, centering=0.0)
    assert "centering" not in plain.signature()  # the signature of older checkpoints
    # the biases are R^3 with a residual update: x + v, and v is affine in c
    b = slice(12, 18)
    assert torch.allclose(steps[0.5][:, b], (steps[0.0][:, b] + steps[1.0][:, b]) / 2, atol=1e-12)
    assert not torch.allclose(steps[0.0][:, b], steps[1.0][:, b], atol=1e-6)


@pytest.mark.parametrize("gain", [False, True])
def test_rollout_and_online_steps_agree(gain):
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.3)
    obs = rigid_observer(system, gain=gain, centering=0.6)
    est = assert_online_matches_rollout(obs, data.measurements)
    system.group.check_member(est)


def test_the_gradient_is_finite_and_reaches_every_weight_but_the_heads_bias():
    """At centering 1 the head's bias is in ``T(z)`` and in ``T(z^0)`` alike: it cancels, and
    its gradient is zero; every other weight gets one."""
    system = RigidBody()
    data = simulate(system, n=4, t=10, sigma=0.1)
    obs = rigid_observer(system)
    est = obs(data.measurements)
    (est[:, 2:] - data.states[:, 2:]).pow(2).mean().backward()
    grads = dict(obs.named_parameters())
    assert all(p.grad is not None and bool(torch.isfinite(p.grad).all()) for p in grads.values())
    assert torch.count_nonzero(grads.pop("core.head.bias").grad) == 0
    assert all(float(p.grad.abs().sum()) > 0 for p in grads.values())


def save(obs, path):
    return save_checkpoint(
        path, {"model": obs.state_dict(), "signature": obs.signature(), "config": {}, "epoch": 1}
    )


def test_weights_load_across_centerings_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    plain = rigid_observer(system, seed=1, centering=0.0)
    path = save(plain, tmp_path / "plain.pt")
    centred = rigid_observer(system, seed=2, centering=0.5)
    with pytest.raises(CheckpointError, match="centering"):  # evaluation: the same observer
        load_weights(centred, path)
    load_weights(centred, path, widen_gain=True)  # train.init_from
    assert centred.centering == 0.5
    for a, b in zip(centred.state_dict().values(), plain.state_dict().values()):
        assert torch.equal(a, b)
    back = rigid_observer(system, seed=3, centering=0.0)  # and back from a centred one
    load_weights(back, save(centred, tmp_path / "centred.pt"), widen_gain=True)
    assert "centering" not in back.signature()
    # a plain observer's weights into a centred one with the gain head: both widenings
    gain = rigid_observer(system, seed=5, gain=True)
    load_weights(gain, path, widen_gain=True)
    assert torch.count_nonzero(gain.core.head.weight[12:]) == 0


def test_bad_centering_says_what_is_wrong():
    system = RigidBody()
    with pytest.raises(ValueError, match=r"model.centering must be a number in \[0, 1\]"):
        rigid_observer(system, centering=1.5)
    with pytest.raises(ValueError, match="model.innovation is empty"):
        rigid_observer(system, innovation={}, relative_only=[])
    with pytest.raises(ValueError, match="centering must be a number"):
        ResidualObserver(system.group, 18, hidden_size=4, num_layers=1, centering=True)
    with pytest.raises(ValueError, match="reads none"):
        ResidualObserver(system.group, 18, hidden_size=4, num_layers=1, centering=1.0)
    with pytest.raises(ValueError, match="already zero at zero innovation"):
        rigid_observer(system, gain=True, gain_offset=False)
    # no prediction: the output at zero innovation is the motion itself (session 13 measured it:
    # session 6's outlier observer, no prior, at c = 0.7 went from a validation loss of -4.9 to 1.0)
    with pytest.raises(ValueError, match=r"no prediction \(model.prior=none"):
        rigid_observer(system, prior="none")
    inputs = ObserverInputs({"R": (0, 9), "p": (9, 12)}, ("p",))
    with pytest.raises(ValueError, match="no prediction"):
        ResidualObserver(system.group, 18, hidden_size=4, num_layers=1, inputs=inputs, centering=1)


def test_the_train_command_trains_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path, "model.centering=1.0"
    )
    assert observer.centering == 1.0 and observer.signature()["centering"] == 1.0
    data = simulate(system, n=2, t=5, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
