"""Train the learned observer for BROAD: pre-train on the simulator, fine-tune on real windows.

::

    python -m manifold_nets_examples.broad.train --data-dir ../shared/broad/data_mat --out runs/broad

Stages (each optional, each a :func:`manifold_nets.fit` run in its own sub-folder):

1. ``pretrain``: sequences of :class:`~.simulator.BroadSimulator` (this IMU's sensor models at
   ``sigma = 1``) at 285.7 Hz, decimated like the recordings (:mod:`.rate`);
2. ``finetune``: windows cut from the training trials (validation: windows of the validation
   trials), from the pre-trained weights, with the random-mounting augmentation
   (:class:`~.learning.RandomMounting`); masked where the reference is missing.

Every training and validation window starts near its true first state
(:func:`~.learning.near_truth_start`: a window from inside a trial is where the deployed
observer has converged); whole trials are evaluated from TRIAD of their first sample.

The run folder then holds ``config.yaml`` and ``checkpoints/best.pt`` (the last stage's best
model: ``manifold_nets.load_observer(<run folder>)`` and ``broad.apply`` read it) and the
evaluation on whole validation and test trials from their first sample
(:func:`~.compare.comparison`): ``results/``. The split is ``configs/broad/trials.yaml``.

Every argument is checked before any work (:func:`prepare`): the numbers' ranges, the run
folder (a folder that can be written and holds no trained observer), the split names of
``--eval-splits``, the trials (read whole; the fine-tuning windows cut from them, so a window
longer than every trial fails here), that each evaluated trial has samples to score, and
``--init-from`` (loaded into the model). Errors end the command with ``error: ...``; the best
checkpoint is copied into place atomically.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shutil
import time
from dataclasses import asdict
from pathlib import Path

import torch
import yaml

from manifold_nets import TrainSettings, fit
from manifold_nets.atomic import atomic_open, write_text_atomic
from manifold_nets.checkpoint import load_weights, save_checkpoint
from manifold_nets.destination import check_destination
from manifold_nets.losses import check_loss_weights
from manifold_nets.threads import use_threads
from manifold_nets.training import check_settings

from .data import BroadFormatError, read_trials, split_trials, trials_to_dataset
from .evaluate import check_scored, chosen_splits, evaluate_run
from .learning import (
    RandomHeading,
    RandomMounting,
    field_gate,
    make_observer,
    model_config,
    near_truth_start,
    without_magnetometer,
)
from .prefilter import prefilter_dataset, prefiltered
from .rate import decimate
from .simulator import BROAD_DT, BroadSimulator

log = logging.getLogger("broad.train")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data-dir", default=None, help="BROAD's .mat files (default: the split file's)")
    p.add_argument("--split", default=None, help="trials yaml (default configs/broad/trials.yaml)")
    p.add_argument("--out", required=True, help="the run folder (created; must not hold a run)")
    p.add_argument("--hidden-size", type=int, default=64)
    p.add_argument("--num-layers", type=int, default=2)
    p.add_argument("--output-scale", type=float, default=0.01)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--decimation", type=int, default=8,
                   help="the observer steps every k-th sample (285.7 / k Hz; rate.py)")
    p.add_argument("--pretrain-sequences", type=int, default=256, help="0: no pre-training")
    p.add_argument("--pretrain-length", type=int, default=256, help="observer steps")
    p.add_argument("--pretrain-epochs", type=int, default=10)
    p.add_argument("--window", type=int, default=256, help="fine-tuning window (observer steps)")
    p.add_argument("--stride", type=int, default=128, help="between windows (observer steps)")
    p.add_argument("--finetune-epochs", type=int, default=10, help="0: no fine-tuning")
    p.add_argument("--mounting", type=float, default=3.141592653589793,
                   help="max angle (rad) of the random mounting; 0: no augmentation")
    p.add_argument("--magnetometer", type=int, choices=(0, 1), default=1,
                   help="0: a 6-D observer (gyroscope and accelerometer; the magnetometer "
                        "columns zeroed, starts from the tilt, random headings in training)")
    p.add_argument("--acc-lowpass", type=float, default=0.0,
                   help="seconds: the accelerometer low-passed in a gyro-strapdown frame "
                        "(prefilter.py) before the observer reads it; 0: raw")
    p.add_argument("--acc-lowpass-order", type=int, choices=(1, 2), default=1,
                   help="the low-pass of --acc-lowpass: 1 first order, 2 VQF's second-order "
                        "Butterworth filter (prefilter.py)")
    p.add_argument("--rest-bias", type=int, choices=(0, 1), default=0,
                   help="1: the gyroscope's bias from rest removed before the observer reads it "
                        "(prefilter.py)")
    p.add_argument("--tilt-tau", type=float, default=0.0,
                   help="seconds: the complementary prior's tilt correction towards the "
                        "accelerometer after the gyroscope's step (learning.py); 0: none")
    p.add_argument("--heading-only", type=int, choices=(0, 1), default=0,
                   help="1: the network's correction turns the estimate about 'up' only (the "
                        "tilt is left to --tilt-tau's correction)")
    p.add_argument("--heading-tau", type=float, default=0.0,
                   help="seconds: the complementary prior's heading correction towards magnetic "
                        "north (a turn about 'up' only), after the tilt correction; 0: none")
    p.add_argument("--heading-gate", type=int, choices=(0, 1), default=0,
                   help="1: the heading correction only where the magnetometer's strength and "
                        "dip are within 10 %% and 10 deg of the system's (learning.field_gate)")
    p.add_argument("--loss-weights", default=None,
                   help="9 comma-separated weights >= 0 of the loss's squared errors of R's "
                        "entries, row by row (manifold_nets.losses); the third row is R^T e_z, "
                        "'up' seen from the body: '0,0,0,0,0,0,1,1,1' scores the inclination "
                        "alone (a 6-D observer's heading is unobservable); default: all 1")
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--start-std", type=float, default=0.05,
                   help="training windows start at the truth turned by N(0, std^2) rad per axis")
    p.add_argument("--max-batches", type=int, default=None)
    p.add_argument("--tbptt", type=int, default=None,
                   help="truncated BPTT: an optimizer step per this many observer steps")
    p.add_argument("--init-from", default=None, help="start from this checkpoint or run folder")
    p.add_argument("--eval-splits", default="val,test", help="splits evaluated on whole trials")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: one, or OMP_NUM_THREADS)")
    return p.parse_args(argv)


def check_args(args) -> None:
    """The arguments that need no file, checked: ``ValueError`` naming the flag."""
    def bad(flag: str, want: str, got) -> ValueError:
        return ValueError(f"{flag} must be {want}, got {got!r}.")

    for flag in ("hidden_size", "num_layers", "decimation", "pretrain_length", "window",
                 "stride", "batch_size"):  # fmt: skip
        if getattr(args, flag) < 1:
            raise bad("--" + flag.replace("_", "-"), "an integer >= 1", getattr(args, flag))
    for flag in ("pretrain_epochs", "finetune_epochs", "seed"):
        if getattr(args, flag) < 0:
            raise bad("--" + flag.replace("_", "-"), "an integer >= 0", getattr(args, flag))
    for flag in ("max_batches", "tbptt", "threads"):
        if getattr(args, flag) is not None and getattr(args, flag) < 1:
            raise bad("--" + flag.replace("_", "-"), "an integer >= 1 (or left out)",
                      getattr(args, flag))  # fmt: skip
    if args.pretrain_sequences == 1 or args.pretrain_sequences < 0:
        raise bad("--pretrain-sequences", "0 (no pre-training) or >= 2 (one in 8, at least one, "
                  "validates)", args.pretrain_sequences)  # fmt: skip
    for flag in ("output_scale", "lr"):
        if not (math.isfinite(getattr(args, flag)) and getattr(args, flag) > 0):
            raise bad("--" + flag.replace("_", "-"), "a finite number > 0", getattr(args, flag))
    if not (math.isfinite(args.acc_lowpass) and args.acc_lowpass >= 0):
        raise bad("--acc-lowpass", "a finite number >= 0 (seconds; 0: raw)", args.acc_lowpass)
    if args.acc_lowpass_order == 2 and not args.acc_lowpass > 0:
        raise ValueError("--acc-lowpass-order 2 is the order of the accelerometer's low-pass, and "
                         "--acc-lowpass is 0: give --acc-lowpass (seconds, e.g. 3) or drop "
                         "--acc-lowpass-order.")
    if not (math.isfinite(args.tilt_tau) and args.tilt_tau >= 0):
        raise bad("--tilt-tau", "a finite number >= 0 (seconds; 0: no tilt correction)",
                  args.tilt_tau)
    if args.heading_only and not args.tilt_tau > 0:
        raise ValueError("--heading-only 1 leaves the tilt to --tilt-tau's correction, and "
                         "--tilt-tau is 0: nothing would correct the tilt; give --tilt-tau "
                         "(seconds, e.g. 3) or drop --heading-only.")
    if not (math.isfinite(args.heading_tau) and args.heading_tau >= 0):
        raise bad("--heading-tau", "a finite number >= 0 (seconds; 0: no heading correction)",
                  args.heading_tau)
    if args.heading_tau > 0 and not args.magnetometer:
        raise ValueError("--heading-tau corrects the heading from the magnetometer, and "
                         "--magnetometer is 0: drop --heading-tau for a 6-D observer.")
    if args.heading_gate and not args.heading_tau > 0:
        raise ValueError("--heading-gate 1 gates the heading correction, and --heading-tau is 0: "
                         "give --heading-tau (seconds, e.g. 10) or drop --heading-gate.")
    args.loss_weights = loss_weights(args.loss_weights)
    if not (math.isfinite(args.start_std) and args.start_std >= 0):
        raise bad("--start-std", "a finite number >= 0 (radians)", args.start_std)
    if not 0 <= args.mounting <= math.pi:
        raise bad("--mounting", "an angle in [0, pi] radians (0: no augmentation)", args.mounting)
    if not args.init_from and not (args.pretrain_sequences and args.pretrain_epochs) \
            and not args.finetune_epochs:
        raise ValueError("nothing to train: give --pretrain-epochs, --finetune-epochs or "
                         "--init-from.")


def loss_weights(text: str | list | None) -> list[float] | None:
    """``--loss-weights``: ``None`` or 9 weights (:func:`manifold_nets.losses.check_loss_weights`,
    one per entry of ``R``); ``ValueError`` naming the flag and the fix."""
    if text is None or isinstance(text, list):
        return check_loss_weights(text, 9)
    try:
        return check_loss_weights([float(w) for w in str(text).split(",")], 9)
    except ValueError as err:
        raise ValueError(f"--loss-weights {text!r}: {err} E.g. '0,0,0,0,0,0,1,1,1' (the "
                         "inclination alone).") from None


def settings(args, epochs: int) -> TrainSettings:
    return TrainSettings(
        epochs=epochs, batch_size=args.batch_size, lr=args.lr, weight_decay=0.01,
        schedule="cosine", lr_min=args.lr / 20, grad_clip=1.0, max_batches=args.max_batches,
        eval_batch_size=64, threads=args.threads, tbptt=args.tbptt, loss_weights=args.loss_weights,
    )


def pretrain(args, system, model, out: Path, config: dict) -> Path:
    """Stage 1 (simulated data); returns its best checkpoint."""
    gen = torch.Generator().manual_seed(args.seed)
    n, k = args.pretrain_sequences, args.decimation
    full_rate = BroadSimulator()  # this IMU at 285.7 Hz, decimated like the recordings
    data = prefilter_dataset(full_rate.simulate(n, args.pretrain_length * k, 1.0, gen), BROAD_DT,
                             args.acc_lowpass, bool(args.rest_bias), order=args.acc_lowpass_order)
    data = decimate(data, k, BROAD_DT)
    n_val = max(1, n // 8)
    if not args.magnetometer:
        data = without_magnetometer(data)
    train, val = data[n_val:], data[:n_val]
    res = fit(
        model, train, val, settings(args, args.pretrain_epochs), out_dir=out / "pretrain",
        seed=args.seed, start=near_truth_start(system, args.start_std, bool(args.magnetometer)),
        config=config, augment=None if args.magnetometer else RandomHeading(),
    )
    log.info("pretrain: best val loss %.4g at epoch %d", res.best_val_loss, res.best_epoch)
    return res.best_path


def windows(args, trials: dict) -> tuple:
    """The fine-tuning data: windows of the training trials (every ``--stride``) and of the
    validation trials (none overlapping), decimated to the observer's step."""
    k = args.decimation
    try:
        train = trials_to_dataset(trials["train"], args.window * k, args.stride * k)
        val = trials_to_dataset(trials["val"], args.window * k, args.window * k)
    except BroadFormatError as err:
        raise BroadFormatError(
            f"--window {args.window} x --decimation {k} = {args.window * k} samples: {err}"
        ) from None
    train, val = decimate(train, k, BROAD_DT), decimate(val, k, BROAD_DT)
    if not args.magnetometer:
        train, val = without_magnetometer(train), without_magnetometer(val)
    return train, val


def augmentation(args):
    """The training batches' augmentation: the random mounting (``--mounting``), then for a
    6-D observer a random heading (:class:`~.learning.RandomHeading`); ``None`` for neither."""
    steps = ([RandomMounting(args.mounting)] if args.mounting > 0 else []) + (
        [] if args.magnetometer else [RandomHeading()])
    if not steps:
        return None

    def augment(batch, generator):
        for step in steps:
            batch = step(batch, generator)
        return batch

    return augment


def finetune(args, system, model, out: Path, data: tuple, config: dict) -> Path:
    """Stage 2 (real windows of the training trials: :func:`windows`); returns its best
    checkpoint."""
    train, val = data
    log.info("finetune: %d training windows, %d validation windows of %d samples",
             len(train), len(val), args.window)
    augment = augmentation(args)
    res = fit(
        model, train, val, settings(args, args.finetune_epochs), out_dir=out / "finetune",
        seed=args.seed, start=near_truth_start(system, args.start_std, bool(args.magnetometer)),
        augment=augment,
        config=config,
    )
    log.info("finetune: best val loss %.4g at epoch %d", res.best_val_loss, res.best_epoch)
    return res.best_path


def _config(args, system, model_cfg) -> dict:
    """The run config: what ``load_observer`` needs (``system``, ``model``) plus the command's
    arguments, plain data (fits :class:`manifold_nets.config.RunConfig`)."""
    model = asdict(model_cfg)
    sys_cfg = {"_target_": f"{type(system).__module__}.{type(system).__qualname__}",
               **system.config()}
    return {"name": "broad", "seed": args.seed, "system": sys_cfg, "model": model}


def prepare(args) -> dict:
    """Everything checked and read before any work (module docstring); ``BroadFormatError`` or
    ``ValueError`` naming the argument. Returns what :func:`run` needs."""
    check_args(args)
    out = check_destination(args.out, folder=True)
    if (out / "checkpoints" / "best.pt").exists():
        raise ValueError(f"--out {out} already holds a trained observer; choose another --out.")
    data_dir, split = split_trials(args.split)
    args.data_dir = args.data_dir or data_dir
    evaluated = chosen_splits(args.eval_splits, split, "--eval-splits")
    stages = ["train", "val"] if args.finetune_epochs > 0 else []
    missing = [s for s in stages if s not in split]
    if missing:
        raise BroadFormatError(f"{args.split or 'configs/broad/trials.yaml'}: fine-tuning needs "
                               f"the split(s) {missing}; the file has {sorted(split)}.")
    trials = {s: read_trials(args.data_dir, split[s]) for s in dict.fromkeys(stages + evaluated)}
    trials = {s: [prefiltered(t, args.acc_lowpass, bool(args.rest_bias), args.acc_lowpass_order)
                  for t in ts] for s, ts in trials.items()}  # fmt: skip
    for s in evaluated:
        check_scored(trials[s], f"--eval-splits {s}")
    system = BroadSimulator(  # the observer's step, and how it reads the recordings
        dt=args.decimation * BROAD_DT, magnetometer=bool(args.magnetometer),
        acc_lowpass=args.acc_lowpass, rest_bias=bool(args.rest_bias),
        acc_lowpass_order=args.acc_lowpass_order)
    model_cfg = model_config(args.hidden_size, args.num_layers, args.output_scale, args.tilt_tau,
                             bool(args.heading_only), args.heading_tau,
                             field_gate(system) if args.heading_gate else None)
    model = make_observer(system, model_cfg, args.seed)
    for epochs in (args.pretrain_epochs, args.finetune_epochs):
        check_settings(settings(args, epochs))
    init = None
    if args.init_from:
        try:  # widened: a run may add the tilt correction to an observer trained without it
            init, ckpt = load_weights(model, args.init_from, widen=True)
        except (ValueError, OSError) as err:
            raise ValueError(f"--init-from {args.init_from}: {err}") from None
        if ckpt["signature"] != model.signature():  # nothing to copy: the model is another
            init = {"model": model.state_dict(), "signature": model.signature(), "epoch": 0}
    return {
        "out": out, "system": system, "model": model, "model_cfg": model_cfg,
        "windows": windows(args, trials) if stages else None, "init": init, "split": split,
    }


def run(args) -> Path:
    """Trains by the arguments (:func:`parse_args`), checked first (:func:`prepare`)."""
    ready = prepare(args)
    out, system, model = ready["out"], ready["system"], ready["model"]
    out.mkdir(parents=True, exist_ok=True)
    config = _config(args, system, ready["model_cfg"])
    write_text_atomic(out / "config.yaml", yaml.safe_dump(config, sort_keys=False))
    write_text_atomic(out / "command.json", json.dumps(vars(args), indent=1) + "\n")
    # the trials of each split as this run read them (broad.crossval checks a run's fold by them)
    write_text_atomic(out / "split.yaml", yaml.safe_dump({"splits": ready["split"]}, sort_keys=False))
    best = ready["init"]
    if args.pretrain_sequences > 0 and args.pretrain_epochs > 0:
        best = pretrain(args, system, model, out, config)
        load_weights(model, best)
    if args.finetune_epochs > 0:
        best = finetune(args, system, model, out, ready["windows"], config)
        load_weights(model, best)
    if isinstance(best, dict):  # --init-from widened and not trained: this model's weights
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)
        save_checkpoint(out / "checkpoints" / "best.pt", {**best, "config": config})
    else:
        with open(best, "rb") as src, atomic_open(out / "checkpoints" / "best.pt", "wb") as dst:
            shutil.copyfileobj(src, dst)
    return out


def main(argv=None) -> None:
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s")
    args = parse_args(argv)
    try:
        use_threads(args.threads)
        t0 = time.perf_counter()
        out = run(args)
        log.info("trained in %.0f s: %s", time.perf_counter() - t0, out)
        evaluate_run(out, args.data_dir, args.split, args.eval_splits)
    except (ValueError, OSError) as err:
        raise SystemExit(f"error: {err}") from None


if __name__ == "__main__":
    main()
