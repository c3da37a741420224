"""Per-sample cost of the BROAD filters run online, one sample at a time, on one CPU thread.

Run by hand from the repository root (not by CI)::

    python benchmarks/bench_broad_step.py --write          # writes results/broad_step.md
    python benchmarks/bench_broad_step.py --run zoo:broad/attitude_6d \
        --write benchmarks/results/broad_step_6d.md       # the 6-D entry
    python benchmarks/bench_broad_step.py --samples 4000 --rounds 2   # a quick look

Each filter is fed a test trial's readings (07, fast rotation) one sample at a time from a
Python loop, as a robot's driver would, and the table gives the CPU time of the process per
sample (and the wall time), median over ``--rounds`` rounds (the first a warm-up, not counted),
the rows interleaved within each round so that other processes' load hits them alike:

* ``learned RUN, full online loop`` (``--run``, default ``zoo:broad/attitude``): per sample the
  run's pre-filters (:mod:`manifold_nets_examples.broad.prefilter`, ``OnlinePrefilter``, where
  its system has them), the gyroscope integrated into the
  estimate (``R exp(dt w)``, numpy) and the block increment kept; every 8th sample the
  decimated rate (:mod:`manifold_nets_examples.broad.rate`) and one ``observer.step`` at batch 1
  (eager, ``torch.inference_mode``): what ``broad.evaluate`` computes, sample by sample;
* the same for a second run (``--prefiltered-run RUN``), e.g. one with other pre-filters;
* ``..., step compiled (AOTInductor)``: the same loop, the observer's step exported
  (``manifold_nets.export_observer``, batch 1) and compiled ahead of time to native code
  (``torch._inductor.aoti_compile_and_package``; needs a C++ compiler, ``--no-aoti`` leaves
  these rows out), as a deployment would run it; and that step alone;
* ``learned observer.step alone``: one step at batch 1 divided by 8 (the network's share);
* ``learned step with its covariance``: where the run's folder holds a ``covariance.pt`` (the
  zoo entry's), the step of the observer with its readout (``CalibratedObserver.step``, random
  context), eager and compiled as above;
* ``vqf.VQF.update`` (9-D and 6-D), called per sample from Python, and ``vqf.VQF.updateBatch``
  over the whole stream divided by its length (the C++ loop without Python's per-call cost);
* ``riann predict_step`` (the ``riann`` package's ONNX network, one onnxruntime thread), where
  ``riann`` is installed.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import random
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DEFAULT_RUN, DEFAULT_OUT = "zoo:broad/attitude", str(RESULTS / "broad_step.md")
TRIAL = "07_undisturbed_fast_rotation_B"


def _rodrigues(w: np.ndarray) -> np.ndarray:
    t = math.sqrt(float(w @ w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if t < 1e-8:
        return np.eye(3) + K
    return np.eye(3) + math.sin(t) / t * K + (1 - math.cos(t)) / t**2 * (K @ K)


def aoti_package(observer, folder: Path, name: str):
    """``observer``'s exported online step (``manifold_nets.export_observer``, batch 1) compiled
    ahead of time by AOTInductor to ``folder/<name>_aoti.pt2`` (built once per folder and name,
    then loaded), loaded: call it as the exported step. Seconds to build: printed."""
    from torch._inductor import aoti_compile_and_package, aoti_load_package

    from manifold_nets import export_observer

    package = folder / f"{name}_aoti.pt2"
    if not package.is_file():
        t0 = time.perf_counter()
        program = export_observer(observer, folder / f"{name}.pt2", batch=1)
        aoti_compile_and_package(program, package_path=str(package))
        print(f"{name}: exported and compiled (AOTInductor) in {time.perf_counter() - t0:.1f} s")
    return aoti_load_package(str(package))


def compiled_step(observer, folder: Path):
    """:func:`aoti_package` of the observer's step: ``(native, start)``, ``native(*state, y, u)``
    the next state tensors (``x`` first, float64; ``y`` float64, ``u`` float32), ``start(x0)``
    the state tensors of a start ``x0`` ``(1, 3, 3)`` (every estimate in it ``x0``, the cores'
    initial hidden states)."""
    native = aoti_package(observer, folder, "step")
    module = observer.online_step_module()
    names = ["x", *module.state_names()]

    def start(x0):
        state = list(module.initial_state(1))
        for i, name in enumerate(names):
            if name == "x" or name.endswith("_x"):  # the estimate, each member's
                state[i] = x0.reshape(1, -1).to(state[i].dtype)
        return tuple(state)

    return native, start


def learned_stream(run: str, x0=None, aoti_dir: Path | None = None):
    """``feed(gyr, acc, mag) -> (3, 3)`` estimate per sample (see the module docstring); it
    starts from TRIAD of the first sample, or from ``x0`` ``(1, 3, 3)`` (``broad.evaluate``
    starts from TRIAD of the first observer step's readings, sample 8: :func:`check`).
    The run's system says how it reads (``broad.evaluate.input_settings``: the pre-filters,
    per sample by ``OnlinePrefilter``; a 6-D observer's magnetometer zeroed). ``aoti_dir``: a
    folder; the observer's step is then :func:`compiled_step`'s, built there."""
    from manifold_nets_examples.broad.prefilter import OnlinePrefilter

    from groups import SO3
    from manifold_nets import load_observer
    from manifold_nets_examples.broad.data import G0, M0

    from manifold_nets_examples.broad.evaluate import input_settings

    observer, system, _ = load_observer(run)
    observer.eval()
    so3, k = SO3(), 8
    dt = system.dt / k
    inputs = input_settings(system)
    pre = OnlinePrefilter(1 / dt, inputs["acc_lowpass"], inputs["rest_bias"],
                          order=inputs["acc_lowpass_order"])
    six = not inputs.get("magnetometer", True)
    st = {"n": 0, "block": np.eye(3), "state": None, "R": None}
    native, native_start = compiled_step(observer, aoti_dir) if aoti_dir else (None, None)

    @torch.inference_mode()
    def feed(gyr, acc, mag):
        gyr, acc = pre.update(gyr, acc)

        def reading():  # the observer's measurement, made only where a step reads it
            return torch.tensor(np.concatenate((acc / G0, 0 * mag if six else mag / M0)),
                                dtype=torch.float32)[None]

        if st["state"] is None:  # TRIAD of the first sample (its gyro is not integrated)
            start = system.state_from_measurement(reading().double()) if x0 is None else x0
            st["state"] = (observer.init_state(1, estimate=start) if native is None
                           else native_start(start))
            st["R"] = start[0].numpy()
            return st["R"]
        st["block"] = st["block"] @ _rodrigues(gyr * dt)
        st["n"] += 1
        if st["n"] % k:
            return st["R"] @ st["block"]
        rate = so3.log(torch.from_numpy(st["block"]))[None] / system.dt
        y = reading()
        if native is None:
            st["state"] = observer.step(st["state"], y, rate.float())
            st["R"] = st["state"].estimate[0].numpy()
        else:
            st["state"] = native(*st["state"], y.double(), rate.float())
            st["R"] = st["state"][0].reshape(3, 3).numpy()
        st["block"] = np.eye(3)
        return st["R"]

    return feed, observer


def check(run: str, trial, n: int, aoti_dir: Path | None = None) -> float:
    """The largest angle (deg) between the online loop's estimates (its step compiled in
    ``aoti_dir`` when given) and ``broad.evaluate``'s (``observer_quaternions``) over the first
    ``n`` samples of ``trial``, from one start."""
    import dataclasses

    from manifold_nets import load_observer
    from manifold_nets_examples.broad.data import G0, M0
    from manifold_nets_examples.broad.evaluate import input_settings, observer_quaternions
    from manifold_nets_examples.broad.metric import errors, matrix_to_quat

    part = dataclasses.replace(trial, **{f: getattr(trial, f)[:n] for f in
                                         ("gyr", "acc", "mag", "quat", "movement")})
    observer, system, _ = load_observer(run)
    inputs = input_settings(system)
    batch = observer_quaternions(observer, system, [part])[0]
    from manifold_nets_examples.broad.learning import tilt
    from manifold_nets_examples.broad.prefilter import prefiltered

    pre = prefiltered(part, inputs["acc_lowpass"], inputs["rest_bias"], inputs["acc_lowpass_order"])
    y8 = torch.tensor(np.concatenate((pre.acc[8] / G0, part.mag[8] / M0)))[None]
    x0 = system.state_from_measurement(y8) if inputs.get("magnetometer", True) else tilt(
        y8[:, :3])
    feed = learned_stream(run, x0, aoti_dir)[0]
    R = np.array([feed(part.gyr[i], part.acc[i], part.mag[i]) for i in range(n)])
    return float(np.degrees(errors(matrix_to_quat(R), batch)["total"]).max())


def step_alone(observer):
    state = observer.init_state(1)
    y, u = torch.randn(1, 6), torch.randn(1, 3) * 0.1

    @torch.inference_mode()
    def feed(*_):
        nonlocal state
        state = observer.step(state, y, u)

    return feed


def compiled_alone(observer, folder: Path):
    """:func:`compiled_step`'s step alone, batch 1, from the identity."""
    native, start = compiled_step(observer, folder)
    state = start(torch.eye(3, dtype=torch.float64)[None])
    y, u = torch.randn(1, 6, dtype=torch.float64), torch.randn(1, 3) * 0.1

    @torch.inference_mode()
    def feed(*_):
        nonlocal state
        state = native(*state, y, u)

    return feed


def calibrated_alone(run: str, folder: Path | None = None):
    """The observer's step with its covariance readout (``covariance.pt`` in the run's folder),
    batch 1, from the identity: eager (``CalibratedObserver.step``), or, with ``folder``, its
    exported step (``export_observer``) compiled there by AOTInductor."""
    from manifold_nets import load_observer
    from manifold_nets.covariance_training import load_readout
    from manifold_nets.plugins import locate

    cal = load_readout(locate(run) / "covariance.pt", load_observer(run)[0]).eval()
    c = torch.randn(1, cal.readout.context)
    if folder is None:
        state, y, u = cal.init_state(1), torch.randn(1, 6), torch.randn(1, 3) * 0.1

        @torch.inference_mode()
        def feed(*_):
            nonlocal state
            state, _ = cal.step(state, y, u, context=c if cal.readout.context else None)

        return feed
    native = aoti_package(cal, folder, "calibrated")
    step = cal.online_step_module()
    *state, y, u = step.example_inputs(1)[: len(step.initial_state(1)) + 2]
    y, u = torch.randn_like(y), torch.randn_like(u) * 0.1
    extra = (c,) if cal.readout.context else ()

    @torch.inference_mode()
    def feed(*_):
        nonlocal state
        state = native(*state, y, u, *extra)[:-1]

    return feed


def barycentre_alone(ensemble):
    """The ensemble's barycentre of its members' estimates, batch 1 (as its online step takes it)."""
    x = ensemble.group.random((len(ensemble.members), 1), dtype=ensemble.state_dtype)

    @torch.inference_mode()
    def feed(*_):
        ensemble.barycentre(list(x))

    return feed


def rows(args, trial):
    import vqf

    out = {}
    feed, observer = learned_stream(args.run)
    out[f"learned `{args.run}`, full online loop"] = (feed, 1)
    if args.prefiltered_run:
        out[f"learned `{args.prefiltered_run}`, full online loop"] = (
            learned_stream(args.prefiltered_run)[0], 1)
    out["learned observer.step alone (per sample: / 8)"] = (step_alone(observer), 8)
    if args.compiled:  # the same observer, its exported step compiled ahead of time
        out[f"learned `{args.run}`, full online loop, step compiled (AOTInductor)"] = (
            learned_stream(args.run, aoti_dir=args.compiled / "loop")[0], 1)
        out["learned step compiled (AOTInductor) alone (per sample: / 8)"] = (
            compiled_alone(observer, args.compiled / "alone"), 8)
    from manifold_nets.plugins import locate

    if (locate(args.run) / "covariance.pt").is_file():  # its covariance readout beside it
        out["learned step with its covariance alone (per sample: / 8)"] = (
            calibrated_alone(args.run), 8)
        if args.compiled:
            out["learned step with its covariance, compiled (AOTInductor) alone (per sample: / 8)"] = (
                calibrated_alone(args.run, args.compiled / "alone"), 8)
    members = getattr(observer, "members", None)
    if members is not None:  # an ensemble: where its step's time goes
        out["one member's step alone (per sample: / 8)"] = (step_alone(members[0]), 8)
        out["the members' barycentre alone (per sample: / 8)"] = (barycentre_alone(observer), 8)
    dt = 1.0 / trial.rate
    v9, v6 = vqf.VQF(dt), vqf.VQF(dt)
    out["vqf.VQF.update 9-D (per call from Python)"] = (lambda g, a, m: v9.update(g, a, m), 1)
    out["vqf.VQF.update 6-D (per call from Python)"] = (lambda g, a, m: v6.update(g, a), 1)
    try:
        import onnxruntime as ort
        import riann

        onnx = str(Path(riann.__file__).parent / "riann.onnx")
        net = riann.RIANN(onnx)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = opts.inter_op_num_threads = 1
        net.session = ort.InferenceSession(onnx, opts)
        net.set_sampling_rate(trial.rate)
        out["riann predict_step 6-D"] = (lambda g, a, m: net.predict_step(a, g), 1)
    except ImportError:
        print("riann not installed: its row is left out")
    return out


def time_rows(args):
    from manifold_nets_examples.broad.data import read_trial, split_trials
    import vqf

    torch.set_num_threads(1)
    data_dir, _ = split_trials(None)
    trial = read_trial(Path(args.data_dir or data_dir) / f"{TRIAL}.mat")
    n = min(args.samples, len(trial))
    g, a, m = (np.ascontiguousarray(x[:n], dtype=np.float64) for x in (trial.gyr, trial.acc, trial.mag))
    table = rows(args, trial)
    times = {name: [] for name in table}
    times["vqf.VQF.updateBatch 9-D (C++ loop)"] = []
    rng = random.Random(0)
    for r in range(args.rounds + 1):
        names = list(table) + ["vqf.VQF.updateBatch 9-D (C++ loop)"]
        rng.shuffle(names)
        for name in names:
            c0, w0 = time.process_time(), time.perf_counter()
            if name in table:
                feed, per = table[name]
                for i in range(0, n, per):
                    feed(g[i], a[i], m[i])
            else:
                vqf.VQF(1.0 / trial.rate).updateBatch(g, a, m)
            c1, w1 = time.process_time(), time.perf_counter()
            if r:
                times[name].append(((c1 - c0) / n * 1e6, (w1 - w0) / n * 1e6))
    return times, n, trial.rate, trial


def markdown(times, n, rate, args) -> str:
    lines = [
        "# BROAD: per-sample cost of the online filters, one CPU thread",
        "",
        f"`python benchmarks/bench_broad_step.py --samples {args.samples} --rounds {args.rounds}"
        + (f" --run {args.run}" if args.run != DEFAULT_RUN else "")
        + (f" --prefiltered-run {args.prefiltered_run}" if args.prefiltered_run else "")
        + (" --no-aoti" if args.compiled is None else "")
        + (" --write" if args.write == DEFAULT_OUT else f" --write {args.write}") + "`; "
        f"trial {TRIAL[:2]}, its first {n} samples ({rate:.1f} Hz: a real-time budget of "
        f"{1e6 / rate:.0f} us per sample); median over {args.rounds} rounds (one warm-up not "
        "counted), rows interleaved in a shuffled order each round; torch "
        f"{torch.__version__}, Python {platform.python_version()}, {platform.machine()}, "
        f"{os.cpu_count()} cores shared with other jobs.",
        "",
        "| filter | CPU us / sample | wall us / sample | share of the real-time budget |",
        "|---|---|---|---|",
    ]
    for name, ts in times.items():
        cpu = statistics.median(t[0] for t in ts)
        wall = statistics.median(t[1] for t in ts)
        lines.append(f"| {name} | {cpu:.1f} | {wall:.1f} | {cpu * rate / 1e4:.2f} % |")
    lines += ["", "Data: BROAD (D. Laidig, M. Caruso, A. Cereatti, T. Seel, Data 6(7):72, 2021, "
              "https://doi.org/10.3390/data6070072), CC-BY-4.0.", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", default=DEFAULT_RUN, help="the learned observer")
    p.add_argument("--prefiltered-run", default=None, help="a broad.train run with --acc-lowpass")
    p.add_argument("--samples", type=int, default=20000)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--data-dir", default=None)
    p.add_argument("--write", nargs="?", const=DEFAULT_OUT, default=None, metavar="PATH",
                   help="write the table (default path: benchmarks/results/broad_step.md)")
    p.add_argument("--no-aoti", action="store_true",
                   help="leave out the rows of the step compiled by AOTInductor (needs a C++ "
                        "compiler)")
    args = p.parse_args(argv)
    if not args.no_aoti and not any(shutil.which(c) for c in ("c++", "g++", "clang++")):
        raise SystemExit("error: no C++ compiler found (c++, g++ or clang++), which AOTInductor "
                         "needs for the compiled rows; install one, or pass --no-aoti.")
    sys.path.insert(0, str(ROOT))
    with tempfile.TemporaryDirectory() as tmp:
        args.compiled = None if args.no_aoti else Path(tmp)
        if args.compiled:
            for sub in ("loop", "alone"):
                (args.compiled / sub).mkdir()
        times, n, rate, trial = time_rows(args)
        text = markdown(times, n, rate, args)
        agree = {f"`{r}`": check(r, trial, min(n, 4001))
                 for r in (args.run, args.prefiltered_run) if r}
        if args.compiled:
            agree[f"`{args.run}` with its step compiled"] = check(
                args.run, trial, min(n, 4001), args.compiled / "loop")  # the loop's build
    text += "".join(f"\nThe online loop of {r} agrees with `broad.evaluate`'s estimates "
                    f"to {d:.1e} deg (largest difference over the first 4001 samples, one start)."
                    "\n" for r, d in agree.items())
    print(text)
    if args.write:
        Path(args.write).write_text(text)


if __name__ == "__main__":
    main()
