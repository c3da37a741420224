"""The observer on the device of ``pytest --device`` (default cpu; CI), against the CPU.

Each test runs the same work on the CPU and on ``device``: the shipped observers' rollouts and
online steps, a training run, its resume, and the train command end to end. On the CPU the two
are the same computation (the tests then pin that nothing assumes a device: every tensor a
module makes follows its inputs). On a GPU the float32 network rounds differently from the
CPU's, so rollouts agree to float32 rounding grown over the steps, not bit for bit; the largest
deviation is recorded (``record_property``, in ``--junitxml``) and bounded. ``benchmarks/gpu/run.sh``
runs this file with ``--device cuda``.
"""

from __future__ import annotations

import copy
import functools
import json

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets import GRUCore, TrainSettings, load_observer
from manifold_nets.data import TrajectoryDataset
from manifold_nets.evaluation import evaluate, rollout
from manifold_nets.observer import GroupUpdate, ResidualObserver
from manifold_nets.training import fit
from manifold_nets.observer.fused import runs_lean
from tests.observer_checks import rigid_readings, run_tiny
from tests.test_observer_lean_loop import _observer as _lean_observer
from tests.test_observer_lean_loop import _train as _lean_train

ZOO = [
    "zoo:rigid_body/paper",
    "zoo:rigid_body/nominal",
    "zoo:rigid_body/outliers",
    "zoo:rigid_body/correlated",
    "zoo:rigid_body/bias_walk",
    "zoo:broad/attitude",
]
#: float32 rounding (1e-7) grown over 100 closed-loop steps of a stable observer; the bound on
#: another device than the CPU (on the CPU the results are identical)
ROLLOUT_TOL = 1e-4


def _deviation(group, a: torch.Tensor, b: torch.Tensor) -> float:
    """The largest entry of ``embed(a) - embed(b)`` (both moved to the CPU in float64)."""
    a, b = a.detach().cpu().double(), b.detach().cpu().double()
    return float((group.embed(a) - group.embed(b)).abs().max())


def _bound(device: torch.device, tol: float) -> float:
    return 0.0 if device.type == "cpu" else tol


def _relative(cov: torch.Tensor, want: torch.Tensor) -> float:
    """The largest entry of ``cov - want`` over its scale ``sqrt(want_ii want_jj)``."""
    s = want.diagonal(dim1=-2, dim2=-1).sqrt()
    return float(((cov.cpu() - want) / (s.unsqueeze(-1) * s.unsqueeze(-2))).abs().max())


@pytest.mark.parametrize("entry", ZOO)
def test_shipped_observers_roll_out_and_step_on_the_device(entry, device, record_property):
    loaded = load_observer(entry)
    system, cpu = loaded.system, loaded.observer
    there = load_observer(entry, map_location=device).observer
    assert {p.device for p in there.parameters()} == {device}
    data = system.simulate(6, 100, 0.2, torch.Generator().manual_seed(3))
    est_cpu = rollout(cpu, data)
    est_dev = rollout(there, data)  # the CPU's data, moved by the observer; estimates on the CPU
    assert est_dev.device.type == "cpu" and est_dev.dtype == est_cpu.dtype
    group = system.group
    assert float(group.membership_error(est_dev).max()) < 1e-9  # float64 state on any device
    dev = _deviation(group, est_dev, est_cpu)
    record_property(f"rollout_deviation[{entry}]", dev)
    assert dev <= _bound(device, ROLLOUT_TOL), dev
    # the online step (what deployment runs), fed one sample at a time on the device
    step = there.online_step_module()  # OnlineStep, or an ensemble's EnsembleStep
    x, *state = step.initial_state(len(data))
    assert x.device == device and all(s.device == device for s in state)
    y, u = data.measurements.to(device), data.inputs.to(device)
    with torch.inference_mode():
        for k in range(data.measurements.shape[1]):
            x, *state = step(x, *state, y[:, k], *((u[:, k],) if there.input_dim else ()))
    last = x.reshape(est_dev[:, -1].shape)
    assert last.device == device
    torch.testing.assert_close(last.cpu(), est_dev[:, -1], rtol=0, atol=1e-9)


def test_a_calibrated_ensemble_rolls_out_and_steps_on_the_device(device, record_property):
    """The zoo's BROAD ensemble with a readings readout (random weights): its covariances on the
    device follow the CPU's, in the rollout and the online step."""
    from manifold_nets.observer import CalibratedObserver, CovarianceReadout
    from manifold_nets.observer.covariance import input_width
    from observer_checks import assert_covariances_close

    loaded = load_observer("zoo:broad/attitude")
    ens, system = loaded.observer, loaded.system
    torch.manual_seed(0)
    readout = CovarianceReadout(ens.group, input_width(ens, "readings"), memory=8, source="readings")
    with torch.no_grad():
        for p in readout.parameters():
            p.normal_(0, 0.1)
    cpu = CalibratedObserver(ens, readout).eval()
    there = CalibratedObserver(load_observer("zoo:broad/attitude", map_location=device).observer,
                               copy.deepcopy(readout)).to(device).eval()
    data = system.simulate(4, 60, 0.2, torch.Generator().manual_seed(3))
    y, u = data.measurements, data.inputs
    with torch.no_grad():
        est_cpu, cov_cpu = cpu(y, u)
        est_dev, cov_dev = there(y.to(device), u.to(device))
        assert cov_dev.device == device
        dev = _deviation(ens.group, est_dev, est_cpu)
        record_property("calibrated_ensemble_deviation", dev)
        assert dev <= _bound(device, ROLLOUT_TOL), dev
        # the readout's float32 GRU: cuDNN's (TF32 by default, a 10-bit mantissa) against the
        # CPU's; measured on an H100: 1.3e-4 of an entry's scale
        record_property("calibrated_ensemble_cov_deviation", _relative(cov_dev, cov_cpu))
        assert_covariances_close(cov_dev.cpu(), cov_cpu, tol=max(_bound(device, 1e-3), 1e-12))
        state = there.init_state(4)
        for k in range(y.shape[1]):
            state, P = there.step(state, y[:, k].to(device), u[:, k].to(device))
        assert_covariances_close(P.cpu(), cov_cpu[:, -1], tol=max(_bound(device, 1e-3), 1e-5))


CALIBRATED = [e for e in ZOO if e != "zoo:rigid_body/paper"]  # the entries with a covariance.pt


@pytest.mark.parametrize("entry", CALIBRATED)
def test_the_shipped_covariances_on_the_device_follow_the_cpu(entry, device, record_property):
    """Each zoo entry's own ``covariance.pt`` (BROAD's reads the context of ``--context 1``;
    here random numbers of its shape) on the device: the rollout's covariances and the online
    step's last one follow the CPU's."""
    from manifold_nets.plugins import zoo_path
    from manifold_nets.covariance_training import load_readout
    from observer_checks import assert_covariances_close

    loaded = load_observer(entry)
    path = zoo_path(entry.removeprefix("zoo:")) / "covariance.pt"
    cpu = load_readout(path, loaded.observer).eval()
    there = load_readout(path, load_observer(entry, map_location=device).observer)
    there = there.to(device).eval()
    data = loaded.system.simulate(4, 60, 0.2, torch.Generator().manual_seed(3))
    y, u = data.measurements, data.inputs
    c = cpu.readout.context
    ctx = torch.randn(4, 60, c, generator=torch.Generator().manual_seed(5)) if c else None

    def run(cal, where):
        return cal(y.to(where), u.to(where), **({"context": ctx.to(where)} if c else {}))

    with torch.no_grad():
        est_cpu, cov_cpu = run(cpu, "cpu")
        est_dev, cov_dev = run(there, device)
        assert cov_dev.device == device
        dev = _deviation(loaded.system.group, est_dev, est_cpu)
        record_property(f"calibrated_deviation[{entry}]", dev)
        assert dev <= _bound(device, ROLLOUT_TOL), dev
        record_property(f"calibrated_cov_deviation[{entry}]", _relative(cov_dev, cov_cpu))
        # cuDNN's GRU in TF32 (its default, a 10-bit mantissa): measured on an H100 4e-4 to
        # 1.1e-3 of an entry's scale over these 60 steps; in float32 4.8e-6 to 1.1e-5
        if device.type == "cuda":
            with torch.backends.cudnn.flags(enabled=True, allow_tf32=False):
                cov_exact = run(there, device)[1]
            record_property(f"calibrated_cov_deviation_no_tf32[{entry}]",
                            _relative(cov_exact, cov_cpu))
            assert_covariances_close(cov_exact.cpu(), cov_cpu, tol=1e-4)
        assert_covariances_close(cov_dev.cpu(), cov_cpu, tol=max(_bound(device, 5e-3), 1e-12))
        state = there.init_state(4)
        for k in range(y.shape[1]):
            extra = {"context": ctx[:, k].to(device)} if c else {}
            state, P = there.step(state, y[:, k].to(device), u[:, k].to(device), **extra)
        assert P.device == device
        assert_covariances_close(P.cpu(), cov_cpu[:, -1], tol=max(_bound(device, 1e-3), 1e-5))


GROUP = Product(SO3(), Euclidean(3), names=("R", "p"))


def _walks(n: int, t: int, seed: int) -> TrajectoryDataset:
    """Random walks on SO(3) x R^3 measured as their noisy embedding."""
    g = torch.Generator().manual_seed(seed)
    xs = [GROUP.random((n,), generator=g, dtype=torch.float64)]
    for _ in range(t):
        xs.append(GROUP.rplus(xs[-1], 0.2 * torch.randn(n, 6, generator=g, dtype=torch.float64)))
    states = torch.stack(xs, 1)
    meas = GROUP.embed(states[:, 1:]) + 0.1 * torch.randn(n, t, 12, generator=g,
                                                          dtype=torch.float64)
    return TrajectoryDataset(states, meas, torch.zeros(n, t, 0, dtype=torch.float64))


def _observer(device) -> ResidualObserver:
    torch.manual_seed(0)
    core = functools.partial(GRUCore, hidden_size=32, num_layers=2)
    return ResidualObserver(GROUP, 12, core, update=GroupUpdate({})).to(device)


def _fit(device, out, **settings):
    model = _observer(device)
    base = {"epochs": 2, "batch_size": 8, "lr": 3e-3, "progress": False}
    res = fit(model, _walks(32, 20, 0), _walks(8, 20, 1), TrainSettings(**{**base, **settings}),
              out_dir=out, seed=4)
    return model, res


def test_training_on_the_device_follows_the_cpu(tmp_path, device, record_property):
    cpu, res_cpu = _fit(torch.device("cpu"), tmp_path / "cpu")
    there, res_dev = _fit(device, tmp_path / "dev")
    assert {p.device for p in there.parameters()} == {device}
    losses = [(a["val_loss"], b["val_loss"]) for a, b in zip(res_cpu.history, res_dev.history)]
    worst = max(abs(a - b) / a for a, b in losses)
    record_property("training_val_loss_relative_deviation", worst)
    assert len(losses) == 3 and worst <= _bound(device, 1e-4), losses
    # the checkpoints are read back on the CPU
    best = torch.load(res_dev.best_path, map_location="cpu", weights_only=True)
    assert all(t.device.type == "cpu" for t in best["model"].values())
    # evaluation of the device's model: the same rows as the CPU's within the same rounding
    test = _walks(8, 30, 2)
    row_cpu, row_dev = evaluate(cpu, test).row, evaluate(there, test).row
    for key, value in row_cpu.items():
        if isinstance(value, float) and key != "seconds":
            want = pytest.approx(value, rel=_bound(device, 1e-4), abs=1e-12, nan_ok=True)
            assert row_dev[key] == want, key


def test_resume_on_the_device_gives_the_uninterrupted_weights(tmp_path, device, record_property):
    straight, _ = _fit(device, tmp_path / "a")
    _fit(device, tmp_path / "b", epochs=1)
    resumed, _ = _fit(device, tmp_path / "c", resume=str(tmp_path / "b"))
    worst = max(float((a - b).abs().max()) for a, b in
                zip(straight.state_dict().values(), resumed.state_dict().values()))
    record_property("resume_weight_deviation", worst)
    # the CPU is bit for bit; cuBLAS may pick another reduction order between two runs
    assert worst <= _bound(device, 1e-6), worst


@pytest.mark.parametrize("schedule", ["constant", "cosine"])
def test_the_captured_training_step_follows_the_eager_one(tmp_path, device, schedule,
                                                          monkeypatch, record_property):
    """train.cuda_graph: the same training as the eager step (capturable AdamW, float32
    rounding), the graph replayed for every full batch, the partial last batch eager."""
    if device.type != "cuda":
        with pytest.raises(ValueError, match="train.cuda_graph=true needs the model on a CUDA"):
            _fit(device, tmp_path / "refused", cuda_graph=True)
        assert not (tmp_path / "refused").exists()
        return
    replays = []
    real = torch.cuda.CUDAGraph.replay
    monkeypatch.setattr(torch.cuda.CUDAGraph, "replay", lambda g: (replays.append(1), real(g)))
    settings = {"epochs": 3, "batch_size": 6, "schedule": schedule}  # 32 = 5 x 6 + 2
    _, eager = _fit(device, tmp_path / "eager", **settings)
    _, graphed = _fit(device, tmp_path / "graph", cuda_graph=True, **settings)
    worst = max(abs(a["val_loss"] - b["val_loss"]) / a["val_loss"]
                for a, b in zip(eager.history, graphed.history))
    record_property(f"cuda_graph_val_loss_relative_deviation[{schedule}]", worst)
    assert worst <= 1e-4, (eager.history, graphed.history)
    # 5 full batches an epoch: 3 eager warm-up steps, then the graph (captured once for the
    # constant rate, once an epoch for the cosine schedule, 3 warm-up steps each time)
    assert len(replays) == (2 + 5 + 5 if schedule == "constant" else 2 + 2 + 2), len(replays)


def test_the_train_command_on_the_device(tmp_path, device):
    """The whole command (data, training, checkpoints, table, figure) with train.device set."""
    name = "cpu" if device.type == "cpu" else str(device)
    run_tiny("default", tmp_path, tmp_path / "run", f"train.device={name}", "train.epochs=2")
    metrics = json.loads((tmp_path / "run" / "results" / "metrics.json").read_text())
    assert metrics["best_epoch"] in (0, 1, 2)
    assert (tmp_path / "run" / "results" / "table.md").is_file()
    loaded = load_observer(tmp_path / "run")  # the files are the CPU's to read
    assert {p.device.type for p in loaded.observer.parameters()} == {"cpu"}


def test_the_lean_rollout_on_the_device_follows_the_step_by_step_one(device, monkeypatch,
                                                                     record_property):
    """The lean rollout (``fused.lean_steps``, ``tests/test_observer_lean_loop.py``) runs on the
    device and gives the step-by-step rollout's estimates, loss and gradients there: to the bit
    on the CPU, to float32 rounding on a GPU (relative to each tensor's largest entry)."""
    y, x = (t.to(device) for t in rigid_readings(n=64, t=20))
    lean_obs = _lean_observer().to(device)
    assert runs_lean(lean_obs)
    n_params = len(list(lean_obs.parameters()))
    lean = _lean_train(lean_obs, y, x, True, monkeypatch, steps=1)[:-n_params]
    plain = _lean_train(_lean_observer().to(device), y, x, False, monkeypatch, steps=1)
    plain = plain[:-n_params]  # (after one AdamW step, ~lr * sign(g): not a rounding measure)
    assert len(lean) == len(plain) == 2 + n_params
    assert all(a.device == device for a in lean)
    worst = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))
                for a, b in zip(lean, plain))
    record_property("lean_rollout_relative_deviation", worst)
    assert worst <= _bound(device, 1e-4), worst
