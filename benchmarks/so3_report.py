"""The results file of the SO(3) benchmark (``bench_so3.py``): its header (machine, versions,
commit), the targets met or not, the speed, drift and agreement tables, written atomically.

A helper of ``benchmarks/bench_so3.py`` (which imports it from beside itself), not a benchmark
of its own.
"""

from __future__ import annotations

import datetime
import os
import platform
import tempfile
from pathlib import Path

import numpy as np
import torch
from so3_contenders import BASELINE, DTYPES, LIBS, OPS, _git, kornia, pp, roma

TARGET_BATCH = 100_000
# Figures measured earlier on this 2-core machine (float32, batch 1e5) and in the paper.
EARLIER = {
    "exp": "roma ~50 ns/rot; kornia 113-134; pypose 245",
    "log": "pypose ~92 ns/rot; kornia 96; roma 181; scipy 3600",
    "drift": "best peer median 3.7e-6, max 8.8e-6; the paper reports 4e-6",
}


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
