"""The gain head (``GainHead()``, ``head: {type: gain}``): the core outputs an offset ``a`` and a
gain ``K`` and the observer's update is ``v = a + K nu``, ``nu`` the measured factors' innovation.
Pinned: the update is that product, exactly, for a core with known outputs; ``K`` starts at zero
in a GRU core the observer makes; the rollout, the online step and the exported step agree; the
gradient reaches ``K``; the signature records it; bad settings say what is wrong; a plain
observer's weights start it where the plain one is; the train command trains and reloads it."""

from __future__ import annotations

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.builders import build_piece
from manifold_nets.checkpoint import CheckpointError, check_signature, load_weights
from manifold_nets.cores import RecurrentCore
from manifold_nets.observer import (
    CentredHead,
    Embedding,
    FramedInnovation,
    GainHead,
    Innovation,
    Measurement,
    ObserverState,
    OutputScale,
    PlainHead,
    Readings,
    ResidualObserver,
)
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load
from tests.test_centred_update import MEASURED, block_overrides, rigid_observer, save, simulate


def gain_observer(system=None, seed=0, head=None, **changes):
    """The rigid body's observer with the gain head (``K = 0``, the offset random)."""
    return rigid_observer(system, seed, head=GainHead() if head is None else head, **changes)


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


def _measured(dim=12):
    return dict(measurement=Measurement(dim, 0, MEASURED),
                features=[Embedding(), Readings(), Innovation()])


def test_the_core_output_size_is_the_offset_and_the_gain():
    assert PlainHead().output_size(8, 6) == 8
    assert GainHead().output_size(8, 6) == 8 * (1 + 6)
    assert CentredHead(0.5, inner=GainHead()).output_size(8, 6) == 8 * 7
    group = Product(SO3(), Euclidean(3), Euclidean(2), names=("R", "p", "b"))
    obs = ResidualObserver(group, core=lambda i, o: FixedCore(i, torch.zeros(o)), head=GainHead(),
                           **_measured())
    assert obs.core.output_size == 8 * 7 and obs.core.input_size == 14 + 12 + 6


def test_the_update_is_the_offset_plus_the_gain_times_the_innovation():
    """One step from a known state with a core whose output is a fixed (a, K): the new estimate
    is ``x · exp(a + K nu)`` per factor, ``nu = (log(Rhat^T R^m), p^m - phat)``."""
    group = Product(SO3(), Euclidean(3), names=("R", "p"))
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(6, generator=gen, dtype=torch.float64) * 0.1
    K = torch.randn(6, 6, generator=gen, dtype=torch.float64) * 0.3
    core = FixedCore(12 + 12 + 6, torch.cat([a, K.flatten()]))
    obs = ResidualObserver(group, core=core, head=GainHead(), **_measured())
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


@pytest.mark.parametrize("make", ["none", "factory"])
def test_a_gru_cores_gain_starts_at_zero_and_its_offset_does_not(make):
    n = 12
    if make == "factory":
        obs = gain_observer(untrained=True)
    else:  # the default core, made by the observer too
        system = RigidBody()
        obs = ResidualObserver(system.group, head=GainHead(), **_measured(18))
    assert obs.core.head.weight.shape[0] == n * 7
    assert torch.count_nonzero(obs.core.head.weight[n:]) == 0
    assert torch.count_nonzero(obs.core.head.bias[n:]) == 0
    assert torch.count_nonzero(obs.core.head.weight[:n]) > 0


def test_a_zero_gain_and_offset_started_at_the_truth_follows_it_exactly():
    system = RigidBody()
    data = simulate(system, t=40, sigma=0.2)
    obs = gain_observer(system)
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
    obs = gain_observer(system, prior=prior)
    with torch.no_grad():
        for p in obs.core.head.parameters():  # a gain that is not zero
            p.normal_(0, 0.05)
    est = assert_online_matches_rollout(obs, data.measurements)
    system.group.check_member(est)


def test_the_gradient_reaches_the_gain_and_is_finite():
    system = RigidBody()
    data = simulate(system, n=4, t=10, sigma=0.1)
    obs = gain_observer(system)
    est = obs(data.measurements)
    (est[:, 2:] - data.states[:, 2:]).pow(2).mean().backward()
    grads = [p.grad for p in obs.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    # K's rows start at zero, yet they get a gradient: dL/dK = dL/dv nu^T
    assert float(obs.core.head.weight.grad[12:].abs().sum()) > 0


def test_the_signature_records_the_gain_and_a_checkpoint_needs_it():
    with_gain = gain_observer().signature()
    without = gain_observer(head=PlainHead()).signature()
    assert with_gain["head"] == {"type": "gain"} and without["head"] == {"type": "plain"}
    check_signature(with_gain, gain_observer(seed=3).signature())
    with pytest.raises(CheckpointError, match="head.type: checkpoint 'gain', model 'plain'"):
        check_signature(with_gain, without)


def test_bad_gain_settings_say_what_is_wrong():
    system = RigidBody()
    message = "the gain head multiplies a learned gain with the innovation, but the measurement " \
              "names no measured factor"
    with pytest.raises(ValueError, match=message):
        gain_observer(system, measurement=Measurement(18), features=[Embedding(), Readings()])
    with pytest.raises(ValueError, match=message):
        ResidualObserver(system.group, 18, head=GainHead())
    for bad in (1, None, "true"):
        with pytest.raises(ValueError, match="gain head: offset must be true or false"):
            GainHead(offset=bad)
    with pytest.raises(ValueError, match=r"model.head \(gain\): gain head: offset must be true"):
        build_piece("head", {"type": "gain", "offset": 1}, "model.head")
    core = FixedCore(18 + 18 + 3, torch.zeros(12))  # the plain head's output size
    with pytest.raises(ValueError, match=r"core maps 39 -> 12, but the observer needs 39 "
                                         r"\(embedding 18 \+ readings 18 \+ innovation 3\) -> 48 "
                                         r"\(the gain head's output\)"):
        ResidualObserver(system.group, Measurement(18, 0, {"R": (0, 9)}), core,
                         features=[Embedding(), Readings(), Innovation()], head=GainHead())


def test_without_the_offset_the_update_is_the_gain_times_the_innovation():
    group = Product(SO3(), Euclidean(3), names=("R", "p"))
    assert GainHead(offset=False).output_size(6, 6) == 6 * 6
    gen = torch.Generator().manual_seed(3)
    K = torch.randn(6, 6, generator=gen, dtype=torch.float64) * 0.3
    core = FixedCore(12 + 12 + 6, K.flatten())
    obs = ResidualObserver(group, core=core, head=GainHead(offset=False), **_measured())
    x = group.random((4,), generator=gen, dtype=torch.float64)
    m = group.random((4,), generator=gen, dtype=torch.float64)
    new = obs.step(ObserverState(x, core.initial_hidden(4)), m).estimate
    nu = torch.cat(
        [SO3().rminus(m[:, :9].unflatten(-1, (3, 3)), x[:, :9].unflatten(-1, (3, 3))),
         m[:, 9:] - x[:, 9:]],
        dim=-1,
    )
    assert torch.allclose(new[:, 9:], x[:, 9:] + nu @ K[3:].T, atol=1e-12)
    assert obs.signature()["head"] == {"type": "gain", "offset": False}


def test_without_the_offset_the_truth_measured_exactly_is_a_fixed_point():
    """Any gain, a random one here: started at the truth with noise-free readings the prior's
    prediction is exact, the innovation zero, so the estimate stays on the truth (to rounding,
    which a random gain may amplify, hence a small one)."""
    system = RigidBody()
    data = simulate(system, t=60, sigma=0.0)
    obs = gain_observer(system, head=GainHead(offset=False))
    assert torch.count_nonzero(obs.core.head.weight) == 0  # K starts at zero ...
    with torch.no_grad():
        for p in obs.core.head.parameters():  # ... but any K will do
            p.normal_(0, 0.02)
    start = ObserverState(data.states[:, 0].clone(), obs.init_state(4).hidden)
    with torch.no_grad():
        est = obs(data.measurements, state=start)
    assert torch.allclose(est, data.states, atol=1e-10)
    with_offset = gain_observer(system)  # the offset moves it off
    with torch.no_grad():
        est = with_offset(data.measurements, state=start)
    assert not torch.allclose(est, data.states, atol=1e-6)


def test_no_offset_without_the_gain_head_says_so():
    with pytest.raises(ValueError, match=r"model.head \(plain\): unknown key\(s\) \['offset'\]"):
        build_piece("head", {"type": "plain", "offset": False}, "model.head")


def test_a_flat_gain_offset_without_the_gain_says_so():
    """The first format's ``gain_offset: false`` means nothing without ``gain: true``: the
    translated config must refuse it, as the first format did, not drop it."""
    from omegaconf import OmegaConf

    from manifold_nets.builders import build_observer
    from manifold_nets.config import ModelConfig

    system = RigidBody()
    model = OmegaConf.structured(ModelConfig(
        hidden_size=4, num_layers=1, innovation={"R": [0, 9], "p": [9, 12]}, prior="system",
        gain=False, gain_offset=False,
    ))
    with pytest.raises(ValueError, match="gain"):
        build_observer(system.group, 18, 0, model, system=system)


@pytest.mark.parametrize("scale", [1.0, 0.1])
def test_a_plain_observers_weights_start_the_gain_observer_where_it_is(tmp_path, scale):
    """``train.init_from`` a checkpoint without the gain head: the gain observer computes what
    the plain one does (the offset rows rescaled to its output scale, K = 0)."""
    system = RigidBody()
    plain = gain_observer(system, head=PlainHead(), seed=1)
    path = save(plain, tmp_path / "plain.pt")
    gain = gain_observer(system, seed=2, scales=[OutputScale(scale)] if scale != 1 else [])
    with pytest.raises(CheckpointError, match="head"):  # only fine-tuning widens
        load_weights(gain, path)
    load_weights(gain, path, widen=True)
    assert torch.count_nonzero(gain.core.head.weight[12:]) == 0
    data = simulate(system, n=3, t=40, sigma=0.2)
    with torch.no_grad():
        assert torch.allclose(gain(data.measurements), plain(data.measurements), atol=1e-10)


def test_a_plain_observer_widens_to_the_gain_and_a_feature_at_once(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=8, sigma=0.2)
    plain = gain_observer(system, seed=1, head=PlainHead())
    both = gain_observer(system, seed=2, extra=[FramedInnovation({"p": "R"})])
    load_weights(both, save(plain, tmp_path / "plain.pt"), widen=True)
    with torch.no_grad():
        assert torch.allclose(both(data.measurements), plain(data.measurements), atol=1e-12)


def test_only_a_plain_observer_of_the_same_shape_widens(tmp_path):
    system = RigidBody()
    path = save(gain_observer(system, head=PlainHead(), hidden=8), tmp_path / "plain.pt")
    with pytest.raises(CheckpointError, match="core.hidden_size differs: checkpoint 8, model 16"):
        load_weights(gain_observer(system), path, widen=True)
    gain_path = save(gain_observer(system), tmp_path / "gain.pt")
    with pytest.raises(CheckpointError, match="the checkpoint's head is 'gain', this "
                                              "observer's 'plain'"):  # into a plain one: no
        load_weights(gain_observer(system, head=PlainHead()), gain_path, widen=True)
    plain_path = save(gain_observer(system, head=PlainHead()), tmp_path / "plain16.pt")
    with pytest.raises(CheckpointError, match="widen only into a gain head with its offset"):
        load_weights(gain_observer(system, head=GainHead(offset=False)), plain_path, widen=True)


def test_the_train_command_trains_with_the_gain_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior_gain", tmp_path,
        *block_overrides(head="{type:gain}", scales="[{type:output,scale:0.1}]"),
    )
    assert observer.signature()["head"] == {"type": "gain"} and isinstance(observer.head, GainHead)
    assert observer.signature()["scales"] == [{"type": "output", "scale": 0.1}]
    data = simulate(system, n=2, t=5, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
