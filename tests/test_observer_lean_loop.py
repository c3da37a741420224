"""The lean rollout (issue #37): while an observer of the paper's features over an SO(3) x R^n
state trains, its rollout runs ``fused.lean_steps``, each step's update and the next step's core
input as one autograd node whose SO(3) derivatives read coefficients made for all the steps at
once. It must give the step-by-step rollout's estimates, losses, gradients and trained weights to
the last bit."""

from __future__ import annotations

import pytest
import torch

from groups import SO3
from groups import so3_kernels as K
from manifold_nets.losses import embedding_mse
from manifold_nets.observer import GroupUpdate, Measurement, ObserverState, ResidualObserver
from manifold_nets.observer import observer as observer_module
from manifold_nets.observer.features import Embedding, Innovation, Readings
from manifold_nets.observer.fused import runs_lean
from manifold_nets.observer.heads import GainHead
from tests.observer_checks import rigid_readings, rigid_short

RIGID = rigid_short()
ANGLES = (0.0, 1e-8, 1e-5, 3e-3, 0.25, 1.0, 3.0, 3.14159265, 3.141592653589793)


def _bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    ints = {torch.float64: torch.int64, torch.float32: torch.int32, torch.bool: torch.bool,
            torch.int64: torch.int64}
    return a.dtype == b.dtype and a.shape == b.shape and torch.equal(
        a.contiguous().view(ints[a.dtype]), b.contiguous().view(ints[b.dtype]))


def _observer(head=None, seed=0):
    torch.manual_seed(seed)
    obs = ResidualObserver(
        RIGID, Measurement(18, factors={"R": (0, 9), "p": (9, 12)}),
        update=GroupUpdate({"bw": "absolute", "bv": "absolute"}),
        features=[Embedding(), Readings(), Innovation()], head=head,
    )
    obs.core.head.reset_parameters()  # the untrained head is zero: let the estimate move
    return obs


def _train(obs, y, x, lean, monkeypatch, steps=3, start=None, keep_hidden=False):
    """Losses, the first step's gradients (of the parameters and of a start that requires
    grad), the hidden states kept and the weights after ``steps`` AdamW steps."""
    monkeypatch.setattr(observer_module, "runs_lean", runs_lean if lean else lambda obs: False)
    opt = torch.optim.AdamW(obs.parameters(), lr=1e-2, weight_decay=0.1)
    out = []
    for i in range(steps):
        run = obs.rollout(y, state=start, keep_hidden=keep_hidden)
        loss = embedding_mse(RIGID, run.estimates, x)
        wrt = list(obs.parameters()) + ([start.estimate] if start is not None else [])
        grads = torch.autograd.grad(loss, wrt, retain_graph=keep_hidden)
        if keep_hidden:  # the kept states are the graph's too
            grads += torch.autograd.grad(sum(h.square().sum() for h in run.hidden),
                                         list(obs.parameters()))
        for p, g in zip(obs.parameters(), grads):
            p.grad = g
        opt.step()
        out += [run.estimates.detach(), loss.detach(), *grads, *(run.hidden or ())]
    return out + [p.detach().clone() for p in obs.parameters()]


@pytest.mark.parametrize("n, t", [(1, 1), (5, 2), (4, 7), (64, 5)])
def test_the_lean_rollout_trains_to_the_same_bits(n, t, monkeypatch):
    y, x = rigid_readings(n=n, t=t)
    obs = _observer()
    lean = _train(_observer(), y, x, True, monkeypatch)
    assert runs_lean(obs)
    plain = _train(obs, y, x, False, monkeypatch)
    assert len(lean) == len(plain) and all(_bits(a, b) for a, b in zip(lean, plain))


@pytest.mark.filterwarnings("ignore:Converting a tensor with requires_grad")  # (check_start)
def test_kept_hidden_states_and_a_start_that_requires_grad_give_the_same_bits(monkeypatch):
    y, x = rigid_readings(n=3, t=5)

    def start():
        x0 = RIGID.random((3,), generator=torch.Generator().manual_seed(4), dtype=torch.float64)
        obs = _observer()
        return obs, ObserverState(x0.requires_grad_(), obs.core.initial_hidden(3))

    obs, s = start()
    lean = _train(obs, y, x, True, monkeypatch, start=s, keep_hidden=True)
    obs, s = start()
    plain = _train(obs, y, x, False, monkeypatch, start=s, keep_hidden=True)
    assert len(lean) == len(plain) and all(_bits(a, b) for a, b in zip(lean, plain))


def test_a_second_derivative_through_the_lean_rollout_is_the_formula_s(monkeypatch):
    y, x = rigid_readings(n=3, t=3)
    obs = _observer().double()
    params = list(obs.parameters())

    def hvp(lean):
        monkeypatch.setattr(observer_module, "runs_lean", runs_lean if lean else lambda o: False)
        g = torch.autograd.grad(embedding_mse(RIGID, obs(y), x), params, create_graph=True)
        return torch.autograd.grad(sum((gi * gi).sum() for gi in g), params)

    for a, b in zip(hvp(True), hvp(False)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_only_a_training_rollout_of_the_paper_s_step_runs_lean():
    obs = _observer()
    assert runs_lean(obs)
    with torch.no_grad():
        assert not runs_lean(obs)
    assert not runs_lean(_observer(head=GainHead()))
    obs.update._fused = False
    assert not runs_lean(obs)
    obs = _observer()
    obs._view = obs.measurement.view  # each feature its own node
    assert not runs_lean(obs)
    obs = _observer()
    obs._compiled_step = obs.step_unchecked  # (what compile_step sets)
    assert not runs_lean(obs)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_coefficients_of_many_steps_at_once_are_each_step_s(dtype):
    """The tape's coefficients (elementwise arithmetic over the stacked steps) are the eager
    ones of each step, edge angles (0, pi, the series' threshold) included."""
    g = torch.Generator().manual_seed(5)
    angles = torch.tensor(ANGLES, dtype=torch.float64).repeat_interleave(3)
    steps = []
    for i in range(4):
        axes = torch.randn(len(angles), 3, generator=g, dtype=torch.float64)
        v = (angles[:, None] * axes / axes.norm(dim=-1, keepdim=True)).to(dtype)
        x = SO3().random((len(v),), generator=g, dtype=dtype)
        y = SO3().random((len(v),), generator=g, dtype=dtype)
        steps.append((x, v, y))
    eager = [(K.rplus_values(x, v)[1], K.rminus_values(y, x)[1]) for x, v, y in steps]
    exp_raw = [K.rplus_parts(x, v)[2] for x, v, _ in steps]
    log_raw = [K.rminus_parts(y, x)[2] for x, _, y in steps]
    over, coef = K.exp_coefficients(*[torch.stack(t) for t in zip(*exp_raw)])
    k2, e, h = K.log_coefficients(*[torch.stack(t) for t in zip(*log_raw)])
    for i, ((_, _, over_i, coef_i), (_, _, k2_i, e_i, h_i)) in enumerate(eager):
        assert _bits(over[i], over_i) and _bits(coef[i], coef_i)
        assert _bits(k2[i], k2_i) and _bits(e[i], e_i) and _bits(h[i], h_i)
