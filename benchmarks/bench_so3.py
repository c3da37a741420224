"""SO(3) speed and drift benchmark: ``groups.SO3`` against roma, PyPose, kornia and scipy.

Run by hand from the repository root (never by CI's pass/fail)::

    pip install -e '.[bench]'                  # roma, pypose, kornia at pinned versions
    python benchmarks/bench_so3.py             # full run, writes benchmarks/results/so3.md
    python benchmarks/bench_so3.py --quick     # smoke run: batches 1e3 and 1e4, prints only
    python benchmarks/bench_so3.py --baseline HEAD   # adds a column: groups/ as committed

What it measures, all in one process so that the ratios compare like with like:

* **Speed** of ``exp`` (rotation vector -> matrix), ``log`` (matrix -> rotation vector) and
  ``compose`` at batches 1e3 / 1e5 / 1e6, float32 and float64, forward alone and forward +
  backward, as nanoseconds per rotation: the median over the repeats of
  ``torch.utils.benchmark.Timer.blocked_autorange`` (which warms up and sets the thread count),
  taken in a few rounds that interleave the libraries so that a busy machine slows everyone
  alike. Everyone gets the same inputs: rotation vectors with uniform random axes and angles
  uniform in ``[0, pi)``, and the matching matrices / quaternions computed once in float64 by
  scipy. PyPose works with unit quaternions, so its native ``exp`` returns a quaternion and its
  ``log`` reads one; a second PyPose row goes through matrices (``.matrix()`` /
  ``pp.mat2SO3``) for a same-representation comparison. scipy is forward only, float64 (numpy
  has no autograd). ``--baseline REV`` adds this library as of a git revision, measured in the
  same run: a before/after column for performance work.
* **Drift** of float32 chains ``R <- R exp(v)``: 1000 chains of 1000 updates with ``|v| = 0.1``
  along random directions (fixed seed, the same increments for every library); the median and
  maximum over chains of ``||R R^T - I||_F`` after the last step, evaluated in float64.
* The **targets** of the speed issue (float32, batch 1e5, forward): our ``exp`` at least as fast
  as roma's ``rotvec_to_rotmat``, our ``log`` at least as fast as PyPose's ``SO3.Log``, and our
  drift no worse than the best peer's. The results file says whether each is met.

The results file records the date, torch version, thread count, CPU, load average and git
commit. Timings on a shared machine are noisy: read ratios from one run, not across runs.

The contenders and their inputs are in ``so3_contenders.py``, the results file in
``so3_report.py``, both beside this file.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch.utils.benchmark import Timer

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the helpers beside this file

from so3_contenders import (  # noqa: E402, F401  (all importable here as they always were)
    BASELINE,
    DTYPES,
    G,
    LIBS,
    OPS,
    PEERS,
    ROOT,
    SO3,
    _git,
    closure,
    kc,
    kornia,
    load_baseline,
    make_inputs,
    pp,
    roma,
    scipy_op,
    torch_ops,
)
from so3_report import (  # noqa: E402, F401
    EARLIER,
    SPEED_NOTES,
    TARGET_BATCH,
    _cpu,
    _fmt,
    _git_commit,
    _ratio,
    _version,
    agreement_table,
    drift_table,
    header,
    speed_tables,
    targets,
    write_atomically,
)


# --------------------------------------------------------------------------- speed


def time_interleaved(
    fns: dict[str, Callable], n: int, threads: int, min_time: float, rounds: int
) -> dict[str, float]:
    """ns per rotation of each ``fns[lib]()``: the median over all repeats of ``rounds`` rounds.

    In each round every library gets ``min_time / rounds`` seconds of
    ``Timer.blocked_autorange`` (which warms up, and sets the thread count), one after the
    other; interleaving the rounds spreads the load of a busy machine over everyone alike.
    """
    times: dict[str, list[float]] = {lib: [] for lib in fns}
    timers = {
        lib: Timer(stmt="f()", globals={"f": f}, num_threads=threads) for lib, f in fns.items()
    }
    for _ in range(rounds):
        for lib, timer in timers.items():
            times[lib] += timer.blocked_autorange(min_run_time=min_time / rounds).times
    return {lib: statistics.median(t) / n * 1e9 for lib, t in times.items()}


def run_speed(batches, threads: int, min_time: float, rounds: int, log: Callable) -> dict:
    """``results[(op, n, dtype, mode)][lib] = ns per rotation`` (None where n/a)."""
    results: dict = {}
    for n in batches:
        for dname, dtype in DTYPES.items():
            inputs = make_inputs(n, dtype, seed=0)
            for op in OPS:
                for mode in ("fwd", "fwd+bwd"):
                    fns = {}
                    for lib in LIBS:
                        f = closure(lib, op, inputs, backward=(mode == "fwd+bwd"))
                        if f is not None:
                            fns[lib] = f
                    timed = time_interleaved(fns, n, threads, min_time, rounds)
                    row = {lib: timed.get(lib) for lib in LIBS}
                    results[(op, n, dname, mode)] = row
                    log(f"{op:8s} n={n:<8d} {dname} {mode:8s} " + "  ".join(
                        f"{lib}={_fmt(row[lib])}" for lib in LIBS
                    ))
            del inputs
    return results


# --------------------------------------------------------------------------- agreement


def run_agreement(n: int = 1000) -> dict:
    """Max abs difference to scipy in float64 (the benchmark compares equivalent computations).

    Quaternion outputs are turned into matrices by scipy before comparing; ``log`` is compared
    as rotation vectors (angles stay below pi, so the vector is unique).
    """
    inp = make_inputs(n, torch.float64, seed=2)
    a, b = inp["a"], inp["b"]
    ref = {
        "exp": a["R_np"],
        "log": a["v_np"],
        "compose": (a["rot"] * b["rot"]).as_matrix(),
    }
    res: dict = {}
    for lib in (lib for lib in LIBS if lib != "scipy"):
        ops = torch_ops(lib)
        for op in OPS:
            if ops[op] is None:
                res[(op, lib)] = None
                continue
            key, fn = ops[op]
            args = [a[key]] if op != "compose" else [a[key], b[key]]
            out = torch.as_tensor(fn(*args)).detach().numpy()
            if out.shape[-1] == 4:  # PyPose quaternion (x, y, z, w)
                out = Rotation.from_quat(out).as_matrix()
            res[(op, lib)] = float(np.abs(out - ref[op]).max())
    return res


# --------------------------------------------------------------------------- drift


def frobenius_orthogonality_error(r: torch.Tensor) -> torch.Tensor:
    """``||R R^T - I||_F`` per element, evaluated in float64 so the check adds no rounding."""
    r = r.double()
    return torch.linalg.matrix_norm(r @ r.transpose(-1, -2) - torch.eye(3, dtype=torch.float64))


def run_drift(chains: int, steps: int, step_norm: float, seed: int) -> dict:
    """Chains ``R <- R exp(v)``; returns ``{label: (median, max, seconds per step)}``."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(steps, chains, 3, generator=g, dtype=torch.float64)
    v64 = step_norm * d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    v32 = v64.float()

    def matrix_chain(update, v):
        r = G.identity((chains,), dtype=v.dtype)
        for k in range(steps):
            r = update(r, v[k])
        return r

    runs: dict[str, Callable[[], torch.Tensor]] = {
        "ours (matrix)": lambda: matrix_chain(lambda r, w: G.compose(r, G.exp(w)), v32),
    }
    for label, g in BASELINE.items():
        runs[f"{label} (matrix)"] = lambda g=g: matrix_chain(
            lambda r, w: g.compose(r, g.exp(w)), v32
        )
    if roma is not None:
        runs["roma (matrix)"] = lambda: matrix_chain(lambda r, w: r @ roma.rotvec_to_rotmat(w), v32)
    if pp is not None:

        def pypose_chain():
            q = pp.identity_SO3(chains, dtype=torch.float32)
            for k in range(steps):
                q = q * pp.so3(v32[k]).Exp()
            return q.matrix()

        runs["pypose (quaternion, matrix at the end)"] = pypose_chain
    if kc is not None:
        runs["kornia (matrix)"] = lambda: matrix_chain(
            lambda r, w: r @ kc.axis_angle_to_rotation_matrix(w), v32
        )
    runs["ours, float64 (matrix)"] = lambda: matrix_chain(
        lambda r, w: G.compose(r, G.exp(w)), v64
    )
    out = {}
    with torch.no_grad():
        for label, run in runs.items():
            t0 = time.perf_counter()
            r = run()
            dt = (time.perf_counter() - t0) / steps
            e = frobenius_orthogonality_error(r)
            out[label] = (float(e.median()), float(e.max()), dt)
    return out



def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true",
                   help="smoke run: batches 1e3 and 1e4, less time per case; prints, and writes "
                   "a file only with --out")
    p.add_argument("--threads", type=int, default=1,
                   help="torch intra-op threads for every measurement (default 1: steadier on a "
                   "shared machine)")
    p.add_argument("--min-time", type=float, default=None,
                   help="seconds of repeats per library and case (default 1.0; quick 0.2)")
    p.add_argument("--rounds", type=int, default=3,
                   help="interleaved rounds the time is split into (default 3)")
    p.add_argument("--baseline", metavar="REV", action="append", default=[],
                   help="also measure groups/ as of this git revision (a before/after column); "
                   "may be repeated")
    p.add_argument("--out", type=Path, default=None,
                   help="results file (default benchmarks/results/so3.md; none for --quick)")
    argv = sys.argv[1:] if argv is None else argv
    args = p.parse_args(argv)
    if args.min_time is None:
        args.min_time = 0.2 if args.quick else 1.0

    batches = (1_000, 10_000) if args.quick else (1_000, 100_000, 1_000_000)
    out = args.out if args.out is not None else (
        None if args.quick else ROOT / "benchmarks" / "results" / "so3.md"
    )
    torch.set_num_threads(args.threads)
    for i, rev in enumerate(args.baseline):
        label = f"ours@{rev}"
        BASELINE[label] = load_baseline(rev)
        LIBS.insert(1 + i, label)
    chains, steps, step_norm = 1000, 1000, 0.1

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    lines = header(args, argv)
    log("agreement with scipy ...")
    agree = run_agreement()
    log("speed ...")
    results = run_speed(batches, args.threads, args.min_time, args.rounds, log)
    log("drift ...")
    drift = run_drift(chains, steps, step_norm, seed=0)
    lines += targets(results, drift, batches)
    lines += speed_tables(results, batches)
    lines += drift_table(drift, chains, steps, step_norm)
    lines += agreement_table(agree)
    text = "\n".join(lines)
    if out is not None:
        write_atomically(out, text)
        log(f"wrote {out}")
    print(text)


if __name__ == "__main__":
    main()
