"""Deployment: the online step as a check-free module, exported with torch.export and to ONNX.

The exported step, saved and loaded back, must give the eager ``observer.step``'s estimates over
a stream of measurements. Float32 network, float64 state: the exported graph is the same
arithmetic in the same order (``gru_cell`` decomposed into its matmuls and pointwise ops), so
the only differences are float32 roundings of the network, far below 1e-6 over 50 steps.
"""

from __future__ import annotations

import functools
import importlib.util

import pytest
import torch

from manifold_nets_examples.rigid_body import RigidBody
from groups import SO3, Euclidean, Product
from manifold_nets import GRUCore, ResidualObserver, export_observer
from manifold_nets.builders import build_observer
from manifold_nets.config import ModelConfig
from manifold_nets.deploy import OnlineStep, export_onnx, load_exported_step
from manifold_nets.observer import Embedding, Innovation, Measurement, Readings
from tests.observer_checks import randomise_head

STEPS = 50


def _rigid_body_observer(state_dtype: str = "float64") -> tuple[ResidualObserver, torch.Tensor]:
    """The rigid body's observer of ``experiment=default`` (innovation ``R: [0, 9], p: [9, 12]``,
    biases absolute; a 2x32 GRU to stay fast; its output layer random, so that it moves) and a
    noisy stream ``(STEPS, 1, 18)`` float64."""
    system = RigidBody()
    model = ModelConfig(
        hidden_size=32, num_layers=2, updates={"b_omega": "absolute", "b_v": "absolute"},
        measurement={"factors": {"R": [0, 9], "p": [9, 12]}}, state_dtype=state_dtype,
    )
    torch.manual_seed(0)
    obs = build_observer(system.group, system.measurement_dim, system.input_dim, model).eval()
    randomise_head(obs, seed=0)
    data = system.simulate(1, STEPS, 0.1, torch.Generator().manual_seed(1))
    return obs, data.measurements.transpose(0, 1).contiguous()


def _eager(obs: ResidualObserver, ys: torch.Tensor, us=None) -> list[torch.Tensor]:
    state, out = obs.init_state(ys.shape[1]), []
    with torch.no_grad():
        for k, y in enumerate(ys):
            state = obs.step(state, y, None if us is None else us[k])
            out.append(state.estimate.reshape(y.shape[0], -1))
    return out


def _stepped(step, state: tuple, ys: torch.Tensor, us=None) -> list[torch.Tensor]:
    out = []
    with torch.no_grad():
        for k, y in enumerate(ys):
            state = step(*state, y.to(torch.float64), *(() if us is None else (us[k],)))
            out.append(state[0])
    return out


def test_the_online_step_module_is_the_eager_step():
    obs, ys = _rigid_body_observer()
    step = obs.online_step_module()
    assert isinstance(step, OnlineStep) and step.num_hidden == 2
    for a, b in zip(_stepped(step, step.initial_state(), ys), _eager(obs, ys)):
        assert torch.equal(a, b)
    with pytest.raises(TypeError, match="takes \\(x, 2 hidden tensors, y\\)"):
        step(*step.initial_state())


def test_the_exported_step_saved_and_loaded_equals_the_eager_step(tmp_path):
    obs, ys = _rigid_body_observer()
    export_observer(obs, tmp_path / "step.pt2")
    loaded = load_exported_step(tmp_path / "step.pt2")
    assert loaded.meta["signature"] == obs.signature() and loaded.meta["batch"] is None
    assert loaded.meta["inputs"] == ["x", "hidden0", "hidden1", "y"]
    eager = _eager(obs, ys)
    exported = _stepped(loaded, loaded.initial_state(), ys)
    assert exported[-1].dtype == torch.float64
    err = max(float((a - b).abs().max()) for a, b in zip(exported, eager))
    assert err < 1e-6, err
    # the exported estimate stays on the group (float64 state)
    x = exported[-1].view(1, *obs.group.element_shape)
    assert float(obs.group.membership_error(x).max()) < 1e-12
    # any batch size (dynamic first dimension)
    ys3 = torch.cat([ys, ys.flip(0), ys], dim=1)[:5]
    out3 = _stepped(loaded, loaded.initial_state(3), ys3)
    assert torch.allclose(out3[-1], torch.stack(_eager(obs, ys3))[-1], rtol=0, atol=1e-6)


def test_inputs_and_relative_only_factors_export_too(tmp_path):
    group = Product(SO3(), Euclidean(3), names=("R", "p"))
    torch.manual_seed(0)
    obs = ResidualObserver(
        group, Measurement(12, 3, factors={"R": (0, 9), "p": (9, 12)}),
        functools.partial(GRUCore, hidden_size=16, num_layers=1),
        features=[Embedding(drop=["p"]), Readings(drop=["p"]), Innovation()],
    ).eval()
    randomise_head(obs, seed=0)
    g = torch.Generator().manual_seed(0)
    ys = torch.cat(
        (SO3().random((20, 2), generator=g, dtype=torch.float64).flatten(-2),
         torch.randn(20, 2, 3, generator=g, dtype=torch.float64)), -1
    )
    us = torch.randn(20, 2, 3, generator=g)
    export_observer(obs, tmp_path / "step.pt2", batch=2)
    loaded = load_exported_step(tmp_path / "step.pt2")
    assert loaded.meta["inputs"] == ["x", "hidden0", "y", "u"] and loaded.meta["batch"] == 2
    exported = _stepped(loaded, loaded.initial_state(), ys, us)
    for a, b in zip(exported, _eager(obs, ys, us)):
        assert torch.allclose(a, b, rtol=0, atol=1e-6)


def test_the_eager_step_still_refuses_non_finite_measurements():
    obs, ys = _rigid_body_observer()
    y = ys[0].clone()
    y[0, 12] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        obs.step(obs.init_state(1), y)


def test_observer_step_itself_traces_without_its_value_checks():
    """torch.export of a wrapper around the checked step: the finiteness check is skipped while
    tracing (torch.compiler.is_compiling), the shape checks are static and stay."""
    obs, ys = _rigid_body_observer()

    class Wrapper(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.obs = obs

        def forward(self, x, h0, h1, y):
            from manifold_nets.observer import ObserverState

            s = self.obs.step(ObserverState(x, (h0, h1)), y)
            return s.estimate, *s.hidden

    state = obs.init_state(1)
    program = torch.export.export(Wrapper(), (state.estimate, *state.hidden, ys[0]))
    out = program.module()(state.estimate, *state.hidden, ys[0])
    ref = obs.step(state, ys[0])
    assert torch.allclose(out[0], ref.estimate, rtol=0, atol=1e-6)


_HAS_ONNX = all(importlib.util.find_spec(m) for m in ("onnx", "onnxscript"))
_HAS_ORT = importlib.util.find_spec("onnxruntime") is not None


@pytest.mark.skipif(not _HAS_ONNX, reason="ONNX export needs onnx and onnxscript (extra 'export')")
def test_the_float64_state_step_exports_to_a_valid_onnx_model(tmp_path, capfd, caplog):
    import logging
    import warnings

    import onnx

    obs, _ = _rigid_body_observer()
    caplog.set_level(logging.INFO)  # a program that logs at INFO (hydra's commands do)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        path = export_onnx(obs, tmp_path / "step.onnx")
    # quiet: no line of the exporter's passes (one per initializer), of torch's registry
    # (torchvision's skipped operators), no warning
    assert [r.getMessage() for r in caplog.records] == []
    assert capfd.readouterr() == ("", "") and [str(w.message) for w in caught] == []
    model = onnx.load(str(path))
    onnx.checker.check_model(model)
    assert [i.name for i in model.graph.input] == ["x", "hidden0", "hidden1", "y"]


@pytest.mark.skipif(not (_HAS_ONNX and _HAS_ORT),
                    reason="the ONNX round trip needs onnx, onnxscript and onnxruntime")
def test_the_onnx_step_runs_in_onnxruntime_like_the_eager_step(tmp_path):
    """float32 state: onnxruntime's CPU kernels have no float64 Atan (SO(3)'s log)."""
    import onnxruntime as ort

    obs, ys = _rigid_body_observer("float32")
    path = export_onnx(obs, tmp_path / "step.onnx")
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    state = [t.numpy() for t in obs.online_step_module().initial_state()]
    outs = []
    for y in ys:
        state = sess.run(None, dict(zip(names, [*state, y.float().numpy()])))
        outs.append(torch.from_numpy(state[0]))
    err = max(float((a - b).abs().max()) for a, b in zip(outs, _eager(obs, ys.float())))
    assert err < 1e-4, err  # float32 state: 50 steps of float32 rounding, in another runtime


def test_the_exported_step_reads_a_strided_view_like_a_contiguous_one(tmp_path):
    """A row of a bigger array (here every other column of a wider one, strides (36, 2)) gives
    the estimates a contiguous copy gives: the step makes its inputs contiguous."""
    from manifold_nets import load_observer
    from manifold_nets.deploy import export_observer, load_exported_step

    observer, system, _ = load_observer("zoo:rigid_body/paper")
    data = system.simulate(2, 6, 0.1, torch.Generator().manual_seed(0))
    wide = torch.zeros(2, 6, 36, dtype=torch.float64)
    wide[..., ::2] = data.measurements
    export_observer(observer, tmp_path / "step.pt2")
    step = load_exported_step(tmp_path / "step.pt2")
    x, *hidden = step.initial_state(2)
    xs, *hs = step.initial_state(2)
    for k in range(6):
        strided = wide[:, k, ::2]
        assert not strided.is_contiguous()
        x, *hidden = step(x, *hidden, strided.contiguous())
        xs, *hs = step(xs, *hs, strided)
        assert torch.equal(x, xs)
