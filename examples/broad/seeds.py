"""Learned observers over seeds: the mean and spread of each configuration, its seed ensemble,
and VQF beside them, on one split::

    python -m manifold_nets_examples.broad.seeds --split val --out docs/real_data/seeds_val \\
        --runs F=examples/broad/zoo/attitude --runs RL9=runs/RL9_s0,runs/RL9_s1,runs/RL9_s2 \\
        [--ensemble]

Each run folder's whole-trial estimates on the split (``results/learned_<split>_quaternions.npz``,
written by ``broad.train`` and ``broad.evaluate``; estimated here, and not written, where a run
lacks them) are scored by the benchmark's metric. A configuration's row gives, for total,
heading and inclination, the mean over its runs of the split's mean RMSE and the sample standard
deviation over the runs (``±``), and each trial's total averaged over the runs. ``--ensemble``
adds, for each configuration of several runs, the row of their averaged estimate (per sample the
normalised sum of the runs' quaternions, signs aligned to the first's). Rows ``vqf`` (online,
default settings) for reference. Writes ``table.md`` and ``metrics.json``; data: BROAD,
CC-BY-4.0 (Laidig et al. 2021).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from manifold_nets.atomic import write_text_atomic
from manifold_nets.destination import check_destination
from manifold_nets.threads import use_threads

from .compare import ATTRIBUTION, METRICS
from .data import Trial, read_trials, split_trials
from .metric import rmse

__all__ = ["run_estimates", "ensemble", "seed_rows", "main"]


def run_estimates(run, split: str, trials: list[Trial]) -> list[np.ndarray]:
    """The run's ``(T, 4)`` estimates of ``trials``: its stored ones for ``split`` where they
    cover every trial, else estimated (:func:`.six_d.learned_quaternions`)."""
    stored = Path(run) / "results" / f"learned_{split}_quaternions.npz"
    if stored.is_file():
        with np.load(stored) as z:
            if all(t.name in z.files and len(z[t.name]) == len(t) for t in trials):
                return [z[t.name] for t in trials]
    from .six_d import learned_quaternions

    return learned_quaternions(run, trials)


def ensemble(estimates: list[np.ndarray]) -> np.ndarray:
    """``(T, 4)``: the normalised sum of the runs' quaternions ``[(T, 4)]``, each sign-aligned
    to the first's (the chordal mean, close to the geodesic one for estimates degrees apart)."""
    ref = estimates[0]
    total = sum(q * np.sign(np.sum(q * ref, axis=1, keepdims=True) + 1e-300) for q in estimates)
    return total / np.linalg.norm(total, axis=1, keepdims=True)


def _score(trials: list[Trial], quats: list[np.ndarray]) -> dict:
    per = {t.name: rmse(q, t.quat, t.movement) for t, q in zip(trials, quats)}
    return {"trials": per, "mean": {m: float(np.mean([v[m] for v in per.values()]))
                                    for m in METRICS}}  # fmt: skip


def seed_rows(trials: list[Trial], groups: dict, split: str, with_ensemble: bool) -> dict:
    """``{row: {"runs", "mean", "std", "trials"}}`` for ``groups`` ``{label: [run folders]}``."""
    rows = {}
    for label, runs in groups.items():
        est = [run_estimates(r, split, trials) for r in runs]
        scores = [_score(trials, q) for q in est]
        means = {m: [s["mean"][m] for s in scores] for m in METRICS}
        rows[label] = {
            "runs": [str(r) for r in runs],
            "mean": {m: float(np.mean(v)) for m, v in means.items()},
            "std": {m: float(np.std(v, ddof=1)) if len(v) > 1 else None for m, v in means.items()},
            "per_run": [s["mean"] for s in scores],
            "trials": {t.name: float(np.mean([s["trials"][t.name]["total"] for s in scores]))
                       for t in trials},  # fmt: skip
        }
        if with_ensemble and len(runs) > 1:
            joined = _score(trials, [ensemble([q[i] for q in est]) for i in range(len(trials))])
            rows[f"{label} (ensemble of {len(runs)})"] = {
                "runs": [str(r) for r in runs], "mean": joined["mean"], "std": None,
                "trials": {n: v["total"] for n, v in joined["trials"].items()},
            }
    return rows


def _table(rows: dict, names: list[str], title: str) -> str:
    head = ["method", "runs", *METRICS, *[n[:2] for n in names]]
    lines = [f"### {title}", "", "RMSE in degrees over the movement phases: mean over trials "
             "(± the sample std over the runs, seeds), then each trial's total (mean over the "
             "runs).", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, r in rows.items():
        std = r.get("std") or {}
        cells = [f"{r['mean'][m]:.2f}" + (f" ± {std[m]:.2f}" if std.get(m) is not None else "")
                 for m in METRICS]  # fmt: skip
        lines.append("| " + " | ".join([label, str(len(r["runs"])) if r["runs"] else "-", *cells,
                                        *[f"{r['trials'][n]:.2f}" for n in names]]) + " |")
    return "\n".join(lines + ["", ATTRIBUTION, ""])


def _groups(items: list[str]) -> dict:
    out = {}
    for item in items:
        label, sep, runs = item.partition("=")
        runs = [r for r in runs.split(",") if r]
        if not sep or not label or not runs or label in out:
            raise ValueError(f"--runs takes LABEL=RUN[,RUN...] with a new label, got {item!r}.")
        missing = [r for r in runs if not Path(r).exists()]
        if missing:
            raise ValueError(f"--runs {label}: no such run folder(s) {missing}.")
        out[label] = runs
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="val")
    p.add_argument("--out", required=True)
    p.add_argument("--runs", action="append", default=[], metavar="LABEL=RUN[,RUN...]")
    p.add_argument("--ensemble", action="store_true")
    p.add_argument("--config", default=None, help="split file (default configs/broad/trials.yaml)")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--threads", type=int, default=None)
    a = p.parse_args(argv)
    try:
        use_threads(a.threads)
        groups = _groups(a.runs)
        default_dir, splits = split_trials(a.config)
        if a.split not in splits:
            raise ValueError(f"--split {a.split!r}: choose from {sorted(splits)}.")
        out = check_destination(a.out, folder=True)
        trials = read_trials(a.data_dir or default_dir, splits[a.split])
        from .reference import vqf_9d

        rows = {"vqf": {"runs": [], "std": None,
                        **_score(trials, vqf_9d(trials))}}  # fmt: skip
        rows["vqf"]["trials"] = {n: v["total"] for n, v in rows["vqf"]["trials"].items()}
        rows.update(seed_rows(trials, groups, a.split, a.ensemble))
        names = [t.name for t in trials]
        text = _table(rows, names, f"BROAD, {a.split} split ({len(trials)} trials)")
        out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(out / "table.md", text)
        write_text_atomic(out / "metrics.json", json.dumps(rows, indent=1) + "\n")
        print(text)
    except (ValueError, OSError) as err:
        raise SystemExit(f"error: {err}") from None


if __name__ == "__main__":
    main()
