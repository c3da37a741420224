"""The readings pre-filter as a library piece: :class:`ReadingsFilter`, :class:`FilteredObserver`
and the exported step that carries the filter's state, on a toy filter written here (a running
mean of ``u`` removed from it and an exponential smoothing of ``y``: state, a first-sample rule
and a count, like a real one) in front of a small observer with inputs."""

from __future__ import annotations

import functools

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets import GRUCore, ResidualObserver, export_observer
from manifold_nets.deploy import load_exported_step
from manifold_nets.observer import (
    Embedding,
    FilteredObserver,
    FilteredState,
    Innovation,
    Measurement,
    Readings,
    ReadingsFilter,
    with_readings_filter,
)
from tests.observer_checks import randomise_head


class Smoothing(ReadingsFilter):
    """``u' = u - mean(u so far)``, ``y' = y smoothed, y'_0 = y_0`` (the loop is its sequence)."""

    name = "smoothing"

    def __init__(self, width: int, inputs: int, alpha: float = 0.3):
        super().__init__(width, inputs)
        self.alpha = alpha

    def state_names(self):
        return ["count", "u_sum", "smoothed"]

    def init_state(self, batch, dtype=torch.float64, device=None):
        kw = {"dtype": dtype, "device": device}
        return (torch.zeros(batch, **kw), torch.zeros(batch, self.input_dim, **kw),
                torch.zeros(batch, self.measurement_dim, **kw))

    def step_unchecked(self, state, y, u):
        count, total, s = state
        total = total + u
        s = torch.where((count == 0)[:, None], y, s + self.alpha * (y - s))
        return (count + 1, total, s), s, u - total / (count + 1)[:, None]


def _observer():
    group = Product(SO3(), Euclidean(3), names=["R", "p"])
    torch.manual_seed(0)
    obs = ResidualObserver(
        group, Measurement(12, 3, factors={"R": (0, 9), "p": (9, 12)}),
        functools.partial(GRUCore, hidden_size=16, num_layers=1),
        features=[Embedding(), Readings(), Innovation()],
    ).eval()
    randomise_head(obs, seed=0)
    return obs


def _readings(n=2, t=30, seed=0):
    g = torch.Generator().manual_seed(seed)
    y = torch.cat((SO3().random((n, t), generator=g, dtype=torch.float64).flatten(-2),
                   torch.randn(n, t, 3, generator=g, dtype=torch.float64)), -1)
    return y, torch.randn(n, t, 3, generator=g, dtype=torch.float64)


def test_the_rollout_is_the_observer_on_the_filtered_readings_and_the_step_loop():
    obs, (y, u) = _observer(), _readings()
    f = FilteredObserver(Smoothing(12, 3), obs)
    yf, uf, _ = f.prefilter(y, u)
    with torch.no_grad():
        est = f(y, u)
        assert torch.equal(est, obs(yf, uf))  # nothing in the observer changes
        state = f.init_state(2)
        for k in range(y.shape[1]):
            state = f.step(state, y[:, k], u[:, k])
            assert torch.allclose(state.observer.estimate, est[:, k + 1], rtol=0, atol=1e-12)
        # in chunks, the state carried over
        a, st = f(y[:, :11], u[:, :11], return_state=True)
        b = f(y[:, 11:], u[:, 11:], state=st)
    assert isinstance(st, FilteredState)
    torch.testing.assert_close(torch.cat((a, b[:, 1:]), 1), est, rtol=0, atol=1e-12)


def test_the_exported_step_on_raw_readings_is_the_filtered_rollout(tmp_path):
    obs, (y, u) = _observer(), _readings(t=20)
    f = FilteredObserver(Smoothing(12, 3), obs)
    export_observer(f, tmp_path / "step.pt2")
    loaded = load_exported_step(tmp_path / "step.pt2")
    assert loaded.meta["inputs"] == ["x", "hidden0", "filter_count", "filter_u_sum",
                                     "filter_smoothed", "y", "u"]
    assert loaded.meta["readings_filter"] == f.prefilter.signature()
    assert loaded.meta["state_dtypes"] == ["float64", "float32", "float64", "float64", "float64"]
    with torch.no_grad():
        want = f(y, u)
        for batch, step in ((2, loaded), (2, f.online_step_module().eval())):
            state = loaded.initial_state(batch)
            for k in range(y.shape[1]):
                state = step(*state, y[:, k], u[:, k])
                torch.testing.assert_close(state[0], want[:, k + 1].flatten(1), rtol=0, atol=1e-6)
    # an observer without a filter exports as before
    export_observer(obs, tmp_path / "plain.pt2")
    assert load_exported_step(tmp_path / "plain.pt2").meta["readings_filter"] is None


def test_strided_inputs_and_float32_filters():
    obs, (y, u) = _observer(), _readings(t=40)
    f = FilteredObserver(Smoothing(12, 3), obs)
    with torch.no_grad():
        want = f(y, u)
        wide = torch.cat((y, u), -1).transpose(0, 1).contiguous().transpose(0, 1)  # (N, T, 15) strided
        assert not wide[..., :12].is_contiguous()
        assert torch.equal(f(wide[..., :12], wide[..., 12:]), want)
        f32 = FilteredObserver(Smoothing(12, 3), obs, dtype=torch.float32)
        yf, uf, state = f32.prefilter(y, u, f32.prefilter.init_state(2, torch.float32))
        assert yf.dtype == uf.dtype == state[0].dtype == torch.float32
        torch.testing.assert_close(f32(y, u), want, rtol=0, atol=1e-4)


def test_bad_readings_are_refused_with_the_fix():
    obs, (y, u) = _observer(), _readings()
    f = FilteredObserver(Smoothing(12, 3), obs)
    with pytest.raises(ValueError, match=r"y \(N, T, 12\).*got \(2, 30, 11\).*all of their columns"):
        f(y[..., :11], u)
    with pytest.raises(ValueError, match=r"inputs u .*\(3,\) beside y, got NoneType"):
        f(y, None)
    with pytest.raises(ValueError, match=r"y \(B, 12\)"):
        f.step(f.init_state(2), y[:, 0, :9], u[:, 0])
    with pytest.raises(ValueError, match=r"batch of 3.*batch of 2.*init_state\(2"):
        f.step(f.init_state(3), y[:, 0], u[:, 0])
    with pytest.raises(ValueError, match="build the filter for the observer's system"):
        FilteredObserver(Smoothing(6, 3), obs)
    with pytest.raises(TypeError, match="ReadingsFilter"):
        FilteredObserver(torch.nn.Identity(), obs)


def test_a_system_hands_its_filter_to_the_observer():
    obs = _observer()

    class Plain:  # an older system, without the hook: the observer as it is
        pass

    class Filtered:
        def readings_filter(self):
            return Smoothing(12, 3)

    assert with_readings_filter(obs, Plain()) is obs
    wrapped = with_readings_filter(obs, Filtered())
    assert isinstance(wrapped, FilteredObserver) and wrapped.observer is obs
    assert wrapped.signature()["readings_filter"]["type"] == "smoothing"
