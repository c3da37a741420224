"""The lock-out guard on the rigid body: a zoo observer (``--case``, default ``outliers``) and
its shipped readout, alone and behind a :class:`~manifold_nets.observer.LockOutGuard`, on the
same sequences: how often the guard re-acquires a factor, which sequences it changes, the errors
and the readout's ANEES (steps ``k >= 10``) with and without it::

    python benchmarks/lock_out.py --write benchmarks/results/lock_out

Two sets per sigma: fresh sequences (``--seed`` + the sigma's index, as
``benchmarks/calibration_in_band.py`` draws them: 1000 x 1000) and the paper's inference sets of
the case's experiment (``mismatch_outliers`` for the outliers; 1000 x 1000, what ``mn-evaluate``
scores). About 25 minutes a case on one thread. ``--timing`` measures instead what the guard
adds to the online step at batch 1 (the eager ``step``, guarded and not, in shuffled interleaved
rounds on one thread)::

    python benchmarks/lock_out.py --timing --write benchmarks/results/lock_out_step
"""

from __future__ import annotations

import argparse
import json
import math
import random
import statistics
import sys
import time
from pathlib import Path

import torch

from manifold_nets.calibration import nees, tangent_errors
from manifold_nets.observer import CalibratedObserver, LockOutGuard
from manifold_nets.threads import use_threads
from manifold_nets_examples.rigid_body.calibration import SIGMAS, SKIP, _sim
from manifold_nets_examples.rigid_body.level_scale import zoo_readout

ROOT = Path(__file__).resolve().parents[1]
FACTORS = ("R", "p")
CHUNK = 100
#: the zoo cases whose observers have a robust measurement, and the experiment of their paper sets
EXPERIMENTS = {"nominal": "paper_cpu_prior", "sensor": "mismatch_sensor",
               "outliers": "mismatch_outliers", "correlated": "mismatch_correlated"}


def paper_set(system, experiment: str, sigma: float):
    """The ``experiment``'s inference set at ``sigma`` (``mn-evaluate``'s)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from manifold_nets.datasets import inference_data

    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=[f"experiment={experiment}"])
    dataset = OmegaConf.to_object(cfg.dataset)
    return inference_data(system, dataset, cfg.eval, sigma, cache_dir=ROOT / dataset.cache_dir)


def _score(cal, data) -> dict[str, torch.Tensor]:
    """Per sequence and factor: the mean error over steps ``k >= SKIP`` (rad for R, m for p) and
    the mean ``NEES / d``; the estimates' checksum to compare runs, and the resets."""
    g, out = cal.group, {}
    for b in range(0, len(data.measurements), CHUNK):
        y = data.measurements[b : b + CHUNK]
        est, cov = cal(y)
        xi = tangent_errors(g, est, data.states[b : b + CHUNK])[:, SKIP:]
        for f in FACTORS:
            s = g.tangent_slice(f)
            part = {
                f"{f} error": xi[..., s].norm(dim=-1),
                f"{f} nees": nees(xi[..., s], cov[:, SKIP:, s, s]) / (s.stop - s.start),
            }
            for k, v in part.items():
                out.setdefault(k, []).append(v)
        out.setdefault("estimates", []).append(est.flatten(2))
        if isinstance(cal.observer, LockOutGuard):
            out.setdefault("resets", []).append(cal.observer.rollout(y).resets)
    return {k: torch.cat(v) for k, v in out.items()}


def _row(plain: dict, guarded: dict, factors: list[str]) -> dict:
    changed = (plain["estimates"] != guarded["estimates"]).flatten(1).any(1)
    resets = guarded["resets"]  # (N, T, F)
    row = {
        "sequences": len(changed),
        "sequences with a reset": int(resets.any(2).any(1).sum()),
        **{f"resets of {f}": int(resets[..., j].sum()) for j, f in enumerate(factors)},
        "sequences changed": int(changed.sum()),
    }
    for f in FACTORS:
        for tag, run in (("", plain), (" guarded", guarded)):
            err, q = run[f"{f} error"], run[f"{f} nees"]
            row[f"{f} mean error{tag}"] = float(err.mean())
            row[f"{f} worst sequence{tag}"] = float(err.mean(1).max())
            row[f"{f} ANEES{tag}"] = float(q.mean())
    return row


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", default="outliers", choices=list(EXPERIMENTS))
    p.add_argument("--sets", nargs="+", default=["fresh", "paper"], choices=["fresh", "paper"])
    p.add_argument("--sigmas", nargs="+", type=float, default=list(SIGMAS))
    p.add_argument("--sequences", type=int, default=1000, help="fresh sequences per sigma")
    p.add_argument("--seed", type=int, default=8000)
    p.add_argument("--tau", type=float, default=20.0)
    p.add_argument("--floor", type=float, default=0.1)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--write", type=Path, default=None, help="PATH: writes PATH.md and PATH.json")
    p.add_argument("--timing", action="store_true", help="time the online step instead")
    p.add_argument("--rounds", type=int, default=21, help="timing rounds (the first a warm-up)")
    args = p.parse_args(argv)
    use_threads(args.threads)
    plain, system = zoo_readout(args.case)
    plain.eval()
    guard = LockOutGuard(plain.observer, args.tau, args.floor)
    if args.timing:
        return _timing(guard, system, args, argv)
    guarded = CalibratedObserver(guard, plain.readout, plain.level_scale).eval()
    rows = []
    with torch.no_grad():
        for which in args.sets:
            for i, sigma in enumerate(args.sigmas):
                data = (_sim(system, args.sequences, 1000, sigma, args.seed + i)
                        if which == "fresh" else paper_set(system, EXPERIMENTS[args.case], sigma))
                row = {"case": args.case, "set": which, "sigma": sigma,
                       **_row(_score(plain, data), _score(guarded, data), guard.factors)}
                print(json.dumps(row), flush=True)
                rows.append(row)
    if args.write is not None:
        command = "python benchmarks/lock_out.py " + " ".join(argv or sys.argv[1:])
        args.write.with_suffix(".json").write_text(json.dumps(
            {"command": command, "tau": args.tau, "floor": args.floor, "rows": rows}, indent=1))
        args.write.with_suffix(".md").write_text(_markdown(rows, command, args))


def _timing(guard, system, args, argv) -> None:
    """Microseconds per online step at batch 1 (median over rounds of 200 steps each, and the
    rounds' spread), the observer's ``step`` and the guard's, in shuffled order each round."""
    obs = guard.observer
    ys = _sim(system, 1, 200, 0.3, args.seed).measurements[0].unsqueeze(1)  # (T, 1, l)
    variants = {"observer.step": (lambda: obs.init_state(1), obs.step),
                "LockOutGuard.step": (lambda: guard.init_state(1), guard.step)}
    per_round = {k: [] for k in variants}
    order = list(variants)
    with torch.inference_mode():
        for r in range(args.rounds):
            random.Random(r).shuffle(order)
            for name in order:
                init, step = variants[name]
                state, t0 = init(), time.perf_counter()
                for y in ys:
                    state = step(state, y)
                if r:  # round 0: warm-up
                    per_round[name].append(1e6 * (time.perf_counter() - t0) / len(ys))
    base = statistics.median(per_round["observer.step"])
    lines = [f"# What the lock-out guard adds to the online step ({args.case}, batch 1, one thread)",
             "", "`python benchmarks/lock_out.py " + " ".join(argv or sys.argv[1:]) + "`: "
             f"{args.rounds - 1} rounds of 200 steps (after a warm-up round), shuffled order.", "",
             "| step | us per step (median) | rounds' range | ratio to observer.step |",
             "| --- | --- | --- | --- |"]
    for name, ts in per_round.items():
        med = statistics.median(ts)
        lines.append(f"| {name} | {med:.0f} | {min(ts):.0f}-{max(ts):.0f} | {med / base:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.write is not None:
        args.write.with_suffix(".md").write_text(text)


def _markdown(rows: list[dict], command: str, args) -> str:
    lines = [
        f"# The lock-out guard on the rigid body: {args.case}",
        "",
        f"`{command}` (tau {args.tau:g} steps, floor {args.floor:g}; the zoo's observer of this "
        "case and its shipped readout; steps k >= 10). Fresh sets: seeds "
        f"{args.seed} + the sigma's index, {args.sequences} sequences of 1000 steps; paper: the "
        f"`{EXPERIMENTS[args.case]}` experiment's inference sets (1000 x 1000). Errors: mean over steps "
        "and sequences of the error's norm (R in degrees, p in m); worst: the largest mean over a "
        "sequence; ANEES: NEES / 3 under the readout's covariance, averaged.",
        "",
        "| set | sigma | sequences reset (R, p resets) | changed | p mean error | p worst | "
        "p ANEES | R mean error | R worst | R ANEES |",
        "|" + " --- |" * 10,
    ]
    deg = 180 / math.pi
    for r in rows:
        def pair(key, scale=1.0, fmt=".3f"):
            return f"{r[key] * scale:{fmt}} -> {r[key + ' guarded'] * scale:{fmt}}"
        lines.append(
            f"| {r['set']} | {r['sigma']:g} | {r['sequences with a reset']} ({r['resets of R']}, "
            f"{r['resets of p']}) | {r['sequences changed']} | {pair('p mean error')} | "
            f"{pair('p worst sequence')} | {pair('p ANEES')} | {pair('R mean error', deg)} | "
            f"{pair('R worst sequence', deg)} | {pair('R ANEES')} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
