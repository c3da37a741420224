"""The 6-D comparison (gyroscope and accelerometer only) and the heading cascade, on BROAD::

    python -m manifold_nets_examples.broad.six_d --split test --out docs/real_data/six_d \\
        [--learned LABEL=RUN[,RUN...] ...] [--cascade LABEL=RUN6[,RUN6...]+RUN9[,RUN9...] ...]

Without a magnetometer the heading is unobservable, so 6-D filters are scored on the benchmark's
inclination alone (:mod:`.metric`: it does not change when the world is turned about "up", so
an arbitrary heading costs nothing). Rows: VQF 6-D (``vqf_6d``), RIANN (``riann``, where the
``riann`` package is installed; otherwise the row is left out and the command says so), VQF 9-D
for context (``vqf_9d``), and each ``--learned`` 6-D observer (run folders of
``broad.train --magnetometer 0``, started from the tilt of the first sample, or a zoo entry,
``zoo:broad/attitude_6d``). A comma-separated
list of runs (seeds) gives one row per run and a row ``LABEL`` with, per trial, the mean over
the runs, and in ``metrics.json`` the spread (sample std) of the runs' means. ``--ensemble`` adds
a row ``LABEL (ensemble of N)``: the runs' estimates joined into one (:func:`tilt_ensemble`).

A *cascade* (``--cascade``) is a 9-D filter made of two learned observers: the inclination of
a 6-D one (which no magnetic disturbance can tilt) and the heading of a 9-D one, joined as VQF
joins its 6-D estimate and its heading correction, ``q = q_z(delta) q_6`` with ``delta`` the
heading of ``q_9 conj(q_6)`` (:func:`cascade`). Its inclination is the 6-D observer's exactly.
Runs are paired in order (one 9-D run serves every 6-D one); ``vqf_6d`` in place of the 6-D
runs takes VQF's 6-D estimate (a learned heading on a classical tilt). Cascades are scored on
all three metrics in a second table. Writes ``table.md`` and ``metrics.json``; data: BROAD, CC-BY-4.0.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from manifold_nets.atomic import write_text_atomic
from manifold_nets.destination import check_destination
from manifold_nets.plugins import locate
from manifold_nets.threads import use_threads

from .compare import ATTRIBUTION, comparison, markdown_table
from .data import Trial, read_trials, split_trials
from .metric import quat_conj, quat_multiply, rmse

__all__ = ["cascade", "tilt_ensemble", "learned_quaternions", "inclination_rows", "main"]


def cascade(q6: np.ndarray, q9: np.ndarray) -> np.ndarray:
    """``(T, 4)``: ``q6``'s inclination with ``q9``'s heading, ``q_z(delta) q6`` where
    ``delta = 2 atan2(z_e, w_e)`` of ``q_e = q9 conj(q6)`` (both ``(T, 4)`` w, x, y, z, body to
    East-North-Up)."""
    e = quat_multiply(q9, quat_conj(q6))
    half = np.arctan2(e[:, 3], e[:, 0])
    qz = np.stack((np.cos(half), 0 * half, 0 * half, np.sin(half)), axis=1)
    return quat_multiply(qz, q6)


def tilt_ensemble(estimates: list[np.ndarray]) -> np.ndarray:
    """``(T, 4)``: the seed ensemble of 6-D estimates ``[(T, 4)]``. Each 6-D observer's heading is
    its own (unobservable), so every estimate is first given the first one's heading
    (:func:`cascade`), keeping its inclination; the chordal mean of these
    (:func:`.seeds.ensemble`) then averages the inclinations alone."""
    from .seeds import ensemble

    return ensemble([cascade(q, estimates[0]) for q in estimates])


def learned_quaternions(run, trials: list[Trial]) -> list[np.ndarray]:
    """The observer of ``run`` (a ``broad.train`` run folder, 6-D or 9-D as it was trained) on
    whole trials: ``(T, 4)`` each."""
    from manifold_nets import load_observer

    from .evaluate import observer_quaternions

    observer, system, _ = load_observer(run)
    return observer_quaternions(observer, system, trials, source=str(run))


def inclination_rows(trials: list[Trial], estimates: dict) -> dict:
    """``{method: {trial: inclination RMSE deg, "mean": ...}}`` of ``{method: [(T, 4)]}``."""
    out = {}
    for method, quats in estimates.items():
        per = {t.name: rmse(q, t.quat, t.movement)["inclination"] for t, q in zip(trials, quats)}
        out[method] = {**per, "mean": float(np.mean(list(per.values())))}
    return out


def _groups(items: list[str], option: str, pair: bool = False) -> dict:
    """``{label: [runs]}`` (or ``{label: ([runs6], [runs9])}`` with ``pair``), checked."""
    out = {}
    for item in items:
        label, sep, runs = item.partition("=")
        parts = runs.split("+") if pair else [runs]
        if not sep or not label or not all(parts) or len(parts) != (2 if pair else 1):
            want = "LABEL=RUN6[,RUN6...]+RUN9[,RUN9...]" if pair else "LABEL=RUN[,RUN...]"
            raise ValueError(f"{option} takes {want}, got {item!r}.")
        lists = [[r for r in p.split(",") if r] for p in parts]
        for r in (r for lst in lists for r in lst):
            if not locate(r).exists() and not (pair and r == "vqf_6d"):  # zoo:... raises
                raise ValueError(f"{option} {label}: no such run folder {r!r}.")
        if pair and len(lists[1]) not in (1, len(lists[0])):
            raise ValueError(f"{option} {label}: give one 9-D run or one per 6-D run.")
        if label in out:
            raise ValueError(f"{option} label {label!r} given twice.")
        out[label] = tuple(lists) if pair else lists[0]
    return out


def _with_mean(rows: dict, label: str, members: list[str], names: list[str]) -> dict:
    """Adds ``label``: the per-trial mean over ``members`` (seeds) and the spread of their means."""
    if len(members) < 2:
        rows[label] = rows.pop(members[0])
        return rows
    per = {n: float(np.mean([rows[m][n] for m in members])) for n in names}
    means = [rows[m]["mean"] for m in members]
    rows[label] = {**per, "mean": float(np.mean(means)), "std_over_runs": float(np.std(means, ddof=1))}
    return rows


def _table(rows: dict, names: list[str], title: str) -> str:
    head = ["method", "inclination", *[n[:2] for n in names]]
    lines = [f"### {title}", "", "Inclination RMSE in degrees over the movement phases; mean over "
             "trials (± the sample std over seeds where a row is a mean of runs), then each "
             "trial's.", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m, r in rows.items():
        spread = f" ± {r['std_over_runs']:.2f}" if "std_over_runs" in r else ""
        cells = [f"{r['mean']:.2f}{spread}", *[f"{r[n]:.2f}" for n in names]]
        lines.append("| " + " | ".join([m, *cells]) + " |")
    return "\n".join(lines + ["", ATTRIBUTION, ""])


def _references(trials: list[Trial]) -> tuple[dict, dict]:
    from . import reference

    est, secs = {}, {}
    for name, fn in (("vqf_6d", reference.vqf_6d), ("riann", reference.riann_6d),
                     ("vqf_9d", reference.vqf_9d)):  # fmt: skip
        try:
            t0 = time.perf_counter()
            est[name] = fn(trials)
            secs[name] = time.perf_counter() - t0
        except ImportError as err:
            print(f"{name}: left out ({err})", flush=True)
    return est, secs


def run(split: str, out, learned: dict, cascades: dict, config=None, data_dir=None,
        with_ensemble: bool = False) -> dict:
    """Scores the rows of the module docstring on ``split``; writes ``out/table.md`` and
    ``out/metrics.json``; returns the metrics."""
    default_dir, splits = split_trials(config)
    if split not in splits:
        raise ValueError(f"--split {split!r}: choose from {sorted(splits)}.")
    out = check_destination(out, folder=True)
    trials = read_trials(data_dir or default_dir, splits[split])
    names = [t.name for t in trials]
    est, secs = _references(trials)
    cache: dict[str, list[np.ndarray]] = {}

    def quats(r: str) -> list[np.ndarray]:
        if r == "vqf_6d" and "vqf_6d" in est:
            return est["vqf_6d"]
        if r not in cache:
            t0 = time.perf_counter()
            cache[r] = learned_quaternions(r, trials)
            secs[r] = time.perf_counter() - t0
        return cache[r]

    for label, runs in learned.items():
        est.update({f"{label} [{r}]" if len(runs) > 1 else label: quats(r) for r in runs})
    rows = inclination_rows(trials, est)
    for label, runs in learned.items():
        if len(runs) > 1:
            _with_mean(rows, label, [f"{label} [{r}]" for r in runs], names)
        if with_ensemble and len(runs) > 1:
            key = f"{label} (ensemble of {len(runs)})"
            joined_q = [tilt_ensemble([quats(r)[i] for r in runs]) for i in range(len(trials))]
            rows.update(inclination_rows(trials, {key: joined_q}))
    joined = {}
    for label, (runs6, runs9) in cascades.items():
        runs9 = runs9 * len(runs6) if len(runs9) == 1 else runs9
        for r6, r9 in zip(runs6, runs9):
            key = f"{label} [{r6}+{r9}]" if len(runs6) > 1 else label
            joined[key] = [cascade(a, b) for a, b in zip(quats(r6), quats(r9))]
    full = comparison(trials, joined) if joined else []
    title = f"BROAD, {split} split ({len(trials)} trials)"
    text = _table(rows, names, f"6-D: {title}")
    if full:
        text += "\n" + markdown_table(full, f"Cascades (6-D inclination, 9-D heading): {title}")
    out.mkdir(parents=True, exist_ok=True)
    metrics = {"split": split, "inclination": rows, "cascades": full, "seconds": secs}
    write_text_atomic(out / "table.md", text)
    write_text_atomic(out / "metrics.json", json.dumps(metrics, indent=1) + "\n")
    return metrics


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="test", help="train, val or test")
    p.add_argument("--out", required=True, help="folder for table.md and metrics.json")
    p.add_argument("--data-dir", default=None, help="default: the split file's data_dir")
    p.add_argument("--config", default=None, help="split file (default configs/broad/trials.yaml)")
    p.add_argument("--learned", action="append", default=[], metavar="LABEL=RUN[,RUN...]")
    p.add_argument("--cascade", action="append", default=[],
                   metavar="LABEL=RUN6[,RUN6...]+RUN9[,RUN9...]")
    p.add_argument("--ensemble", action="store_true",
                   help="add each multi-run row's seed ensemble (headings aligned)")
    p.add_argument("--threads", type=int, default=None)
    a = p.parse_args(argv)
    try:
        use_threads(a.threads)
        learned = _groups(a.learned, "--learned")
        cascades = _groups(a.cascade, "--cascade", pair=True)
        run(a.split, a.out, learned, cascades, a.config, a.data_dir, a.ensemble)
        print((Path(a.out) / "table.md").read_text())
    except (ValueError, OSError) as err:
        raise SystemExit(f"error: {err}") from None


if __name__ == "__main__":
    main()
