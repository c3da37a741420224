"""The residual observer: on the group after every step, gradients, rules, stepwise API, errors."""

from __future__ import annotations

import functools
import shutil

import pytest
import torch

from groups import SE3, SO3, Euclidean, Product
from manifold_nets.losses import embedding_mse
from manifold_nets import GRUCore, RecurrentCore, ResidualObserver
from manifold_nets.observer import Embedding, GroupUpdate, Innovation, Measurement, Readings
from tests.observer_checks import randomise_head

GROUPS = [
    pytest.param(SO3(), id="SO3"),
    pytest.param(Product(SO3(), Euclidean(3), Euclidean(2), names=("R", "p", "b")), id="SO3xR3xR2"),
    pytest.param(Euclidean(4), id="R4"),
    pytest.param(SE3(), id="SE3"),
    pytest.param(Product(SE3(), Euclidean(3), names=("T", "b")), id="SE3xR3"),
]
RIGID = Product(SO3(), Euclidean(3), Euclidean(3), Euclidean(3), names=("R", "p", "b_omega", "b_v"))


def _obs(group, meas=5, hidden=8, layers=2, seed=0, update=None, state_dtype=torch.float64,
         **kw):
    """A small GRU observer; its output layer random (``nn.Linear``'s initialisation), as an
    untrained observer's was before a core made by the observer started at zero."""
    meas = kw.pop("measurement", meas)
    torch.manual_seed(seed)
    obs = ResidualObserver(
        group, meas, functools.partial(GRUCore, hidden_size=hidden, num_layers=layers),
        update=GroupUpdate(update, state_dtype=state_dtype), **kw,
    )
    randomise_head(obs)  # from the seeded generator: same seed, same observer
    return obs


def _measured(meas, factors, drop=()):
    """The measurement and features of innovation inputs on ``factors`` (``drop``: the factors
    the core reads only through their innovation)."""
    return dict(
        measurement=Measurement(meas, factors=factors),
        features=[Embedding(drop=drop), Readings(drop=drop), Innovation()],
    )


def _amplify(obs: ResidualObserver, scale: float = 3.0) -> None:
    """Large outputs: steps of about a radian, to stress the group update."""
    with torch.no_grad():
        obs.core.head.weight.mul_(scale)
        obs.core.head.bias.normal_(0.0, 1.0)


@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("state_dtype", [torch.float64, torch.float32])
def test_estimate_on_group_after_every_step(group, state_dtype):
    obs = _obs(group, state_dtype=state_dtype)
    _amplify(obs)
    y = torch.randn(3, 60, 5, generator=torch.Generator().manual_seed(1)) * 5
    with torch.no_grad():
        est = obs(y)
    assert est.shape == (3, 61, *group.element_shape) and est.dtype == state_dtype
    err = group.membership_error(est)
    tol = 1e-12 if state_dtype == torch.float64 else 2e-5
    assert float(err.max()) <= tol, float(err.max())
    assert torch.equal(est[:, 0], group.identity((3,), dtype=state_dtype))  # starts at e
    assert float((est[:, -1] - est[:, 0]).abs().max()) > 0.1  # it moved


def test_float64_state_stays_on_group_for_1000_steps_with_float32_net():
    obs = _obs(RIGID, meas=18)
    _amplify(obs, 1.0)
    y = torch.randn(2, 1000, 18, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        est = obs(y)
    assert next(obs.parameters()).dtype == torch.float32
    r = RIGID.get(est[:, -1], "R")
    eye = torch.eye(3, dtype=torch.float64)
    assert float(torch.linalg.matrix_norm(r @ r.transpose(-1, -2) - eye).max()) <= 1e-12


@pytest.mark.parametrize("group", GROUPS)
def test_gradients_reach_every_parameter(group):
    obs = _obs(group, state_dtype=torch.float64)
    y = torch.randn(4, 12, 5, generator=torch.Generator().manual_seed(3))
    target = group.random((4, 13), generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    embedding_mse(group, obs(y), target).backward()
    for name, p in obs.named_parameters():
        assert p.grad is not None, name
        assert bool(torch.isfinite(p.grad).all()), name
        assert float(p.grad.abs().max()) > 0, name


def test_gradients_finite_at_identity_and_zero_output():
    """The first step starts at e; a zero head output (exp at 0) must not give NaN gradients."""
    obs = _obs(RIGID, meas=18)
    with torch.no_grad():
        obs.core.head.weight.zero_()
        obs.core.head.bias.zero_()
    y = torch.randn(2, 5, 18)
    loss = embedding_mse(RIGID, obs(y), RIGID.random((2, 6), dtype=torch.float64))
    loss.backward()
    for p in obs.parameters():
        assert bool(torch.isfinite(p.grad).all())


def test_gru_core_matches_torch_gru_open_loop():
    """The core's stepwise torch.gru_cell stack equals nn.GRU + Linear over the same inputs."""
    torch.manual_seed(0)
    core = GRUCore(7, 3, hidden_size=6, num_layers=3).double()
    x = torch.randn(10, 4, 7, dtype=torch.float64)
    ref, _ = core.gru(x)
    h = core.initial_hidden(4)
    outs = []
    for xt in x:
        o, h = core.step(xt, h)
        outs.append(o)
    torch.testing.assert_close(torch.stack(outs), core.head(ref), rtol=1e-12, atol=1e-12)


class ConstantCore(RecurrentCore):
    """A replaceable core: outputs a fixed tangent vector (and counts its steps)."""

    def __init__(self, input_size, output_size, v):
        super().__init__()
        self.input_size, self.output_size = input_size, output_size
        self.v = torch.nn.Parameter(v.clone())

    def initial_hidden(self, batch, device=None, dtype=None):
        return (torch.zeros(batch, 1, dtype=self.v.dtype),)

    def step(self, inp, hidden):
        return self.v.expand(inp.shape[0], -1), (hidden[0] + 1,)


def test_update_rules_residual_and_absolute():
    g = Product(SO3(), Euclidean(3), Euclidean(2), names=("R", "p", "b"))
    v = torch.tensor([0.1, -0.2, 0.05, 1.0, 2.0, 3.0, -4.0, 5.0], dtype=torch.float64)
    core = ConstantCore(g.embedding_dim + 2, g.tangent_dim, v)
    obs = ResidualObserver(g, 2, core=core, update=GroupUpdate({"b": "absolute"}))
    assert obs.update.rules == ("residual", "residual", "absolute")
    est = obs(torch.zeros(1, 4, 2, dtype=torch.float64))
    for k in range(5):
        r, p, b = g.split(est[0, k])
        torch.testing.assert_close(r, SO3().exp(k * v[:3]), rtol=0, atol=1e-14)  # R_k = exp(v)^k
        torch.testing.assert_close(p, k * v[3:6])  # p_k = p_{k-1} + beta
        torch.testing.assert_close(
            b, v[6:] if k else torch.zeros(2, dtype=torch.float64)
        )  # b = gamma


def test_absolute_on_a_non_vector_factor_sets_exp():
    v = torch.tensor([0.3, -0.1, 0.2], dtype=torch.float64)
    obs = ResidualObserver(
        SO3(), 1, core=ConstantCore(10, 3, v), update=GroupUpdate({"x": "absolute"})
    )
    est = obs(torch.zeros(2, 3, 1, dtype=torch.float64))
    torch.testing.assert_close(est[:, 1:], SO3().exp(v).expand(2, 3, 3, 3))


def test_step_api_matches_forward_and_continues():
    obs = _obs(RIGID, meas=18, update={"b_omega": "absolute", "b_v": "absolute"})
    y = torch.randn(3, 9, 18, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        full = obs(y)
        state = obs.init_state(3)
        for k in range(9):
            state = obs.step(state, y[:, k])
            torch.testing.assert_close(state.estimate, full[:, k + 1], rtol=0, atol=0)
        head, mid = obs(y[:, :4], return_state=True)
        tail = obs(y[:, 4:], state=mid)
    torch.testing.assert_close(torch.cat([head, tail[:, 1:]], 1), full, rtol=0, atol=0)


def test_inputs_are_read():
    obs = _obs(SO3(), meas=Measurement(2, input_dim=3))
    y = torch.randn(2, 6, 2)
    u = torch.randn(2, 6, 3)
    with torch.no_grad():
        a, b = obs(y, u), obs(y, u + 1)
    assert not torch.equal(a, b)
    with pytest.raises(ValueError, match="reads inputs u of size 3"):
        obs(y)
    with pytest.raises(ValueError, match=r"inputs must have shape \(N, T, input_dim\)"):
        obs(y, u[:, :, :2])


def test_signature_names_the_model():
    sig = _obs(RIGID, meas=18, update={"b_v": "absolute"}).signature()
    assert sig["core"] == {
        "type": "GRUCore",
        "input_size": 36,
        "output_size": 12,
        "hidden_size": 8,
        "num_layers": 2,
    }
    assert sig["update"] == ["residual", "residual", "residual", "absolute"]
    assert sig["measurement"]["factors"] == {}
    assert sig["features"] == [{"type": "embedding"}, {"type": "readings"}]  # nothing dropped


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda o: o(torch.randn(2, 5, 4)), r"measurement_dim=5\), got \(2, 5, 4\)"),
        (lambda o: o(torch.randn(5, 5)), r"shape \(N, T, measurement_dim=5\)"),
        (lambda o: o(torch.randint(0, 3, (2, 5, 5))), "floating-point"),
        (lambda o: o(torch.full((1, 2, 5), float("nan"))), "NaN or Inf"),
        (lambda o: o.step(o.init_state(2), torch.randn(2, 4)), r"measurement_dim=5"),
        (lambda o: o.step(o.init_state(2), torch.randn(3, 5)), "batch of 2"),
    ],
)
def test_bad_input_is_rejected_clearly(make, match):
    obs = _obs(SO3(), meas=5)
    with pytest.raises((ValueError, TypeError), match=match):
        make(obs)


def test_bad_construction_is_rejected_clearly():
    with pytest.raises(ValueError, match="not one of"):
        ResidualObserver(RIGID, 18, update=GroupUpdate({"R": "additive"}))
    with pytest.raises(ValueError, match="does not have"):
        ResidualObserver(RIGID, 18, update=GroupUpdate({"bias": "absolute"}))
    with pytest.raises(ValueError, match="needs"):
        ResidualObserver(RIGID, 18, core=GRUCore(30, 12, 4, 1))
    with pytest.raises(TypeError, match="LieGroup"):
        ResidualObserver("SO3", 18)
    with pytest.raises(ValueError, match="Measurement: dim"):  # was measurement_dim
        ResidualObserver(SO3(), 0)


class RecordingCore(RecurrentCore):
    """Outputs zero and records what it reads."""

    def __init__(self, input_size, output_size):
        super().__init__()
        self.input_size, self.output_size = input_size, output_size
        self.w = torch.nn.Parameter(torch.zeros(()))
        self.seen = []

    def initial_hidden(self, batch, device=None, dtype=None):
        return ()

    def step(self, inp, hidden):
        self.seen.append(inp.detach().clone())
        return inp.new_zeros(inp.shape[0], self.output_size) + self.w, hidden


def test_innovation_reads_log_of_estimate_to_measured_factor():
    g = Product(SO3(), Euclidean(3), names=("R", "p"))
    meas = 14  # y = (vec R^m, p^m, two more numbers)
    core = RecordingCore(g.embedding_dim + meas + 6, g.tangent_dim)
    obs = ResidualObserver(g, core=core, **_measured(meas, {"R": (0, 9), "p": (9, 12)}))
    rm = SO3().random((2, 3), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    pm = torch.randn(2, 3, 3, dtype=torch.float64)
    y = torch.cat([rm.flatten(-2), pm, torch.randn(2, 3, 2, dtype=torch.float64)], -1)
    obs(y)  # the estimate stays at the identity (zero output): innovation = log(m)
    for k, inp in enumerate(core.seen):
        torch.testing.assert_close(inp[:, 12 + meas : 15 + meas], SO3().log(rm[:, k]).float())
        torch.testing.assert_close(inp[:, 15 + meas :], pm[:, k].float())
    assert obs.signature()["measurement"]["factors"] == {"R": [0, 9], "p": [9, 12]}


def test_innovation_observer_on_group_with_gradients():
    obs = _obs(RIGID, **_measured(18, {"R": (0, 9)}))
    assert obs.core.input_size == 18 + 18 + 3
    y = torch.cat(
        [
            SO3().random((3, 7), dtype=torch.float64).flatten(-2),
            torch.randn(3, 7, 9, dtype=torch.float64),
        ],
        -1,
    )
    est = obs(y)
    assert float(RIGID.membership_error(est.detach()).max()) < 1e-12
    embedding_mse(RIGID, est, RIGID.random((3, 8), dtype=torch.float64)).backward()
    assert all(
        bool(torch.isfinite(p.grad).all()) and p.grad.abs().max() > 0 for p in obs.parameters()
    )
    state = obs.init_state(3)
    for k in range(7):
        state = obs.step(state, y[:, k])
    torch.testing.assert_close(state.estimate, est[:, -1].detach(), rtol=0, atol=1e-12)


def test_bad_innovation_is_rejected():
    with pytest.raises(ValueError, match="does not have"):
        ResidualObserver(RIGID, **_measured(18, {"q": (0, 9)}))
    with pytest.raises(ValueError, match="embedding_dim = 9"):
        ResidualObserver(RIGID, **_measured(18, {"R": (0, 8)}))
    with pytest.raises(ValueError, match="span of y"):
        ResidualObserver(RIGID, **_measured(18, {"p": (16, 19)}))


@pytest.mark.parametrize("group", GROUPS)
def test_internal_embed_and_update_match_the_group(group):
    """The observer's sliced, unchecked embed/update equal the group's own methods."""
    obs = _obs(group, update={})
    g = torch.Generator().manual_seed(6)
    x = group.random((4,), generator=g, dtype=torch.float64)
    v = torch.randn(4, group.tangent_dim, generator=g, dtype=torch.float64)
    flat = x.reshape(4, -1)
    torch.testing.assert_close(obs.update.embed(flat), group.embed(x), rtol=0, atol=0)
    torch.testing.assert_close(obs.update(flat, v), group.rplus(x, v).reshape(4, -1))


def test_relative_only_leaves_the_absolute_factor_out_of_the_core_input():
    g = Product(SO3(), Euclidean(3), names=("R", "p"))
    meas = 14  # y = (vec R^m, p^m, two more numbers)
    core = RecordingCore(9 + 11 + 6, g.tangent_dim)  # embed without p, y without p^m
    obs = ResidualObserver(g, core=core, **_measured(meas, {"R": (0, 9), "p": (9, 12)}, ["p"]))
    gen = torch.Generator().manual_seed(1)
    rm = SO3().random((2, 3), generator=gen, dtype=torch.float64)
    pm = torch.randn(2, 3, 3, generator=gen, dtype=torch.float64)
    rest = torch.randn(2, 3, 2, generator=gen, dtype=torch.float64)
    obs(torch.cat([rm.flatten(-2), pm, rest], -1))
    for k, inp in enumerate(core.seen):
        torch.testing.assert_close(inp[:, 9:18], rm[:, k].flatten(-2).float())  # y's vec R^m
        torch.testing.assert_close(inp[:, 18:20], rest[:, k].float())  # p^m is left out
        torch.testing.assert_close(inp[:, 23:], pm[:, k].float())  # p^m - phat (phat = 0)
    assert obs.signature()["features"][:2] == [
        {"type": "embedding", "drop": ["p"]}, {"type": "readings", "drop": ["p"]}
    ]
    plain = ResidualObserver(g, **_measured(meas, {"p": (9, 12)}))
    assert plain.signature()["features"][:2] == [{"type": "embedding"}, {"type": "readings"}]


def test_relative_only_observer_is_invariant_to_translations():
    """Shifting every position (true and measured) by a constant shifts the estimates of p by
    it and leaves everything else unchanged: the core never reads an absolute position."""
    obs = _obs(RIGID, **_measured(18, {"R": (0, 9), "p": (9, 12)}, ["p"]))
    _amplify(obs)
    gen = torch.Generator().manual_seed(2)
    y = torch.cat(
        [
            SO3().random((3, 9), generator=gen, dtype=torch.float64).flatten(-2),
            torch.randn(3, 9, 9, generator=gen, dtype=torch.float64),
        ],
        -1,
    )
    shift = torch.tensor([40.0, -25.0, 7.0], dtype=torch.float64)
    y2 = y.clone()
    y2[..., 9:12] += shift
    start = obs.init_state(3)
    moved = start.estimate.clone()
    moved[:, 9:12] += shift  # the same start, shifted
    a = obs(y, state=start).detach()
    b = obs(y2, state=start._replace(estimate=moved)).detach()
    torch.testing.assert_close(b[..., 9:12], a[..., 9:12] + shift, rtol=0, atol=1e-9)
    torch.testing.assert_close(b[..., :9], a[..., :9], rtol=0, atol=1e-12)
    torch.testing.assert_close(b[..., 12:], a[..., 12:], rtol=0, atol=1e-12)
    # without relative_only the same observer is not invariant
    plain = _obs(RIGID, **_measured(18, {"R": (0, 9), "p": (9, 12)}))
    _amplify(plain)
    a = plain(y, state=start).detach()
    b2 = plain(y2, state=start._replace(estimate=moved)).detach()
    assert float((b2[..., :9] - a[..., :9]).abs().max()) > 1e-3
    # the online step path reads the same columns
    s = start._replace(estimate=moved.clone())
    for k in range(9):
        s = obs.step(s, y2[:, k])
    torch.testing.assert_close(s.estimate, b[:, -1], rtol=0, atol=1e-12)


def test_bad_relative_only_is_rejected():
    with pytest.raises(ValueError, match="does not have"):
        ResidualObserver(RIGID, **_measured(18, {"p": (9, 12)}, ["q"]))
    with pytest.raises(ValueError, match="does not measure it"):  # R has no innovation span
        ResidualObserver(RIGID, **_measured(18, {"p": (9, 12)}, ["R"]))


@pytest.mark.skipif(shutil.which("g++") is None, reason="torch.compile on the CPU needs a C++ compiler")
def test_compiled_step_gives_the_eager_losses_and_gradients():
    kw = dict(hidden=8, layers=1, **_measured(18, {"R": (0, 9), "p": (9, 12)}),
              update={"b_omega": "absolute", "b_v": "absolute"}, state_dtype=torch.float64)
    eager, compiled = _obs(RIGID, **kw), _obs(RIGID, **kw).compile_step()
    gen = torch.Generator().manual_seed(3)
    y = torch.cat([SO3().random((4, 6), generator=gen, dtype=torch.float64).flatten(-2),
                   torch.randn(4, 6, 9, generator=gen, dtype=torch.float64)], -1)
    x = RIGID.random((4, 7), generator=gen, dtype=torch.float64)
    for obs in (eager, compiled):
        embedding_mse(RIGID, obs(y), x).backward()
    for a, b in zip(eager.parameters(), compiled.parameters()):
        torch.testing.assert_close(b.grad, a.grad, rtol=1e-4, atol=1e-6)
    with torch.no_grad():  # without gradients the eager step runs
        torch.testing.assert_close(compiled(y), eager(y), rtol=0, atol=0)
    assert float(RIGID.membership_error(compiled(y).detach()).max()) < 1e-12
