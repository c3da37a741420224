"""Training, checkpoints, resume, divergence, noise augmentation and evaluation on tiny data.

The data are synthetic, built with ``groups`` directly: random walks on SO(3) x R^3 with a
constant R^2 factor, measured as the noisy embedding of the state (no example system needed).
"""

from __future__ import annotations

import functools
import json

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.checkpoint import FORMAT, CheckpointError, load_checkpoint, save_checkpoint
from manifold_nets.data import TrajectoryDataset
from manifold_nets.evaluation import evaluate
from manifold_nets.reporting import plot_errors, write_table
from manifold_nets.observer import GroupUpdate, ResidualObserver
from manifold_nets import GRUCore, MeasurementNoise, TrainSettings
from manifold_nets.training import TrainingDiverged, fit, learning_rate, validation_loss
from tests.observer_checks import randomise_head

GROUP = Product(SO3(), Euclidean(3), Euclidean(2), names=("R", "p", "b"))
MEAS = GROUP.embedding_dim  # the measurement is the noisy embedding of the state


class EmbeddingSystem:
    """A toy system: y_{k+1} = embed(x_{k+1}) + noise (rotations by exp, the rest added)."""

    group = GROUP
    measurement_dim = MEAS
    input_dim = 0
    noise_dim = GROUP.tangent_dim

    def apply_noise(self, measurements, noise):
        x = GROUP.unembed(measurements)
        return GROUP.embed(GROUP.rplus(x, noise))

    def measurement_errors(self, data):
        diff = GROUP.embed(GROUP.unembed(data.measurements)) - GROUP.embed(data.states[:, 1:])
        return {
            "R": torch.linalg.vector_norm(diff[..., :9], dim=-1),
            "p": torch.linalg.vector_norm(diff[..., 9:12], dim=-1),
        }


def make_data(n=24, t=12, sigma=0.0, seed=0) -> TrajectoryDataset:
    g = torch.Generator().manual_seed(seed)
    x0 = GROUP.random((n,), generator=g, dtype=torch.float64)
    steps = 0.2 * torch.randn(n, t, GROUP.tangent_dim, generator=g, dtype=torch.float64)
    steps[..., -2:] = 0  # the "bias" factor is constant
    xs = [x0]
    for k in range(t):
        xs.append(GROUP.rplus(xs[-1], steps[:, k]))
    states = torch.stack(xs, 1)
    noise = sigma * torch.randn(n, t, GROUP.tangent_dim, generator=g, dtype=torch.float64)
    meas = EmbeddingSystem().apply_noise(GROUP.embed(states[:, 1:]), noise)
    return TrajectoryDataset(
        states, meas, torch.zeros(n, t, 0, dtype=torch.float64), {"sigma": sigma}
    )


def gru(hidden=16):
    """A factory of a one-layer GRU core with ``hidden`` units."""
    return functools.partial(GRUCore, hidden_size=hidden, num_layers=1)


def make_model(seed=0, hidden=16) -> ResidualObserver:
    """A small observer, its output layer random (``nn.Linear``'s initialisation from the seeded
    generator) as an untrained observer's was before a core the observer makes started at zero:
    the training tests' losses and tolerances are those of that start."""
    torch.manual_seed(seed)
    model = ResidualObserver(GROUP, MEAS, gru(hidden), update=GroupUpdate({"b": "absolute"}))
    randomise_head(model)
    return model


FIT = {"epochs": 3, "batch_size": 8, "lr": 1e-2, "progress": False}


def train_model(model, train, val, out_dir, seed=7, transform=None, **settings):
    """``fit`` with the test's settings (``FIT``) and ``settings`` on top."""
    return fit(
        model, train, val, TrainSettings(**{**FIT, **settings}), out_dir=out_dir, seed=seed,
        transform=transform,
    )


def test_training_lowers_the_loss(tmp_path):
    train, val = make_data(32, seed=0), make_data(8, seed=1)
    model = make_model()
    res = train_model(model, train, val, tmp_path)
    losses = [h["val_loss"] for h in res.history]
    assert len(losses) == 4 and losses[0] == res.history[0]["val_loss"]
    assert min(losses[1:]) < 0.7 * losses[0], losses
    assert res.best_val_loss == min(losses)
    # the logs: one row per epoch (0 = untrained) in CSV and JSON
    rows = json.loads((tmp_path / "log.json").read_text())
    assert [r["epoch"] for r in rows] == [0, 1, 2, 3]
    assert (
        (tmp_path / "log.csv").read_text().splitlines()[0].startswith("epoch,train_loss,val_loss")
    )
    # best.pt holds the best epoch's weights
    best = load_checkpoint(res.best_path, expected_signature=model.signature())
    assert best["epoch"] == res.best_epoch
    fresh = make_model(seed=99)
    fresh.load_state_dict(best["model"])
    assert validation_loss(fresh, val) == pytest.approx(res.best_val_loss, rel=1e-6)


@pytest.mark.parametrize(
    "schedule, param_lr", [("constant", {}), ("cosine", {}), ("cosine", {"core.head": 3e-2})]
)
def test_resume_gives_the_uninterrupted_result(tmp_path, schedule, param_lr):
    train, val = make_data(24, seed=0), make_data(8, seed=1)
    # the noise's RNG state matters too, and the learning rate of a resumed epoch (of each
    # parameter group: train.param_lr)
    noisy = {"transform": MeasurementNoise(EmbeddingSystem(), 0.0, 0.3), "schedule": schedule,
             "param_lr": param_lr}
    straight = make_model()
    train_model(straight, train, val, tmp_path / "a", **noisy)

    first = make_model()
    train_model(first, train, val, tmp_path / "b", epochs=1, **noisy)
    resumed = make_model(seed=123)  # different init: everything must come from the checkpoint
    res = train_model(resumed, train, val, tmp_path / "c", resume=str(tmp_path / "b"), **noisy)

    for (k, a), b in zip(straight.state_dict().items(), resumed.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=k)
    a_hist = json.loads((tmp_path / "a" / "log.json").read_text())
    assert [h["val_loss"] for h in res.history] == [h["val_loss"] for h in a_hist]
    assert (tmp_path / "c" / "checkpoints" / "best.pt").is_file()


def test_learning_rate_schedules():
    assert [learning_rate(e, epochs=5, lr=2e-3) for e in range(1, 6)] == [2e-3] * 5
    lrs = [
        learning_rate(e, epochs=40, lr=1e-3, schedule="cosine", lr_min=1e-5) for e in range(1, 41)
    ]
    assert lrs[0] == 1e-3
    assert all(a > b for a, b in zip(lrs, lrs[1:]))  # strictly falling ...
    assert 1e-5 < lrs[-1] < 1e-5 + 0.01 * (1e-3 - 1e-5)  # ... towards lr_min, never at it
    assert lrs[20] == pytest.approx((1e-3 + 1e-5) / 2, rel=1e-12)  # half way at epoch 21 of 40
    assert learning_rate(1, epochs=1, lr=1e-3, schedule="cosine") == 1e-3


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"schedule": "linear"}, "schedule='linear'.*constant, cosine"),
        ({"schedule": "cosine", "lr_min": 0.1}, "lr_min"),
        ({"schedule": "cosine", "lr_min": -1.0}, "lr_min"),
        ({"lr": 0.0}, "lr must be a positive"),
        ({"lr": float("nan")}, "lr must be a positive"),
    ],
)
def test_bad_learning_rate_settings_fail_before_any_work(tmp_path, kwargs, match):
    settings = {**FIT, **kwargs}
    with pytest.raises(ValueError, match=match):
        train_model(make_model(), make_data(8), make_data(4, seed=1), tmp_path / "run", **kwargs)
    assert not (tmp_path / "run").exists()
    with pytest.raises(ValueError, match=match):
        learning_rate(
            1, epochs=3, lr=settings["lr"], **{k: v for k, v in kwargs.items() if k != "lr"}
        )


def test_cosine_schedule_sets_each_epochs_rate(tmp_path):
    train, val = make_data(24, seed=0), make_data(8, seed=1)
    runs = {}
    for schedule in ("constant", "cosine"):
        model = make_model()
        res = train_model(model, train, val, tmp_path / schedule, schedule=schedule, lr_min=1e-4)
        runs[schedule] = model
        want = [
            learning_rate(e, epochs=3, lr=1e-2, schedule=schedule, lr_min=1e-4) for e in (1, 2, 3)
        ]
        assert [h["lr"] for h in res.history[1:]] == want  # read back from the optimizer
    assert want[0] == 1e-2 and want[1] < 1e-2
    a, b = runs["constant"].state_dict(), runs["cosine"].state_dict()
    assert any(not torch.equal(a[k], b[k]) for k in a)  # the schedule reached the optimizer


def test_checkpoint_round_trip_and_errors(tmp_path):
    model = make_model()
    path = save_checkpoint(
        tmp_path / "m.pt",
        {
            "model": model.state_dict(),
            "signature": model.signature(),
            "config": {"model": {"hidden_size": 16}},
            "epoch": 3,
        },
    )
    ckpt = torch.load(path, weights_only=True)  # plain data and tensors only
    assert ckpt["epoch"] == 3 and ckpt["config"]["model"]["hidden_size"] == 16
    other = make_model(seed=5)
    other.load_state_dict(load_checkpoint(path, expected_signature=other.signature())["model"])
    for a, b in zip(model.parameters(), other.parameters()):
        assert torch.equal(a, b)
    assert not list(tmp_path.glob("*.tmp"))  # atomic write left no temporary file

    bigger = make_model(hidden=32)
    with pytest.raises(
        CheckpointError, match="another model.*hidden_size: checkpoint 16, model 32"
    ):
        load_checkpoint(path, expected_signature=bigger.signature())
    rigid = ResidualObserver(Product(SO3(), Euclidean(3)), MEAS, gru(16))
    with pytest.raises(CheckpointError, match="group"):
        load_checkpoint(path, expected_signature=rigid.signature())
    with pytest.raises(CheckpointError, match="no checkpoint at"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a loadable checkpoint"):
        load_checkpoint(tmp_path / "junk.pt")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="format"):
        load_checkpoint(tmp_path / "foreign.pt")


def test_nan_loss_stops_with_a_clear_message_and_keeps_best(tmp_path):
    train, val = make_data(16, seed=0), make_data(8, seed=1)
    train.states[3, 5, 9] = float("nan")  # a corrupt target: the loss of its batch is NaN
    with pytest.raises(
        TrainingDiverged, match=r"training loss became nan at epoch 1, batch \d.*best checkpoint"
    ):
        train_model(make_model(), train, val, tmp_path, batch_size=16)
    assert (tmp_path / "checkpoints" / "best.pt").is_file()


def test_a_loss_that_explodes_without_going_nan_stops_training(tmp_path):
    """A finite loss far above the start (here a corrupt target of 1e9) stops training as a NaN
    does, naming what happened, and keeps the best checkpoint."""
    train, val = make_data(16, seed=0), make_data(8, seed=1)
    train.states[3, 5, 9] = 1e9
    with pytest.raises(TrainingDiverged, match=r"training loss exploded without going NaN "
                                               r"\(.*, over .*\) at epoch 1, batch \d"):
        train_model(make_model(), train, val, tmp_path, batch_size=16)
    assert (tmp_path / "checkpoints" / "best.pt").is_file()


def test_an_untrained_observer_whose_steps_grow_without_bound_is_refused(tmp_path):
    """Validation loss 2.5e23 before any step was once trained on silently; over 1e12 the run
    stops before the first step and says how to start the head."""
    model = make_model()
    with torch.no_grad():
        model.core.head.bias[-2:] = 1e7  # the absolute "bias" factor set to 1e7 every step
    with pytest.raises(TrainingDiverged, match=r"validation loss of the starting model is .*, "
                                               r"over 1e\+12.*start its head at zero"):
        train_model(model, make_data(16, seed=0), make_data(8, seed=1), tmp_path)


def test_noise_augmentation_needs_the_system_hook():
    with pytest.raises(ValueError, match="apply_noise"):
        MeasurementNoise(object(), 0.0, 0.2)
    with pytest.raises(ValueError, match="0 <= sigma_min <= sigma_max"):
        MeasurementNoise(EmbeddingSystem(), 0.3, 0.2)


def test_training_rejects_data_of_another_system(tmp_path):
    bad = make_data(8)
    bad = TrajectoryDataset(bad.states, bad.measurements[..., :10], bad.inputs, {})
    with pytest.raises(ValueError, match="measurements of size 10"):
        train_model(make_model(), bad, make_data(4), tmp_path)


def test_evaluation_table_and_figure(tmp_path):
    model = make_model()
    data = make_data(6, t=20, sigma=0.1, seed=3)
    res = evaluate(model, data, EmbeddingSystem(), skip=5)
    row = res.row
    assert row["sigma"] == 0.1 and row["steps"] == 20 and row["sequences"] == 6
    for key in (
        "R est",
        "R meas",
        "R reduction %",
        "p est",
        "p meas",
        "b est",
        "membership mean",
        "membership max",
    ):
        assert key in row, key
    assert row["R reduction %"] == pytest.approx(100 * (1 - row["R est"] / row["R meas"]))
    assert 0.05 < row["R meas"] < 0.5  # sigma 0.1 on 3 axes: about 0.1 * sqrt(2 * 3) * ...
    assert row["membership max"] < 1e-12
    assert res.curves["R est"].shape == (21,) and torch.isnan(res.curves["R meas"][0])
    # without a system: generic per-factor errors, no measurement columns
    plain = evaluate(model, data, None, skip=5).row
    assert plain["R est"] == pytest.approx(row["R est"]) and "R meas" not in plain
    csv_path, md_path = write_table([row, {**row, "sigma": 0.2}], tmp_path / "table", title="t")
    assert csv_path.read_text().count("\n") == 3
    assert "| sigma | R est | R meas | R reduction % |" in md_path.read_text()
    png = plot_errors(res, tmp_path / "fig.png", title="tiny")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="skip"):
        evaluate(model, data, skip=20)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"epochs": -1}, "epochs must be an integer >= 0 (0: no step, the starting model is "
                         "kept), got -1."),
        ({"batch_size": 0}, "batch_size must be an integer >= 1, got 0."),
        ({"max_batches": 0}, "max_batches must be an integer >= 1 or None (null: the whole "
                             "training split), got 0."),
        ({"grad_clip": -1.0}, "grad_clip must be > 0 or None (null: no clipping), got -1.0"),
        ({"grad_clip": 0.0}, "grad_clip must be > 0 or None (null: no clipping), got 0.0"),
        ({"threads": 0}, "threads must be an integer >= 1 or None (null: one thread, or "
                          "OMP_NUM_THREADS when set), got 0."),
        ({"time_limit": 0}, "time_limit must be a number of minutes > 0 or None (null: all "
                            "epochs), got 0."),
        ({"time_limit": float("nan")}, "time_limit must be a number of minutes > 0"),
        ({"time_limit": "10"}, "time_limit must be a number of minutes > 0"),
    ],
)
def test_nonsense_settings_fail_before_any_work(tmp_path, kwargs, message):
    # max_batches=0 made no optimizer step and logged a loss of 0.0; a negative grad_clip
    # ascends, zero freezes the model (epochs=0 is meant: the next test)
    with pytest.raises(ValueError) as err:
        train_model(make_model(), make_data(8), make_data(4, seed=1), tmp_path / "run", **kwargs)
    assert str(err.value).startswith(message)
    assert not (tmp_path / "run").exists()


def test_a_time_limit_stops_after_the_epoch_the_next_would_overrun_and_resume_goes_on(tmp_path):
    train, val = make_data(16), make_data(4, seed=1)
    # a limit shorter than any epoch: one epoch is trained, its checkpoints kept
    res = train_model(make_model(), train, val, tmp_path / "a", epochs=4, time_limit=1e-9)
    assert [r["epoch"] for r in res.history] == [0, 1]
    assert (tmp_path / "a" / "checkpoints" / "last.pt").is_file()
    # resume continues where the limit stopped it, to the same weights as one straight run
    model = make_model(seed=5)
    resumed = train_model(model, train, val, tmp_path / "b", epochs=2, resume=str(tmp_path / "a"))
    straight = make_model()
    train_model(straight, train, val, tmp_path / "c", epochs=2)
    assert [r["epoch"] for r in resumed.history] == [0, 1, 2]
    for (k, a), b in zip(straight.state_dict().items(), model.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=k)
    # a limit no epoch reaches: all of them
    res = train_model(make_model(), train, val, tmp_path / "d", epochs=2, time_limit=60.0)
    assert [r["epoch"] for r in res.history] == [0, 1, 2]


def test_zero_epochs_validate_and_save_the_starting_model_only(tmp_path):
    # the train command's epochs=0 with init_from: a model's weights from elsewhere, as they are
    model = make_model()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    res = train_model(model, make_data(8), make_data(4, seed=1), tmp_path / "run", epochs=0)
    assert res.best_epoch == 0 and [r["epoch"] for r in res.history] == [0]
    assert res.last_path is None and not (tmp_path / "run" / "checkpoints" / "last.pt").exists()
    saved = torch.load(res.best_path, weights_only=True)["model"]
    for k, v in before.items():
        assert torch.equal(model.state_dict()[k], v) and torch.equal(saved[k], v), k


def nan_model():
    model = make_model()
    with torch.no_grad():
        next(model.parameters())[0, 0] = float("nan")
    return model


def test_nan_weights_fail_the_evaluation_naming_the_method_and_the_sequence():
    from manifold_nets.evaluation import EstimatesNotFinite

    data = make_data(6, t=20, sigma=0.1, seed=3)
    with pytest.raises(
        EstimatesNotFinite,
        match=r"^learned: the estimates are not finite \(NaN/Inf\) in 6 of 6 sequences, the "
        r"first in sequence 0 from step 1 on; no metric",
    ):
        evaluate(nan_model(), data, EmbeddingSystem(), skip=5)
    est = GROUP.identity((6, 21), dtype=torch.float64)
    est[4, 7, 0] = float("inf")  # one sequence, one step
    with pytest.raises(EstimatesNotFinite, match="in 1 of 6 sequences, the first in sequence 4 "
                       "from step 7 on"):
        evaluate(make_model(), data, EmbeddingSystem(), skip=5, estimates=est)


def _saved(tmp_path, **change):
    """A checkpoint of ``make_model()`` with fields changed (``None``: removed)."""
    model = make_model()
    payload = {
        "format": FORMAT, "model": model.state_dict(),
        "signature": model.signature(), "config": {}, "epoch": 2,
    }  # fmt: skip
    payload.update(change)
    payload = {k: v for k, v in payload.items() if v is not None}
    torch.save(payload, tmp_path / "m.pt")
    return tmp_path / "m.pt"


def test_a_checkpoint_without_signature_is_refused_naming_the_file_and_field(tmp_path):
    path = _saved(tmp_path, signature=None)  # was: KeyError: 'signature'
    with pytest.raises(CheckpointError, match=r"m\.pt: the field 'signature' is missing \(the "
                       r"file has \['config', 'epoch', 'format', 'model'\]\)\. The file is "
                       "damaged or was not written by manifold_nets"):
        load_checkpoint(path, expected_signature=make_model().signature())


@pytest.mark.parametrize("epoch", ["3", 1.5, None])
def test_a_checkpoint_with_a_non_integer_epoch_is_refused(tmp_path, epoch):
    path = _saved(tmp_path, epoch=epoch)
    what = "is missing" if epoch is None else f"must be an integer >= 0, got {epoch!r}"
    with pytest.raises(CheckpointError, match=rf"m\.pt: the field 'epoch' {what}"):
        load_checkpoint(path)


def test_a_tensor_of_the_wrong_shape_is_refused_naming_the_file(tmp_path):
    from manifold_nets.checkpoint import load_weights

    state = make_model().state_dict()
    name = next(iter(state))
    state[name] = torch.zeros(3, 3)  # the signature still matches; a tensor does not
    path = _saved(tmp_path, model=state)
    model = make_model(seed=4)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with pytest.raises(CheckpointError, match=rf"m\.pt: the field 'model' does not fit the model "
                       rf"\({name}: checkpoint \(3, 3\), model"):  # was: torch's RuntimeError
        load_weights(model, path)
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())


def test_resume_from_a_garbage_rng_state_is_refused_naming_the_file(tmp_path):
    train, val = make_data(16, seed=0), make_data(4, seed=1)
    train_model(make_model(), train, val, tmp_path / "a", epochs=1)
    last = tmp_path / "a" / "checkpoints" / "last.pt"
    ckpt = torch.load(last, weights_only=True)
    ckpt["rng"]["generator"] = torch.zeros(5056, dtype=torch.uint8)  # the size, not a state
    torch.save(ckpt, last)
    state = torch.get_rng_state()
    with pytest.raises(CheckpointError, match=r"last\.pt: the field 'rng\.generator' is not a "
                       r"generator state \(Invalid mt19937 state\)"):
        train_model(make_model(), train, val, tmp_path / "b", resume=str(tmp_path / "a"))
    assert torch.equal(torch.get_rng_state(), state)  # nothing restored half way
    ckpt["rng"] = {"generator": "garbage", "torch": ckpt["rng"]["torch"]}
    torch.save(ckpt, last)
    with pytest.raises(CheckpointError, match=r"last\.pt: the field 'rng\.generator' must be a "
                       r"generator state \(a uint8 tensor\), got 'garbage'"):
        train_model(make_model(), train, val, tmp_path / "b", resume=str(tmp_path / "a"))
