"""Is the learned filter's gap to VQF larger than the trials' own scatter? A paired comparison
over BROAD's trials.

Run by hand from the repository root (not by CI), with BROAD's ``.mat`` files where the split
file says, the three cross-validation folds' ensembles and the 6-D tables in ``docs/``::

    python benchmarks/broad_paired.py \\
        --scratch-runs runs/w_round/E_f1,runs/w_round/E_f2,runs/w_round/E_f3 \\
        --write benchmarks/results/broad_paired.md

9-D: the shipped configuration as ensembles of seeds 3-5 (each folder an ensemble folder,
``members/<name>`` run folders, one per fold of ``configs/broad/cv/``), each of the 15
cross-validation trials estimated by the ensemble of the fold that held it out, the 8 test trials
by the first folder's (the zoo entry's members: fold 1 is the fixed split); the seeds' estimates
averaged as ``broad.seeds --ensemble`` does. VQF (online, default settings) on the same trials.
``--scratch-runs``: each fold's ensemble trained from scratch, every stage on its fold's training
trials alone, so each of the 23 trials is unseen by the observer that scores it.
``--cv-runs`` (the same, the folds fine-tuned from one start that trained on the fixed split's
training trials, which are folds 2 and 3's held-out trials) adds rows that are optimistic for the
learned filter; without ``--scratch-runs`` the test trials are its first folder's. The validation
trials were not trained on, but they chose among configurations and among the configuration's
ensembles, so only the test rows are free of selection. 6-D: a 6-D row's per-trial inclination
and VQF 6-D's from the ``broad.six_d`` tables ``docs/real_data/<DIR>_{val,test}/metrics.json``,
``--six-d DIR:ROW`` (repeatable; default ``loss6:TIL6``, TIL6's mean over its three seeds; every
6-D row's stages trained on the 11 training trials only). With ``--six-d`` and no folds'
ensembles only the 6-D rows are computed (no BROAD files or runs needed)::

    python benchmarks/broad_paired.py --six-d loss6:TIL6 --six-d start6:Z6 \
        --six-d "start6:Z6 (ensemble of 3)" --write benchmarks/results/broad_paired_6d.md

For each set and metric: both means, the mean of the per-trial differences (learned - VQF) with
its 95 % Student-t interval, the trials where the learned filter is lower, and the two-sided
p-value of the exact sign-flip (permutation) test of a zero mean difference.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import shlex
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from manifold_nets.atomic import write_text_atomic  # noqa: E402
from manifold_nets.loading import ensemble_members  # noqa: E402
from manifold_nets_examples.broad.compare import ATTRIBUTION, METRICS  # noqa: E402
from manifold_nets_examples.broad.crossval import fold_trials  # noqa: E402
from manifold_nets_examples.broad.data import read_trials, split_trials  # noqa: E402
from manifold_nets_examples.broad.metric import rmse  # noqa: E402
from manifold_nets_examples.broad.reference import vqf_9d  # noqa: E402
from manifold_nets_examples.broad.seeds import ensemble, run_estimates  # noqa: E402

FOLDS = [f"configs/broad/cv/fold{k}.yaml" for k in (1, 2, 3)]


def paired(learned: dict, reference: dict) -> dict:
    """Per-trial values ``{trial: x}`` of two methods on the same trials -> the paired figures
    (module docstring). The sign-flip test enumerates all ``2^n`` sign patterns."""
    names = sorted(reference)
    if sorted(learned) != names:
        raise ValueError(f"the two methods were scored on different trials: {sorted(learned)} "
                         f"against {names}.")
    d = np.array([learned[n] - reference[n] for n in names])
    n = len(d)
    half = stats.t.ppf(0.975, n - 1) * d.std(ddof=1) / np.sqrt(n)
    p = sign_flip_p(d)
    return {"trials": n, "learned": float(np.mean([learned[k] for k in names])),
            "reference": float(np.mean([reference[k] for k in names])),
            "difference": float(d.mean()), "ci95": [float(d.mean() - half), float(d.mean() + half)],
            "lower": int((d < 0).sum()), "p_sign_flip": p}


def _sums(d: np.ndarray) -> np.ndarray:
    """Every signed sum ``sum_i s_i d_i``, ``s_i = +-1`` (``2^len(d)`` of them)."""
    return np.array(list(itertools.product((1.0, -1.0), repeat=len(d)))) @ d


def sign_flip_p(d: np.ndarray) -> float:
    """The share of the ``2^n`` sign patterns whose signed sum is at least ``|sum d|`` in size
    (meet in the middle: the two halves' sums, one sorted, counted by bisection)."""
    t = abs(d.sum()) - 1e-12 * np.abs(d).sum()
    if t <= 0:  # a zero sum: every pattern is as extreme (and the two tails below would overlap)
        return 1.0
    a, b = _sums(d[: len(d) // 2]), np.sort(_sums(d[len(d) // 2:]))
    count = (len(b) - np.searchsorted(b, t - a, "left")) + np.searchsorted(b, -t - a, "right")
    return float(count.sum() / (len(a) * len(b)))


def _scored(quats, trials) -> dict:
    return {t.name: rmse(q, t.quat, t.movement) for q, t in zip(quats, trials)}


def cross_validated(cv_runs: list[Path], data_dir: str | None) -> tuple[dict, list]:
    """Each cross-validation trial's metrics by its fold's ensemble (``{trial: metrics}``), and
    the trials."""
    folds_dir, held = fold_trials(FOLDS)
    learned, cv_trials = {}, []
    for folder, names in zip(cv_runs, held):
        trials = read_trials(data_dir or folds_dir, names)
        quats = [run_estimates(m, "val", trials) for m in ensemble_members(folder)]
        learned.update(_scored([ensemble(list(q)) for q in zip(*quats)], trials))
        cv_trials += trials
        print(f"{folder}: {len(trials)} held-out trials", flush=True)
    return learned, cv_trials


def nine_d(cv_runs: list[Path] | None, data_dir: str | None,
           scratch: list[Path] | None = None) -> dict:
    """``{set: {"learned": {trial: metrics}, "vqf": {...}}}`` for ``test`` (by the first folder of
    ``scratch``, else of ``cv_runs``), ``cv`` (fold ensembles fine-tuned from one start) and
    ``scratch`` (fold ensembles trained from scratch on their folds), each where given."""
    default_dir, split = split_trials(None)
    test = read_trials(data_dir or default_dir, split["test"])
    first = (scratch or cv_runs)[0]
    quats = [run_estimates(m, "test", test) for m in ensemble_members(first)]
    out = {"test": {"learned": _scored([ensemble(list(q)) for q in zip(*quats)], test),
                    "vqf": _scored(vqf_9d(test), test)}}
    vqf = None
    for name, runs in (("cv", cv_runs), ("scratch", scratch)):
        if runs:
            learned, cv_trials = cross_validated(runs, data_dir)
            vqf = vqf or _scored(vqf_9d(cv_trials), cv_trials)
            out[name] = {"learned": learned, "vqf": vqf}
    return out


def six_d(root: Path, table: str = "loss6", row: str = "TIL6") -> dict:
    """The 6-D ``row``'s and VQF 6-D's per-trial inclination on validation and test, from the
    docs' tables ``root/<table>_{val,test}/metrics.json``."""
    out = {}
    for name in ("val", "test"):
        path = root / f"{table}_{name}" / "metrics.json"
        rows = json.loads(path.read_text())["inclination"]
        if row not in rows:
            raise SystemExit(f"error: --six-d {table}:{row}: {path} has no row {row!r}; it has "
                             f"{sorted(rows)}.")
        out[name] = {m: {k: v for k, v in rows[src].items() if k[:2].isdigit()}
                     for m, src in (("learned", row), ("vqf", "vqf_6d"))}
    return out


def _six_d_sets(root: Path, items: list[str]) -> dict:
    """``{label: {"inclination": paired}}`` for each ``DIR:ROW`` of ``items``: its validation
    trials, its test trials and both."""
    out = {}
    for item in items:
        table, sep, row = item.partition(":")
        if not (sep and table and row):
            raise SystemExit(f"error: --six-d takes DIR:ROW (e.g. loss6:TIL6), got {item!r}.")
        six = six_d(root, table, row)
        six["both"] = {m: {**six["val"][m], **six["test"][m]} for m in ("learned", "vqf")}
        for name, what in (("val", "{} validation trials, unseen"),
                           ("test", "{} test trials, unseen"), ("both", "the {} unseen")):
            d = six[name]
            what = what.format(len(d["vqf"]))
            out[f"6-D {row}, {what}"] = {"inclination": paired(d["learned"], d["vqf"])}
    return out


def _nine_d_sets(runs, scratch, data_dir) -> dict:
    """``{label: {metric: paired}}`` of the 9-D sets (module docstring)."""
    nine = nine_d(runs, data_dir, scratch)
    val = set(fold_trials(FOLDS[:1])[1][0])
    folds = nine.get("scratch") or nine["cv"]  # fold 1 is the same entry in both
    sets = {  # (label, learned, vqf), per metric
        "9-D, 4 validation trials (fold 1), unseen": {
            m: {k: v for k, v in folds[m].items() if k in val} for m in ("learned", "vqf")},
        "9-D, 8 test trials, unseen": nine["test"],
        "9-D, the 12 unseen (validation and test)": {
            m: {**{k: v for k, v in folds[m].items() if k in val}, **nine["test"][m]}
            for m in ("learned", "vqf")},
    }
    if "cv" in nine:
        sets["9-D, 15 cross-validation trials (11 seen by the folds' start)"] = nine["cv"]
        sets["9-D, all 23 (11 seen by the start)"] = {
            m: {**nine["cv"][m], **nine["test"][m]} for m in ("learned", "vqf")}
    if scratch:
        sets["9-D, 15 cross-validation trials, folds from scratch, unseen"] = nine["scratch"]
        sets["9-D, all 23 unseen (folds from scratch, and test)"] = {
            m: {**nine["scratch"][m], **nine["test"][m]} for m in ("learned", "vqf")}
    return {label: {m: paired({k: v[m] for k, v in d["learned"].items()},
                              {k: v[m] for k, v in d["vqf"].items()}) for m in METRICS}
            for label, d in sets.items()}


def _row(label: str, metric: str, r: dict) -> str:
    return (f"| {label} | {metric} | {r['trials']} | {r['learned']:.3f} | {r['reference']:.3f} | "
            f"{r['difference']:+.3f} [{r['ci95'][0]:+.3f}, {r['ci95'][1]:+.3f}] | "
            f"{r['lower']} of {r['trials']} | {r['p_sign_flip']:.3f} |")


def _folders(flag: str, value: str | None) -> list[Path] | None:
    if value is None:
        return None
    runs = [Path(r) for r in value.split(",") if r]
    if len(runs) != len(FOLDS):
        raise SystemExit(f"error: {flag}: one ensemble folder per fold ({len(FOLDS)}), got "
                         f"{len(runs)}.")
    return runs


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cv-runs", default=None,
                   help="one ensemble folder per fold of configs/broad/cv/, comma-separated: the "
                        "folds fine-tuned from one start that saw folds 2 and 3 (optimistic rows)")
    p.add_argument("--scratch-runs", default=None,
                   help="as --cv-runs, each fold's ensemble trained from scratch on its fold's "
                        "training trials (every stage): its 15 trials are unseen")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--docs", default="docs/real_data", help="where the 6-D tables are")
    p.add_argument("--six-d", action="append", default=None, metavar="DIR:ROW",
                   help="a 6-D row of the broad.six_d tables DOCS/DIR_{val,test} (repeatable; "
                        "default loss6:TIL6); alone, without the folds' ensembles: 6-D rows only")
    p.add_argument("--write", default=None, help="a .md path; the .json beside it")
    args = p.parse_args(argv)
    runs, scratch = (_folders(flag, value) for flag, value in (
        ("--cv-runs", args.cv_runs), ("--scratch-runs", args.scratch_runs)))
    if not (runs or scratch or args.six_d):
        p.error("give the folds' ensembles: --scratch-runs (or --cv-runs), one folder per fold "
                "(or --six-d DIR:ROW alone for the 6-D rows)")
    six = _six_d_sets(Path(args.docs), args.six_d or ["loss6:TIL6"])
    result = _nine_d_sets(runs, scratch, args.data_dir) if (runs or scratch) else {}
    result.update(six)
    lines = ["# BROAD: the learned filter against VQF, paired over trials", "",
             "Difference: learned - VQF (deg, mean over trials) with its 95 % Student-t interval; "
             "p: the exact two-sided sign-flip test of a zero mean difference. \"Unseen\": no "
             "stage of the observer trained on the trial; only the test trials were also left "
             "out of every choice (benchmarks/broad_paired.py's docstring).",
             "", "| set | metric | trials | learned | VQF | difference [95 % CI] | learned lower on "
             "| p |", "|---|---|---|---|---|---|---|---|"]
    for label, ms in result.items():
        lines += [_row(label, m, r) for m, r in ms.items()]
    lines += ["", "Command: `python benchmarks/broad_paired.py " + shlex.join(
        argv if argv is not None else sys.argv[1:]) + "`", "", ATTRIBUTION, ""]
    text = "\n".join(lines)
    print(text)
    if args.write:
        write_text_atomic(Path(args.write), text)
        write_text_atomic(Path(args.write).with_suffix(".json"), json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
