"""The error-state EKF's step: the project's against a plain batched numpy EKF of the same
rigid-body model, and BROAD's eight test trials through the project's EKF.

Run by hand from the repository root (not by CI)::

    python benchmarks/bench_ekf.py --write                     # writes results/ekf.md
    python benchmarks/bench_ekf.py --baseline HEAD --write     # adds the filter as of HEAD
    python benchmarks/bench_ekf.py --batches 100 --rounds 4 --no-broad   # a quick look

**Rigid body.** ``RigidBodyEKF``'s filter (``ErrorStateEKF`` with the analytic Jacobians)
against :func:`numpy_rigid_body_ekf` below: the same model written plainly in numpy (the same
``F``, ``G``, ``H = [I 0]``, Joseph form, reset ``blockdiag(J_r, I)``, symmetrisation), batched
over the sequences, ``np.linalg.solve`` for the gain. Both filter the same simulated sequences
(sigma 0.3) from the same start (:func:`initialize_from_measurements` over the first 5
measurements); their estimates and covariances are checked equal (the largest difference is in
the table). Per batch size, each round times one filter run of each, in shuffled order, one
torch thread; the first round is a warm-up. The ratio project / numpy is taken within each
round, so load from other processes hits both alike; the table gives its median and its range
over the rounds, from process CPU time (what the process itself spent) and from wall time.

**BROAD.** ``filters.ekf`` (what ``broad.compare --methods ekf`` runs) on the test split, the
noise levels of ``results/broad_tuned.json``: wall and CPU time of the whole call, and each
trial's RMSE against the shipped ``results/broad_classical.json``.

``--baseline REV`` runs the same rigid-body rounds (and, with ``--broad-baseline``, the BROAD
run) in a subprocess on the tree of a git revision (``git archive``, read-only), so the file
shows the project's filter before and after a change, each against the same numpy EKF.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))  # the helpers beside this file
from machine import describe as describe_machine  # noqa: E402
RESULTS = ROOT / "benchmarks" / "results"
SIGMA, INIT_STEPS = 0.3, 5

# ------------------------------------------------------------------ the numpy EKF

_I3, _I6, _I12 = np.eye(3), np.eye(6), np.eye(12)


def _coefficients(t2):
    """``A = sin t / t``, ``B = (1 - cos t) / t^2``, ``C = (t - sin t) / t^3`` and their
    derivatives in ``t^2``; Taylor series below ``t = 0.1``."""
    small = t2 < 0.01
    s = np.where(small, 1.0, t2)
    t = np.sqrt(s)
    sn, sh2 = np.sin(t), np.sin(0.5 * t) ** 2
    ser = lambda *c: sum(ci * t2**i for i, ci in enumerate(c))  # noqa: E731
    a = np.where(small, ser(1, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880), sn / t)
    b = np.where(small, ser(1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800), 2 * sh2 / s)
    c = np.where(small, ser(1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800),
                 (t - sn) / (s * t))  # fmt: skip
    db = np.where(small, ser(-1 / 24, 1 / 360, -1 / 13440, 1 / 907200),
                  (t * sn - 4 * sh2) / (2 * s * s))  # fmt: skip
    dc = np.where(small, ser(-1 / 120, 1 / 2520, -1 / 120960, 1 / 9979200),
                  (3 * sn - 2 * t - t * np.cos(t)) / (2 * s * s * t))  # fmt: skip
    return a, b, c, db, dc


def _skew(w):
    o = np.zeros(w.shape[:-1])
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    return np.stack((o, -z, y, z, o, -x, -y, x, o), -1).reshape(*w.shape[:-1], 3, 3)


def _col(s):
    return s[:, None, None]


def _exp_jl(phi):
    """``exp(phi)``, ``J_l(phi)``, ``[phi]x`` and the coefficients."""
    co = _coefficients((phi * phi).sum(-1))
    K = _skew(phi)
    K2 = K @ K
    return _I3 + _col(co[0]) * K + _col(co[1]) * K2, _I3 + _col(co[1]) * K + _col(co[2]) * K2, K, co


def _log(R):
    """Rotation vectors of rotations ``R`` with angles below pi (atan2 of the axis' length)."""
    v = 0.5 * np.stack((R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0],
                        R[:, 1, 0] - R[:, 0, 1]), -1)  # fmt: skip
    s = np.linalg.norm(v, axis=-1)
    angle = np.arctan2(s, 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1))
    return np.where(s > 0, angle / np.where(s > 0, s, 1.0), 1.0)[:, None] * v


def _predict(R, p, b, P, yk, dt, Q):
    """The rigid body's prediction: ``(R^-, p^-, P^-)``."""
    w = yk[:, 12:] - b
    phi, vh = w[:, :3] * dt, w[:, 3:]
    E, Jl, K, (_, bb, cc, db, dc) = _exp_jl(phi)
    t = (Jl @ vh[..., None])[..., 0] * dt
    pv = (phi * vh).sum(-1)
    Kv = (K @ vh[..., None])[..., 0]
    u = 2 * db[:, None] * Kv + 2 * dc[:, None] * (K @ Kv[..., None])[..., 0]
    D = (-_col(bb) * _skew(vh) + _col(cc * pv) * _I3 + cc[:, None, None] * phi[:, :, None]
         * vh[:, None, :] + (u - 2 * cc[:, None] * vh)[:, :, None] * phi[:, None, :])  # fmt: skip
    n = len(R)
    F = np.zeros((n, 12, 12))
    F[:, 0:3, 0:3] = E.transpose(0, 2, 1)
    F[:, 0:3, 6:9] = -Jl.transpose(0, 2, 1) * dt
    F[:, 3:6, 0:3] = -R @ _skew(t)
    F[:, 3:6, 3:6] = _I3
    F[:, 3:6, 6:9] = -(R @ D) * dt * dt
    F[:, 3:6, 9:12] = -(R @ Jl) * dt
    F[:, 6:12, 6:12] = _I6
    G = F[:, :, 6:12].copy()
    G[:, 6:12] = 0.0
    P = F @ P @ F.transpose(0, 2, 1) + G @ Q @ G.transpose(0, 2, 1)
    return R @ E, p + (R @ t[..., None])[..., 0], 0.5 * (P + P.transpose(0, 2, 1))


def numpy_rigid_body_ekf(y, x0, P0, dt, sigma):
    """The rigid body's error-state EKF in plain numpy, batched: ``y`` ``(N, T, 18)``, ``x0``
    ``(N, 18)``, ``P0`` ``(N, 12, 12)`` -> estimates ``(N, T+1, 18)``, covariances
    ``(N, T+1, 12, 12)``. Readings' and pose noise ``sigma``, constant biases."""
    n, steps = y.shape[:2]
    R, p, b, P = x0[:, :9].reshape(n, 3, 3), x0[:, 9:12], x0[:, 12:], P0
    Q, Rn = sigma**2 * _I6, sigma**2 * _I6
    H = _I12[:6]
    est, cov = np.empty((n, steps + 1, 18)), np.empty((n, steps + 1, 12, 12))
    est[:, 0], cov[:, 0] = x0, P0
    for k in range(steps):
        yk = y[:, k]
        R, p, P = _predict(R, p, b, P, yk, dt, Q)
        nu = np.concatenate((_log(R.transpose(0, 2, 1) @ yk[:, :9].reshape(n, 3, 3)),
                             yk[:, 9:12] - p), -1)  # fmt: skip
        PHt = P @ H.T
        K = np.linalg.solve(H @ PHt + Rn, PHt.transpose(0, 2, 1)).transpose(0, 2, 1)
        d = (K @ nu[..., None])[..., 0]
        A = _I12 - K @ H
        P = A @ P @ A.transpose(0, 2, 1) + K @ Rn @ K.transpose(0, 2, 1)
        E, Jl, _, _ = _exp_jl(d[:, :3])
        J = np.broadcast_to(_I12, (n, 12, 12)).copy()
        J[:, :3, :3] = Jl.transpose(0, 2, 1)
        P = J @ P @ J.transpose(0, 2, 1)
        P = 0.5 * (P + P.transpose(0, 2, 1))
        R, p, b = R @ E, p + d[:, 3:6], b + d[:, 6:]
        est[:, k + 1] = np.concatenate((R.reshape(n, 9), p, b), -1)
        cov[:, k + 1] = P
    return est, cov


# ------------------------------------------------------------------ the measurements


def _rigid_rounds(batches, steps, rounds, compiled: bool, seed=0) -> dict:
    """Per batch size: the per-step times of the filters per round and their agreement."""
    import torch

    from manifold_nets_examples.rigid_body import RigidBody
    from manifold_nets_examples.rigid_body.filters import RigidBodyEKF

    torch.set_num_threads(1)
    system = RigidBody()
    out = {}
    for batch, n_steps in zip(batches, steps):
        gen = torch.Generator().manual_seed(seed)
        y = system.simulate(batch, INIT_STEPS + n_steps, SIGMA, gen).measurements
        ekfs = {"project": RigidBodyEKF(system, SIGMA)}
        if compiled:
            ekfs["project, compiled"] = RigidBodyEKF(system, SIGMA)
            ekfs["project, compiled"].ekf.compile = True
        x0, P0 = ekfs["project"].start_belief(y[:, :INIT_STEPS])
        y_run = y[:, INIT_STEPS:].contiguous()
        y_np, x_np, P_np = y_run.numpy(), x0.numpy(), P0.numpy()

        def run(e):
            e.ekf.progress = False
            return lambda: e.ekf.filter(y_run, x0=x0, P0=P0, return_covariances=True)

        variants = {name: run(e) for name, e in ekfs.items()}
        variants["numpy"] = lambda: numpy_rigid_body_ekf(y_np, x_np, P_np, system.dt, SIGMA)
        ref_est, ref_cov = variants["numpy"]()
        diff, first = {}, {}
        for name in ekfs:
            w0 = time.perf_counter()
            res = variants[name]()  # the compiled filter compiles here
            first[name] = time.perf_counter() - w0
            diff[name] = max(float(np.abs(res.estimates.numpy() - ref_est).max()),
                             float(np.abs(res.covariances.numpy() - ref_cov).max()))  # fmt: skip
        times = {name: {"cpu": [], "wall": []} for name in variants}
        for r in range(rounds):
            order = list(variants)
            random.Random(seed + r).shuffle(order)
            for name in order:
                c0, w0 = time.process_time(), time.perf_counter()
                variants[name]()
                c1, w1 = time.process_time(), time.perf_counter()
                if r > 0:  # the first round is a warm-up
                    times[name]["cpu"].append((c1 - c0) / n_steps)
                    times[name]["wall"].append((w1 - w0) / n_steps)
        out[batch] = {"steps": n_steps, "max_diff": diff, "first_call": first, "times": times}
    return out


def _op_counts() -> dict:
    """Torch operations per step (top-level aten calls, ``torch.profiler``): the rigid body's
    filter at batch 100 and BROAD's model at batch 8."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    from manifold_nets.ekf import ErrorStateEKF
    from manifold_nets_examples.broad.filters import BroadFilterModel
    from manifold_nets_examples.rigid_body import RigidBody
    from manifold_nets_examples.rigid_body.filters import RigidBodyEKF

    system = RigidBody()
    y = system.simulate(100, 7, SIGMA, torch.Generator().manual_seed(0)).measurements
    rigid = RigidBodyEKF(system, SIGMA).ekf
    x0, P0 = RigidBodyEKF(system, SIGMA).start_belief(y[:, :INIT_STEPS])
    broad = ErrorStateEKF(BroadFilterModel(285.7, [0.0, 0.36, -0.93], acc=torch.full((8,), 1.0),
                                           mag=torch.full((8,), 3.0)), jacobians="analytic")  # fmt: skip
    cases = {
        "rigid body, batch 100": (rigid, rigid.init(100, x0=x0, P0=P0), y[:, 5], y.new_zeros(100, 0)),
        "BROAD, batch 8": (broad, broad.init(8), torch.nn.functional.normalize(
            torch.ones(8, 2, 3, dtype=torch.float64), dim=-1).flatten(-2),
            torch.full((8, 3), 0.1, dtype=torch.float64)),
    }
    out = {}
    for name, (ekf, state, yk, uk) in cases.items():
        # the constants of a run, as the filter's loops pass them (where the filter has them)
        extra = (True, ekf.constants(torch.float64)) if hasattr(ekf, "constants") else ()
        with torch.no_grad():
            ekf.step(state, yk, uk, *extra)
            with profile(activities=[ProfilerActivity.CPU]) as prof:
                ekf.step(state, yk, uk, *extra)
        events = [e for e in prof.events() if e.name.startswith("aten::")]
        top = sum(1 for e in events if e.cpu_parent is None
                  or not e.cpu_parent.name.startswith("aten::"))  # fmt: skip
        out[name] = f"{top} ({len(events)})"
    return out


def _broad_run() -> dict:
    """BROAD's test trials through ``filters.ekf``: times and per-trial RMSE against the
    shipped table."""
    from manifold_nets_examples.broad import filters
    from manifold_nets_examples.broad.data import read_trials, split_trials
    from manifold_nets_examples.broad.metric import rmse

    data_dir, splits = split_trials(None)
    data_dir = Path(data_dir)
    if not data_dir.is_absolute():
        data_dir = ROOT / data_dir
    trials = read_trials(data_dir, splits["test"])
    tuned = json.loads((RESULTS / "broad_tuned.json").read_text())
    c0, w0 = time.process_time(), time.perf_counter()
    quats = filters.ekf(trials, np.asarray(tuned["m_ref"]), **tuned["ekf"])
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    shipped = {r["trial"]: r["total"] for r in json.loads(
        (RESULTS / "broad_classical.json").read_text())["test"] if r["method"] == "ekf"}
    totals = {t.name: rmse(q, t.quat, t.movement)["total"] for t, q in zip(trials, quats)}
    return {"wall": wall, "cpu": cpu, "loop": filters.ekf.seconds,
            "samples": sum(len(t) for t in trials), "steps": max(len(t) for t in trials),
            "rmse": totals, "rmse_diff": max(abs(totals[n] - shipped[n]) for n in totals)}


def _worker(args) -> None:
    """Runs the measurements on the tree ``args.tree`` and prints them as JSON."""
    sys.path.insert(0, args.tree)
    rounds = _rigid_rounds(args.batches, args.steps, args.rounds, not args.no_compile)
    out = {"rigid": {str(k): v for k, v in rounds.items()}, "ops": _op_counts()}
    if args.broad:
        out["broad"] = _broad_run()
    print("\n@@" + json.dumps(out))


def _baseline(rev: str, args, broad: bool) -> dict:
    """The measurements on the tree of git revision ``rev``, in a subprocess."""
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "archive", rev], cwd=ROOT, capture_output=True, check=True)
        with tarfile.open(fileobj=__import__("io").BytesIO(archive.stdout)) as tar:
            tar.extractall(tmp, filter="data")
        for name, target in (("manifold_nets_examples", "examples"),
                             ("manifold_nets_configs", "configs")):  # fmt: skip
            os.symlink(Path(tmp) / target, Path(tmp) / name)
        cmd = [sys.executable, __file__, "--worker", "--tree", tmp, "--rounds", str(args.rounds),
               "--batches", *map(str, args.batches), "--steps", *map(str, args.steps),
               "--no-compile"]  # fmt: skip
        if broad:
            cmd.append("--broad")
        run = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=True)
    return json.loads(run.stdout.rsplit("\n@@", 1)[1])


# ------------------------------------------------------------------ the report


def _spread(values) -> str:
    return f"{statistics.median(values):.2f} [{min(values):.2f}, {max(values):.2f}]"


def _rigid_table(runs: dict) -> list[str]:
    """``runs``: ``{label: {batch: rounds}}``."""
    lines = [
        "| filter | batch | steps | CPU us/step: filter | numpy | ratio filter / numpy, CPU: "
        "median [min, max] | ratio, wall | first run (s) | max abs difference from numpy |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, run in runs.items():
        for batch, r in run.items():
            t = r["times"]
            for name in (n for n in t if n != "numpy"):
                ratio = {k: [a / b for a, b in zip(t[name][k], t["numpy"][k])]
                         for k in ("cpu", "wall")}  # fmt: skip
                lines.append(
                    f"| {name}{label} | {batch} | {r['steps']} | "
                    f"{1e6 * statistics.median(t[name]['cpu']):.0f} | "
                    f"{1e6 * statistics.median(t['numpy']['cpu']):.0f} | "
                    f"{_spread(ratio['cpu'])} | {_spread(ratio['wall'])} | "
                    f"{r['first_call'][name]:.2f} | {r['max_diff'][name]:.1e} |"
                )
    return lines


def _broad_table(runs: dict) -> list[str]:
    lines = [
        "| filter | wall (s) | CPU (s) | time loop (s) | wall per step (ms) | largest change of a "
        "trial's total RMSE from the shipped table (deg) |",
        "|---|---|---|---|---|---|",
    ]
    for label, b in runs.items():
        lines.append(
            f"| {label} | {b['wall']:.1f} | {b['cpu']:.1f} | {b['loop']:.1f} | "
            f"{1e3 * b['wall'] / b['steps']:.2f} | {b['rmse_diff']:.1e} |"
        )
    return lines


def _goals(rigid: dict, broad: dict) -> list[str]:
    """The issue's two goals, read off this run: the project's step at most numpy's (median CPU
    ratio), BROAD's 8 test trials in under 60 s (wall)."""
    lines = []
    for batch, r in rigid[""].items():
        t = r["times"]
        for name in (n for n in t if n != "numpy"):
            ratio = statistics.median(a / b for a, b in zip(t[name]["cpu"], t["numpy"]["cpu"]))
            verdict = "met" if ratio <= 1 else "not met"
            lines.append(f"- rigid body, batch {batch}, {name}: {ratio:.2f} x numpy ({verdict})")
    if "project" in broad:
        wall = broad["project"]["wall"]
        lines.append(f"- BROAD's 8 test trials: {wall:.1f} s wall "
                     f"({'met' if wall < 60 else 'not met'}; the goal: under 60 s)")  # fmt: skip
    return lines


def _report(args, rigid: dict, broad: dict, ops: dict, loads: tuple[float, float]) -> str:
    import torch

    given = sys.argv[1:] if args.argv is None else args.argv
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()  # fmt: skip
    lines = [
        "# The EKF's step: the project's against a plain numpy EKF, and BROAD's test trials",
        "",
        f"`python benchmarks/bench_ekf.py {' '.join(given)}` (on commit {commit} plus the "
        f"working tree, {time.strftime('%Y-%m-%d %H:%M')})",
        "",
        f"{describe_machine()}; torch {torch.__version__}, numpy {np.__version__}, 1 torch thread; load "
        f"average {loads[0]:.1f} at the start, {loads[1]:.1f} at the end. A shared machine: other "
        "processes ran throughout, so the times are noisy and the wall times longer than the "
        "CPU times; the ratios are taken within each round (order shuffled) and are what to "
        "compare.",
        "",
        f"## Rigid body (sigma {SIGMA}, filter started at step {INIT_STEPS})",
        "",
        f"{args.rounds - 1} rounds counted (the first is a warm-up); per round one filter run "
        "of each, in shuffled order. Ratio below 1: the project's filter is faster.",
        "",
        *_rigid_table(rigid),
    ]
    lines += ["", "## Torch operations per step", "",
              "Top-level aten calls of one step, `torch.profiler` (in brackets: all aten calls, "
              "those that others make included).", "",
              "| filter | " + " | ".join(next(iter(ops.values()))) + " |",
              "|---|" + "---|" * len(next(iter(ops.values())))]  # fmt: skip
    lines += [f"| {label} | " + " | ".join(str(v) for v in counts.values()) + " |"
              for label, counts in ops.items()]  # fmt: skip
    if broad:
        lines += [
            "",
            "## BROAD, test split (8 trials, through `filters.ekf`)",
            "",
            "The tuned noise levels of `results/broad_tuned.json`; the trials run as one batch "
            "of 8, padded to the longest.",
            "",
            *_broad_table(broad),
        ]
    lines += ["", "## The goals, read off this run", "", *_goals(rigid, broad)]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 100, 1000])
    ap.add_argument("--steps", type=int, nargs="+", default=[200, 100, 30],
                    help="steps per filter run, one per batch size")  # fmt: skip
    ap.add_argument("--rounds", type=int, default=11, help="rounds (the first is a warm-up)")
    ap.add_argument("--no-broad", action="store_true", help="skip BROAD's trials")
    ap.add_argument("--no-compile", action="store_true", help="skip the compiled filter")
    ap.add_argument("--baseline", default=None, help="also measure the tree of this git revision")
    ap.add_argument("--broad-baseline", action="store_true",
                    help="with --baseline: BROAD's trials on it too (minutes)")  # fmt: skip
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/ekf.md")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--tree", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--broad", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.argv = argv
    if len(args.steps) != len(args.batches):
        ap.error("--steps needs one value per batch size")
    if args.worker:
        _worker(args)
        return 0
    load0 = os.getloadavg()[0]
    rigid = {"": _rigid_rounds(args.batches, args.steps, args.rounds, not args.no_compile)}
    ops = {"project": _op_counts()}
    broad = {}
    if not args.no_broad:
        broad["project"] = _broad_run()
    if args.baseline:
        base = _baseline(args.baseline, args, args.broad_baseline and not args.no_broad)
        rigid[f" at {args.baseline}"] = base["rigid"]
        ops[f"at {args.baseline}"] = base["ops"]
        if "broad" in base:
            broad[f"at {args.baseline}"] = base["broad"]
    report = _report(args, rigid, broad, ops, (load0, os.getloadavg()[0]))
    print(report)
    if args.write:
        (RESULTS / "ekf.md").write_text(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
