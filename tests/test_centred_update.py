"""The centred head (``CentredHead(c)``, ``head: {type: centred, c: ..}``): ``v = T(z) - c T(z^0)``,
``z^0`` the core's input with each measured factor measured exactly at its prediction. Pinned: the
update is that difference, exactly, for a core with known outputs; at ``c = 1`` the truth measured
exactly is a fixed point whatever the weights and the hidden state, and with the plain head it is
not; the plain head is ``c = 0`` and the update is affine in ``c``; the rollout and the online step
agree; the gradient is finite; weights load across heads only for fine-tuning; bad settings say
what is wrong, naming the piece; the train command trains and reloads it.

Also the helpers the other tests of the rigid body's observer share (:func:`rigid_observer`,
:func:`simulate`, :func:`save`, :func:`block_overrides`)."""

from __future__ import annotations

import functools

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.builders import build_piece
from manifold_nets.checkpoint import CheckpointError, load_weights, save_checkpoint
from manifold_nets.cores import GRUCore, RecurrentCore
from manifold_nets.observer import (
    CentredHead,
    Embedding,
    GainHead,
    Innovation,
    Measurement,
    NoPrior,
    ObserverState,
    PlainHead,
    Prior,
    Readings,
    ResidualObserver,
    SystemPrior,
)
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load

#: The rigid body's measured factors: ``y[0:9]`` is ``vec R``, ``y[9:12]`` is ``p``.
MEASURED = {"R": (0, 9), "p": (9, 12)}


def simulate(system, n=4, t=30, sigma=0.0, seed=1):
    return system.simulate(n, t, sigma, torch.Generator().manual_seed(seed))


def centred(c: float, ramp: int = 0, factors: dict | None = None, gain: bool = False):
    """The head of centring ``c`` (the plain or gain head itself at ``c = 0``)."""
    inner = GainHead() if gain else PlainHead()
    if not c:
        return inner
    return CentredHead(c, ramp=ramp, factors=factors, inner=inner if gain else None)


def rigid_observer(system=None, seed=0, *, head=None, prior="system", measurement=None,
                   features=None, extra=(), scales=(), hidden=16, untrained=False):
    """The rigid body's observer with a 1 x ``hidden`` GRU core: by default the system prior,
    both measured factors, the core reading ``p`` only through its innovation
    (``[Embedding(drop=[p]), Readings(drop=[p]), Innovation(), *extra]``) and the centred head at
    ``c = 1``; float64 throughout.

    The core's output layer is random, as a trained observer's (``untrained=True``: where a core
    the observer makes starts, the plain head's at zero, the gain head's ``K`` at zero); a gain
    head keeps ``K = 0`` either way. The same seed and sizes give the same weights."""
    system = RigidBody() if system is None else system
    prior = {"system": lambda: SystemPrior(system), "none": NoPrior}[prior]() if isinstance(
        prior, str) else prior
    if features is None:
        features = [Embedding(drop=["p"]), Readings(drop=["p"]), Innovation(), *extra]
    head = CentredHead(1.0) if head is None else head
    torch.manual_seed(seed)
    obs = ResidualObserver(
        system.group, Measurement(18, 0, MEASURED) if measurement is None else measurement,
        functools.partial(GRUCore, hidden_size=hidden, num_layers=1), prior=prior,
        features=features, head=head, scales=scales,
    )
    if not untrained:
        with torch.no_grad():
            obs.core.head.reset_parameters()  # a trained observer's output layer ...
        if isinstance(getattr(obs.head, "inner", obs.head), GainHead):
            obs.head.reset(obs.core)  # ... but the gain head's K starts at zero
    return obs.double()


def save(obs, path):
    return save_checkpoint(
        path, {"model": obs.state_dict(), "signature": obs.signature(), "config": {}, "epoch": 1}
    )


def block_overrides(*more: str, measurement="{factors:{R:[0,9],p:[9,12]}}", prior="{type:system}",
                    features="[{type:embedding,drop:[p]},{type:readings,drop:[p]},innovation]",
                    head="{type:plain}", scales="[]") -> list[str]:
    """Overrides of the train command giving the model's every block (the rigid body's observer
    of :func:`rigid_observer` by default), whatever the experiment's model file holds, with
    ``more`` after them."""
    blocks = [f"measurement={measurement}", f"prior={prior}", f"features={features}",
              f"head={head}", f"scales={scales}"]
    return [f"++model.{o}" for o in blocks] + list(more)


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


class StillPrior(Prior):
    """A prior that predicts no motion, ``x^- = x`` (unregistered: it has no name)."""

    def forward(self, x, yu, ys):
        return x


def test_the_update_is_the_core_less_its_output_at_the_predicted_measurement():
    """SO(3) x R^3, both measured, R also read as measured (no dropped factor): ``z`` holds
    ``(embed(x), R^m, p^m, nu_R, nu_p)`` and ``z^0`` the same with ``R^m``, ``p^m`` replaced by
    ``x``'s own and ``nu = 0``; the step must move ``x`` by ``W z - c W z^0``."""
    group = Product(SO3(), Euclidean(3), names=("R", "p"))
    features = [Embedding(), Readings(), Innovation()]
    gen = torch.Generator().manual_seed(0)
    in_size = 12 + 12 + 6
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
            group, Measurement(12, 0, MEASURED), core, prior=StillPrior(), features=features,
            head=CentredHead(c),
        )
        assert sum(f.width for f in obs.features) == in_size
        new = obs.step(ObserverState(x, core.initial_hidden(5)), m).estimate
        v = z @ W.T - c * (z0 @ W.T)
        want_R = so3.rplus(x[:, :9].unflatten(-1, (3, 3)), v[:, :3]).flatten(1)
        assert torch.allclose(new, torch.cat([want_R, x[:, 9:] + v[:, 3:]], -1), atol=1e-12)


@pytest.mark.parametrize("gain", [False, True])
def test_the_truth_measured_exactly_is_a_fixed_point_at_full_centering(gain):
    """Random weights, a random hidden state: started at the truth with noise-free readings the
    prior's prediction is exact and the innovation zero, so the estimate stays on the truth (to
    rounding, which a random gain amplifies, hence a small one). The same weights with the
    uncentred head move it off."""
    system = RigidBody()
    data = simulate(system, t=60, sigma=0.0)
    obs = rigid_observer(system, head=centred(1.0, gain=gain))
    with torch.no_grad():
        for p in obs.core.head.parameters():  # a gain that is not zero, with the gain head
            p.normal_(0, 0.02)
    hidden = tuple(torch.randn_like(h) for h in obs.init_state(4).hidden)
    start = ObserverState(data.states[:, 0].clone(), hidden)
    with torch.no_grad():
        est = obs(data.measurements, state=start)
    assert torch.allclose(est, data.states, atol=1e-10)
    plain = rigid_observer(system, head=centred(0.0, gain=gain))
    plain.load_state_dict(obs.state_dict())
    with torch.no_grad():
        est = plain(data.measurements, state=start)
    assert not torch.allclose(est, data.states, atol=1e-6)


def test_the_plain_head_is_centering_zero_and_the_update_is_affine_in_c():
    system = RigidBody()
    data = simulate(system, n=3, t=1, sigma=0.3)
    steps = {}
    for c in (0.0, 0.5, 1.0):
        obs = rigid_observer(system, seed=4, head=centred(c))
        steps[c] = obs(data.measurements)[:, 1].detach()
    plain = rigid_observer(system, seed=4, head=PlainHead())
    assert plain.signature()["head"] == {"type": "plain"}
    assert rigid_observer(system, head=CentredHead(0.5)).signature()["head"] == {
        "type": "centred", "c": 0.5
    }
    # the biases are R^3 with a residual update: x + v, and v is affine in c
    b = slice(12, 18)
    assert torch.allclose(steps[0.5][:, b], (steps[0.0][:, b] + steps[1.0][:, b]) / 2, atol=1e-12)
    assert not torch.allclose(steps[0.0][:, b], steps[1.0][:, b], atol=1e-6)


@pytest.mark.parametrize("gain", [False, True])
def test_rollout_and_online_steps_agree(gain):
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.3)
    obs = rigid_observer(system, head=centred(0.6, gain=gain))
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


def test_weights_load_across_centerings_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    plain = rigid_observer(system, seed=1, head=PlainHead())
    path = save(plain, tmp_path / "plain.pt")
    cent = rigid_observer(system, seed=2, head=CentredHead(0.5))
    with pytest.raises(CheckpointError, match="head"):  # evaluation: the same observer
        load_weights(cent, path)
    load_weights(cent, path, widen=True)  # train.init_from
    assert cent.head.c == 0.5
    for a, b in zip(cent.state_dict().values(), plain.state_dict().values()):
        assert torch.equal(a, b)
    back = rigid_observer(system, seed=3, head=PlainHead())  # and back from a centred one
    load_weights(back, save(cent, tmp_path / "centred.pt"), widen=True)
    assert back.signature()["head"] == {"type": "plain"}
    # a plain observer's weights into a centred one with the gain head: both widenings
    gain = rigid_observer(system, seed=5, head=centred(1.0, gain=True))
    load_weights(gain, path, widen=True)
    assert torch.count_nonzero(gain.core.head.weight[12:]) == 0
    torch.testing.assert_close(gain.core.head.weight[:12], plain.core.head.weight, rtol=0, atol=0)


def test_bad_centering_says_what_is_wrong():
    system = RigidBody()
    for bad in (1.5, -0.1, True, "0.5", None):
        with pytest.raises(ValueError, match=r"centred head: c must be a number in \[0, 1\]"):
            CentredHead(bad)
    with pytest.raises(ValueError, match=r"model.head \(centred\): centred head: c must be a "
                                         r"number in \[0, 1\]"):
        build_piece("head", {"type": "centred", "c": 1.5}, "model.head")
    with pytest.raises(ValueError, match="centred head: c = 0 centres nothing; use the plain head"):
        CentredHead(0.0)
    # nothing measured: no innovation to centre
    with pytest.raises(ValueError, match="the centred head subtracts the core's output at zero "
                                         "innovation, but the measurement names no measured"):
        rigid_observer(system, measurement=Measurement(18), features=[Embedding(), Readings()])
    with pytest.raises(ValueError, match="names no measured factor"):
        ResidualObserver(system.group, 18, prior=SystemPrior(system), head=CentredHead(1.0))
    with pytest.raises(ValueError, match="already zero at zero innovation"):
        CentredHead(1.0, inner=GainHead(offset=False))
    with pytest.raises(ValueError, match="centred head: inner must be a plain or a gain head"):
        CentredHead(1.0, inner=CentredHead(0.5))
    # no prediction: the output at zero innovation is the motion itself (measured: an
    # outlier observer without a prior, at c = 0.7, went from a validation loss of -4.9 to 1.0)
    with pytest.raises(ValueError, match="the centred head .* but the observer has no prior"):
        rigid_observer(system, prior="none")


def test_the_train_command_trains_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path, *block_overrides(head="{type:centred,c:1.0}")
    )
    assert isinstance(observer.head, CentredHead) and observer.head.c == 1.0
    assert observer.signature()["head"] == {"type": "centred", "c": 1.0}
    data = simulate(system, n=2, t=5, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
