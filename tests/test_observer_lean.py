"""The lean closed-loop step (issue #37, eager): fewer operations and autograd nodes per step,
the same bits. The core's input read as one node (``DeferredView``, ``fused_features``) gives
the losses and gradients of the three features' own nodes bit for bit; the kernels' shortcuts
(``bmm`` for ``matmul``, the shared Rodrigues coefficients, the pivot's rows by ``where``, the
logarithm's gradient rows as views) compute what they replace."""

from __future__ import annotations

import copy
import math

import pytest
import torch

from groups import SO3
from groups import numerics as nx
from groups import so3_kernels as K
from manifold_nets.cores import GRUCore
from manifold_nets.losses import embedding_mse
from manifold_nets.observer import GroupUpdate, Measurement, ResidualObserver
from tests.observer_checks import rigid_readings, rigid_short
from manifold_nets.observer.features import Embedding, Innovation, Readings, reads_as_one
from manifold_nets.observer.fused import gradient_layout
from manifold_nets.observer.heads import GainHead
from manifold_nets.observer.measurement import DeferredView

RIGID = rigid_short()
ANGLES = (0.0, 1e-8, 1e-5, 3e-3, 5e-3, 1e-2, 0.25, 1.0, 3.0, math.pi - 1e-7, math.pi)


def _bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and torch.equal(
        a.contiguous().view(torch.int64 if a.dtype == torch.float64 else torch.int32),
        b.contiguous().view(torch.int64 if b.dtype == torch.float64 else torch.int32))


def _observer(features=None, head=None, seed=0):
    torch.manual_seed(seed)
    obs = ResidualObserver(
        RIGID, Measurement(18, factors={"R": (0, 9), "p": (9, 12)}),
        update=GroupUpdate({"bw": "absolute", "bv": "absolute"}),
        features=features or [Embedding(), Readings(), Innovation()], head=head,
    )
    obs.core.head.reset_parameters()  # the untrained head is zero: let the estimate move
    return obs


_data = rigid_readings


@pytest.mark.parametrize("n", [1, 5, 64])
def test_the_core_input_as_one_node_gives_the_same_bits(n):
    """Loss and every gradient bit for bit: the node hands the embedding's gradient and the
    innovations' to the estimate in the order their own nodes did."""
    obs, (y, x) = _observer(), _data(n=n)
    assert reads_as_one(obs) and obs._view == obs.measurement.deferred_view

    def run():
        loss = embedding_mse(RIGID, obs(y), x)
        return loss, torch.autograd.grad(loss, list(obs.parameters()))

    loss, grads = run()
    assert type(obs.measurement.deferred_view(x[:, 0].flatten(1).requires_grad_(), y[:, 0].float(),
                                              obs.measurement.elements(y[:, 0]))
                .cat_features(obs.features).grad_fn).__name__ == "_FeaturesBackward"
    obs._view = obs.measurement.view  # each feature its own node
    loss0, grads0 = run()
    assert _bits(loss, loss0)
    assert all(_bits(a, b) for a, b in zip(grads, grads0))


def test_a_second_derivative_through_the_core_input_node_is_the_formula_s():
    obs, (y, x) = _observer(), _data(n=3, t=3)
    obs.double()
    params = list(obs.parameters())

    def hvp():
        g = torch.autograd.grad(embedding_mse(RIGID, obs(y), x), params, create_graph=True)
        return torch.autograd.grad(sum((gi * gi).sum() for gi in g), params[-1])[0]

    fused = hvp()
    obs._view = obs.measurement.view
    torch.testing.assert_close(fused, hvp(), rtol=1e-10, atol=1e-12)


def test_only_the_paper_s_features_with_the_plain_head_read_as_one():
    assert not reads_as_one(_observer(features=[Embedding(), Readings()]))
    assert not reads_as_one(_observer(features=[Embedding(drop=["p"]), Readings(), Innovation()]))
    assert not reads_as_one(_observer(features=[Readings(), Embedding(), Innovation()]))
    assert not reads_as_one(_observer(head=GainHead()))


def test_a_deferred_view_makes_its_innovations_when_read_and_copies_rebind():
    obs, (y, _) = _observer(), _data()
    x = RIGID.random((5,), generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    x = x.flatten(1)
    yu, measured = y[:, 0].float(), obs.measurement.elements(y[:, 0])
    view = obs.measurement.deferred_view(x, yu, measured)
    assert isinstance(view, DeferredView) and view._made is None
    plain = obs.measurement.view(x, yu, measured)
    assert all(_bits(a, b) for a, b in zip(view.nu, plain.nu)) and view._made is not None
    with torch.no_grad():  # not recording: each feature, the innovations as made by view
        assert _bits(obs.measurement.deferred_view(x, yu, measured).cat_features(obs.features),
                     plain.cat_features(obs.features))
    twin = copy.deepcopy(obs)
    assert twin._view.__self__ is twin.measurement


def test_the_gradient_layout_puts_each_factor_at_its_columns():
    def layout(factors):
        return gradient_layout(Measurement(18, factors=factors).bind(RIGID))

    assert layout({"R": (0, 9), "p": (9, 12)}) == (0, 1, -6)
    assert layout({"p": (9, 12), "R": (0, 9)}) == (1, 0, -6)
    assert layout({"bv": (9, 12), "R": (0, 9)}) == (1, -6, 0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_kernels_shortcuts_compute_what_they_replace(dtype):
    g = torch.Generator().manual_seed(3)
    angles = torch.tensor(ANGLES, dtype=torch.float64).repeat_interleave(4)
    axes = torch.randn(len(angles), 3, generator=g, dtype=torch.float64)
    v = (angles[:, None] * axes / axes.norm(dim=-1, keepdim=True)).to(dtype)
    t2 = (v * v).sum(-1)
    b, c = K._rodrigues(t2)
    assert _bits(b, nx.sin_over_t(t2)) and _bits(c, nx.one_minus_cos_over_t2(t2))
    x = SO3().random((len(v),), generator=g, dtype=dtype)
    flat = torch.cat([x.flatten(1), torch.randn(len(v), 9, generator=g).to(dtype)], 1)
    xs = flat[:, :9].view(-1, 3, 3)  # a strided block of a flat state, as the observer's
    e = SO3().exp(v)
    for a, m in ((xs, e), (xs.transpose(1, 2), e), (e, xs.transpose(1, 2))):
        assert _bits(K._matmul(a, m), torch.matmul(a, m))
    # the pivot: the first of the largest of the four candidates (ties included)
    r = torch.cat([SO3().exp(v), torch.eye(3, dtype=dtype).expand(2, 3, 3),
                   torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=dtype))[None]])
    _, (rows, *_) = K._log_parts(r, derivative=True)
    f = torch.addmm(K.constant("quat_one", r), K.constant("quat_table", r),
                    r.reshape(-1, 9).t())
    pivot = f[:4].argmax(0)
    table = torch.tensor(K._PIVOT_ROWS)
    assert torch.equal(rows, table[pivot].t())
    # the logarithm's gradient rows as views: what the reshaped ones were
    grad = torch.randn(len(r), 3, generator=g).to(dtype)
    _, saved = K._log_parts(r, derivative=True)
    gd = K._log_grad(r.shape, *saved, grad)
    y = SO3().random((len(r),), generator=g, dtype=dtype)
    gy, gx = K.rminus_grads(y, r, saved, grad)
    assert _bits(gy, torch.matmul(r, gd)) and _bits(gx, torch.matmul(y, gd.transpose(-1, -2)))


def test_the_core_reads_nn_gru_s_own_list_of_its_weights():
    core = GRUCore(5, 3, hidden_size=8, num_layers=2)
    inp = torch.randn(4, 5)
    hidden = core.initial_hidden(4)
    ref = [t for layer in core._layers() for t in layer]
    assert all(a is b for a, b in zip(core.gru._flat_weights, ref))
    out, h = core.step(inp, hidden)
    core.double()  # the module keeps its list current
    assert all(a is b for a, b in zip(core.gru._flat_weights,
                                      [t for layer in core._layers() for t in layer]))
    out64, _ = core.step(inp.double(), tuple(t.double() for t in hidden))
    assert out64.dtype == torch.float64 and out.shape == out64.shape == (4, 3)


def test_the_step_that_reads_as_one_traces_as_one_graph():
    """torch.compile: dynamo refuses one tensor given twice to a Function, so while it traces
    the features are made as before (no graph break; the compiled step of issue #37)."""
    obs, (y, _) = _observer(), _data(n=4, t=2)
    x = (obs.init_state(4).estimate.flatten(1) * 1.0).requires_grad_()
    args = (x, obs.core.initial_hidden(4), y[:, 0].float(), y[:, 0], obs.measurement.elements(y[:, 0]),
            obs.schedule(0, 1)[0])
    with torch._dynamo.config.patch(allow_rnn=True):
        explained = torch._dynamo.explain(obs.step_unchecked)(*args)
    assert explained.graph_count == 1 and explained.graph_break_count == 0
