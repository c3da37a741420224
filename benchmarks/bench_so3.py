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
"""

from __future__ import annotations

import argparse
import atexit
import datetime
import importlib.util
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch.utils.benchmark import Timer

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout without installing

from groups import SO3  # noqa: E402

try:  # the peers are the optional `bench` extra
    import roma
except ImportError:  # pragma: no cover - reported in the results
    roma = None
try:
    import pypose as pp
except ImportError:  # pragma: no cover
    pp = None
try:
    import kornia
    import kornia.geometry.conversions as kc
except ImportError:  # pragma: no cover
    kornia = kc = None

G = SO3()
DTYPES = {"float32": torch.float32, "float64": torch.float64}
OPS = ("exp", "log", "compose")
PEERS = ("roma", "pypose (quat)", "pypose (matrix)", "kornia", "scipy")
LIBS: list[str] = ["ours", *PEERS]  # main() inserts "ours@REV" after "ours" for --baseline
BASELINE: dict[str, object] = {}  # "ours@REV" -> that revision's SO3()
TARGET_BATCH = 100_000
# Figures measured earlier on this 2-core machine (float32, batch 1e5) and in the paper.
EARLIER = {
    "exp": "roma ~50 ns/rot; kornia 113-134; pypose 245",
    "log": "pypose ~92 ns/rot; kornia 96; roma 181; scipy 3600",
    "drift": "best peer median 3.7e-6, max 8.8e-6; the paper reports 4e-6",
}


# --------------------------------------------------------------------------- inputs


def make_inputs(n: int, dtype: torch.dtype, seed: int) -> dict:
    """Rotation vectors with uniform axes and angles uniform in ``[0, pi)``, and their images.

    Everything is computed in float64 by scipy (no library under test makes its own inputs),
    then cast to ``dtype``. Two independent sets, ``a`` and ``b``, feed ``compose``.
    Returns torch tensors ``v (n, 3)``, ``R (n, 3, 3)``, ``q (n, 4)`` (scalar last, PyPose's and
    scipy's order) per set, and the numpy/scipy objects for scipy's own rows.
    """
    g = torch.Generator().manual_seed(seed)
    out: dict = {}
    for key in ("a", "b"):
        axis = torch.randn(n, 3, generator=g, dtype=torch.float64)
        axis = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
        angle = torch.rand(n, 1, generator=g, dtype=torch.float64) * math.pi
        v64 = (axis * angle).numpy()
        rot = Rotation.from_rotvec(v64)
        out[key] = {
            "v": torch.from_numpy(v64).to(dtype),
            "R": torch.from_numpy(rot.as_matrix()).to(dtype),
            "q": torch.from_numpy(rot.as_quat()).to(dtype),
            "v_np": v64,
            "R_np": rot.as_matrix(),
            "rot": rot,
        }
    return out


# --------------------------------------------------------------------------- the contenders


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", *args], cwd=ROOT, capture_output=True, text=True, check=False
    ).stdout.strip()


def load_baseline(rev: str):
    """``groups.SO3()`` as of git revision ``rev``, imported under another name.

    The package's files at ``rev`` are written to a temporary folder and imported as
    ``groups_at_<rev>`` (the package uses relative imports only), so the working tree and the
    baseline run side by side in one process: a before/after column from the same run.
    """
    files = [f for f in _git("ls-tree", "--name-only", rev, "groups/").split() if f.endswith(".py")]
    if not files:
        raise SystemExit(f"--baseline {rev}: no groups/*.py at that revision (is it a git rev?)")
    tmp = Path(tempfile.mkdtemp(prefix="bench_so3_baseline_"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)
    (tmp / "groups").mkdir()
    for f in files:
        (tmp / "groups" / Path(f).name).write_text(_git("show", f"{rev}:{f}") + "\n")
    name = "groups_at_" + "".join(ch if ch.isalnum() else "_" for ch in rev)
    spec = importlib.util.spec_from_file_location(
        name, tmp / "groups" / "__init__.py", submodule_search_locations=[str(tmp / "groups")]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module.SO3()


def torch_ops(lib: str) -> dict[str, tuple[str, Callable] | None]:
    """``op -> (input key, function of the input tensors)`` for a torch library, None if absent."""
    if lib == "ours" or lib in BASELINE:
        g = G if lib == "ours" else BASELINE[lib]
        return {
            "exp": ("v", g.exp),
            "log": ("R", g.log),
            "compose": ("R", g.compose),
        }
    if lib == "roma" and roma is not None:
        return {
            "exp": ("v", roma.rotvec_to_rotmat),
            "log": ("R", roma.rotmat_to_rotvec),
            "compose": ("R", lambda x, y: roma.rotmat_composition((x, y))),
        }
    if lib == "pypose (quat)" and pp is not None:
        return {
            "exp": ("v", lambda v: pp.so3(v).Exp()),
            "log": ("q", lambda q: pp.SO3(q).Log()),
            "compose": ("q", lambda p, q: pp.SO3(p) @ pp.SO3(q)),
        }
    if lib == "pypose (matrix)" and pp is not None:
        return {
            "exp": ("v", lambda v: pp.so3(v).Exp().matrix()),
            "log": ("R", lambda r: pp.mat2SO3(r, check=False).Log()),
            "compose": None,
        }
    if lib == "kornia" and kc is not None:
        return {
            "exp": ("v", kc.axis_angle_to_rotation_matrix),
            "log": ("R", kc.rotation_matrix_to_axis_angle),
            "compose": None,
        }
    return {op: None for op in OPS}


def scipy_op(op: str, a: dict, b: dict) -> Callable:
    """scipy's Rotation on numpy float64 (quaternions inside; compose multiplies quaternions)."""
    if op == "exp":
        return lambda: Rotation.from_rotvec(a["v_np"]).as_matrix()
    if op == "log":
        return lambda: Rotation.from_matrix(a["R_np"]).as_rotvec()
    return lambda: a["rot"] * b["rot"]


def closure(lib: str, op: str, inputs: dict, backward: bool) -> Callable | None:
    """A no-argument callable that runs one forward (and backward) pass, or None if n/a."""
    if lib == "scipy":
        dtype_ok = inputs["a"]["v"].dtype == torch.float64
        return scipy_op(op, inputs["a"], inputs["b"]) if dtype_ok and not backward else None
    entry = torch_ops(lib)[op]
    if entry is None:
        return None
    key, fn = entry
    args = [inputs["a"][key]] if op != "compose" else [inputs["a"][key], inputs["b"][key]]
    if not backward:
        return lambda: fn(*args)
    leaves = [x.clone().requires_grad_(True) for x in args]
    out = fn(*leaves)
    upstream = torch.randn(out.shape, dtype=out.dtype, generator=torch.Generator().manual_seed(1))
    return lambda: torch.autograd.grad(fn(*leaves), leaves, upstream)


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


# --------------------------------------------------------------------------- report


def _fmt(x: float | None) -> str:
    if x is None:
        return "—"
    return f"{x:.3g}" if x < 1000 else f"{x:.0f}"


def _ratio(a: float | None, b: float | None) -> str:
    return "—" if a is None or b is None else f"{a / b:.2f}"


def _git_commit() -> str:
    commit = _git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = _git("status", "--porcelain", "--", "groups")
    return commit + (" + uncommitted changes in groups/" if dirty else "")


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(mod) -> str:
    return getattr(mod, "__version__", "?") if mod is not None else "not installed"


def header(args, argv: list[str]) -> list[str]:
    import scipy

    load = ", ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "?"
    command = " ".join(["python benchmarks/bench_so3.py", *argv])
    lines = [
        "# SO(3) benchmark: speed and drift" + (" (quick smoke run)" if args.quick else ""),
        "",
        f"Written by `{command}`; do not edit by hand.",
        "",
        f"- date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M UTC}",
        f"- git commit: {_git_commit()}",
        f"- torch {torch.__version__}; torch threads: {args.threads} "
        f"(`torch.set_num_threads({args.threads})`, also passed to every Timer)",
        f"- CPU: {_cpu()}, {os.cpu_count()} logical cores; load average at start: {load}",
        f"- python {platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__},"
        f" roma {_version(roma)}, pypose {_version(pp)}, kornia {_version(kornia)}",
        f"- timing: median over {args.rounds} interleaved rounds of "
        f"`Timer.blocked_autorange`, {args.min_time:g} s per library and case in all",
    ]
    for label in BASELINE:
        lines.append(
            f"- `{label}`: this library's `groups/` as of git revision `{label[5:]}`, measured "
            "in the same run (a before/after column)"
        )
    return lines + [
        "",
        "> **Noisy machine.** Unless said otherwise these figures come from a shared 2-core "
        "machine with other jobs running. Compare ratios within this file only (every library "
        "was measured in the same run, interleaved, on the same inputs); re-run on a quiet "
        "machine for the final table.",
        "",
    ]


SPEED_NOTES = (
    "Inputs: uniform random axes, angles uniform in [0, pi); matrices and quaternions made "
    "once by scipy in float64 and cast. `fwd+bwd` is one forward and one "
    "`torch.autograd.grad` with a fixed random upstream gradient. "
    "**pypose (quat)** is PyPose's native form: its `exp` (`pp.so3(v).Exp()`) returns a unit "
    "quaternion, its `log` (`pp.SO3(q).Log()`) reads one and its `compose` "
    "(`pp.SO3 @ pp.SO3`) multiplies quaternions, so it never reads or writes the 3x3 matrix "
    "that the others do. **pypose (matrix)** converts: `pp.so3(v).Exp().matrix()` and "
    "`pp.mat2SO3(R, check=False).Log()`. scipy is `Rotation.from_rotvec(v).as_matrix()`, "
    "`Rotation.from_matrix(R).as_rotvec()` and `Rotation * Rotation` (quaternions), on numpy "
    "float64, forward only. roma's compose is `rotmat_composition` (a matmul, like ours); "
    "kornia has no compose in `kornia.geometry.conversions`. Ratio columns are ours / peer: "
    "below 1 means ours is faster."
)


def speed_tables(results: dict, batches) -> list[str]:
    lines = ["## Speed (ns per rotation; lower is better)", "", SPEED_NOTES, ""]
    peers = [lib for lib in LIBS if lib != "ours"]
    for op in OPS:
        rows = [r for key, r in results.items() if key[0] == op]
        used = [lib for lib in LIBS if any(r[lib] is not None for r in rows)]
        ratio_cols = [p for p in peers if p in used]
        lines += [f"### {op}", ""]
        cols = ["batch", "dtype", "pass", *used, *(f"ours/{p}" for p in ratio_cols)]
        lines.append("| " + " | ".join(cols) + " |")
        lines.append("|" + "---|" * len(cols))
        for n in batches:
            for dname in DTYPES:
                for mode in ("fwd", "fwd+bwd"):
                    row = results[(op, n, dname, mode)]
                    cells = [f"{n:.0e}", dname, mode, *(_fmt(row[lib]) for lib in used)]
                    cells += [_ratio(row["ours"], row[p]) for p in ratio_cols]
                    lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def agreement_table(agree: dict) -> list[str]:
    libs = [lib for lib in LIBS if lib != "scipy"]
    lines = [
        "## Agreement with scipy (float64, 1000 rotations, max abs difference)",
        "",
        "A check that every row above computes the same thing (PyPose's quaternions are turned "
        "into matrices by scipy before comparing).",
        "",
        "| op | " + " | ".join(libs) + " |",
        "|" + "---|" * (len(libs) + 1),
    ]
    for op in OPS:
        cells = ["—" if agree[(op, lib)] is None else f"{agree[(op, lib)]:.1e}" for lib in libs]
        lines.append(f"| {op} | " + " | ".join(cells) + " |")
    return lines + [""]


def drift_table(drift: dict, chains: int, steps: int, step_norm: float) -> list[str]:
    lines = [
        "## Drift off the group (float32 chains)",
        "",
        f"{chains} chains of {steps} updates `R <- R exp(v)`, `|v| = {step_norm}` along random "
        "directions (fixed seed, the same increments for everyone), starting at the identity; "
        "`||R R^T - I||_F` after the last step, evaluated in float64. No re-orthonormalisation "
        "anywhere. PyPose keeps a unit quaternion and multiplies quaternions "
        "(`q * pp.so3(v).Exp()`), converted to a matrix once at the end: its drift is the drift "
        "of the quaternion's norm. The float64 row is for scale. ms per step is the wall time "
        "of one update of all chains, Python overhead included.",
        "",
        "| chain | median | max | ms per step |",
        "|---|---|---|---|",
    ]
    for label, (med, mx, dt) in drift.items():
        lines.append(f"| {label} | {med:.2e} | {mx:.2e} | {dt * 1e3:.3f} |")
    return lines + [""]


def targets(results: dict, drift: dict, batches) -> list[str]:
    n = TARGET_BATCH if TARGET_BATCH in batches else max(batches)
    where = f"float32, batch {n:.0e}, forward"
    if n != TARGET_BATCH:
        where += f"; quick run, the target is stated at batch {TARGET_BATCH:.0e}"

    def speed_line(op: str, peer: str, what: str) -> list[str]:
        row = results[(op, n, "float32", "fwd")]
        if row[peer] is None:
            return [f"- {what}: not measured ({peer} is not installed)."]
        r = row["ours"] / row[peer]
        out = [
            f"- {what}: {'**met**' if r <= 1.0 else '**not met**'}: ours {_fmt(row['ours'])} "
            f"ns/rot vs {peer} {_fmt(row[peer])} ns/rot, ratio ours/{peer} = {r:.2f} ({where})."
        ]
        for label in BASELINE:
            if row.get(label) is not None:
                out.append(
                    f"  Before (`{label}`): {_fmt(row[label])} ns/rot, ratio "
                    f"{label}/{peer} = {row[label] / row[peer]:.2f}."
                )
        return out

    lines = ["## Targets", ""]
    lines += speed_line("exp", "roma", "`exp` at least as fast as roma's `rotvec_to_rotmat`")
    lines += speed_line("log", "pypose (quat)", "`log` at least as fast as PyPose's `SO3.Log`")
    row = results[("log", n, "float32", "fwd")]
    if row["pypose (matrix)"] is not None:
        lines.append(
            "  PyPose's `Log` reads a quaternion; from a matrix, as ours does "
            f"(`pp.mat2SO3(R).Log()`): ours/pypose (matrix) = "
            f"{row['ours'] / row['pypose (matrix)']:.2f}."
        )
    peers = {k: v for k, v in drift.items() if not k.startswith("ours")}
    ours = drift["ours (matrix)"]
    if peers:
        best_med = min(v[0] for v in peers.values())
        best_max = min(v[1] for v in peers.values())
        met = ours[0] <= best_med and ours[1] <= best_max
        lines.append(
            f"- float32 drift no worse than the best peer: {'**met**' if met else '**not met**'}: "
            f"ours median {ours[0]:.2e} / max {ours[1]:.2e}; best peer median {best_med:.2e} "
            f"/ max {best_max:.2e}; ratios ours/best {ours[0] / best_med:.2f} (median) and "
            f"{ours[1] / best_max:.2f} (max)."
        )
        for label in BASELINE:
            before = drift.get(f"{label} (matrix)")
            if before is not None:
                lines.append(
                    f"  Before (`{label}`): median {before[0]:.2e} / max {before[1]:.2e}."
                )
    lines += [
        "",
        "Figures measured earlier on this machine (float32, batch 1e5), for reference: "
        + "; ".join(f"{k}: {v}" for k, v in EARLIER.items())
        + ".",
        "",
    ]
    return lines


def write_atomically(path: Path, text: str) -> None:
    """Write to a temporary file beside ``path``, then ``os.replace`` it in one step."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes it private; a results file is not
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


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
