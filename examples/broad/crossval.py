"""K-fold cross-validation over BROAD's trials: each configuration scored on every trial of the
folds by the run that did not train on it, over several seeds, to choose among configurations
without the test split::

    python -m manifold_nets_examples.broad.crossval --out docs/real_data/cv \\
        --folds configs/broad/cv/fold1.yaml,configs/broad/cv/fold2.yaml,configs/broad/cv/fold3.yaml \\
        --runs TS9=runs/TS9_s0,runs/TS9_f2_s0,runs/TS9_f3_s0 \\
        --runs TS9=runs/TS9_s1,runs/TS9_f2_s1,runs/TS9_f3_s1 ...

``--folds`` names the folds' split files (``configs/broad/cv/``: each fold's ``val`` is its
held-out trials, ``train`` the others). Each ``--runs LABEL=RUN,...`` is one seed of a
configuration: its runs in the order of ``--folds``, the k-th trained (``broad.train --split``)
on fold k; a label given again adds a seed. A run's split (``split.yaml``, which ``broad.train``
records; in a run without it, the split file its ``command.json`` names, relative to the working
directory) must have its fold's ``val`` (so a run cannot be scored on trials it trained on), and
the folds' held-out trials must not overlap. Each run's estimates of its held-out trials (stored by
``broad.train`` in ``results/learned_val_quaternions.npz``, else estimated) are scored by the
benchmark's metric; a seed's cross-validated figure is the mean over every held-out trial, and a
configuration's row the mean and sample standard deviation of its seeds' figures, each fold's
mean and each trial's total (means over the seeds). VQF (default settings) on the same trials
for reference; ``--ensemble`` adds each configuration's seed ensemble. The configuration (not
an ensemble) with the lowest mean total is marked: the selection rule.
Writes ``table.md`` and ``metrics.json``; data: BROAD, CC-BY-4.0 (Laidig et al. 2021).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import yaml

from manifold_nets.atomic import write_text_atomic
from manifold_nets.destination import check_destination
from manifold_nets.loading import MAX_CONFIG_BYTES
from manifold_nets.threads import use_threads

from .compare import ATTRIBUTION, METRICS
from .data import read_trials, split_trials
from .metric import rmse
from .seeds import ensemble, run_estimates

__all__ = ["fold_trials", "check_run_fold", "cv_rows", "main"]


def fold_trials(folds: list[str]) -> tuple[str, list[list[str]]]:
    """``(data_dir, [held-out trial names of each fold])`` from the folds' split files; raises
    ``ValueError`` where folds overlap or a fold trains on its own held-out trials."""
    data_dir, held = None, []
    for path in folds:
        d, splits = split_trials(_small_file(path, "--folds"))
        out, train = splits.get("val", []), splits.get("train", [])
        if not out:
            raise ValueError(f"--folds {path}: its 'val' split (the held-out trials) is empty.")
        if set(out) & set(train):
            raise ValueError(f"--folds {path}: trains on held-out trial(s) "
                             f"{sorted(set(out) & set(train))}.")  # fmt: skip
        data_dir = data_dir or d
        held.append(out)
    seen = [n for names in held for n in names]
    if len(seen) != len(set(seen)):
        raise ValueError(f"--folds: the folds' held-out trials overlap ({sorted(seen)}).")
    return data_dir, held


def _small_file(path, what: str) -> Path:
    """``path`` if it is a regular file of at most :data:`MAX_CONFIG_BYTES` (a run folder's files
    are hostile: a device or a huge file is never read); ``ValueError`` naming it otherwise."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{what} {path} is not a file.")
    if path.stat().st_size > MAX_CONFIG_BYTES:
        raise ValueError(f"{what} {path} is over {MAX_CONFIG_BYTES} bytes.")
    return path


def check_run_fold(run: Path, held: list[str], fold: str) -> None:
    """Raises ``ValueError`` unless ``run`` was trained with a split whose held-out trials are
    ``held``: the trials ``broad.train`` recorded (``split.yaml``), or for a run without that
    file the split file its ``command.json`` names (relative to the working directory; none: the
    default trials.yaml); an ensemble folder's every member so."""
    from manifold_nets.loading import ArtefactError, ensemble_members

    try:
        members = ensemble_members(Path(run))
    except ArtefactError as err:
        raise ValueError(f"--runs {run}: {err}") from None
    if members is not None:
        for member in members:
            check_run_fold(member, held, fold)
        return
    try:
        if (Path(run) / "split.yaml").exists():
            _, splits = split_trials(_small_file(Path(run) / "split.yaml", "the run's"))
        else:
            command = json.loads(_small_file(run / "command.json", "the run's").read_text())
            split = command.get("split") if isinstance(command, dict) else None
            if split is not None and not isinstance(split, str):
                raise ValueError(f"its split is {split!r}, not a path")
            _, splits = split_trials(None if split is None else _small_file(split, "its split file"))
    except (OSError, ValueError, AttributeError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise ValueError(f"--runs {run}: cannot read the split it was trained with ({err}).") from None
    if sorted(splits.get("val", [])) != sorted(held):
        raise ValueError(f"--runs {run}: trained with held-out trials {splits.get('val')}, not "
                         f"fold {fold}'s {held}; give the runs in the order of --folds.")


def cv_rows(trials: dict, held: list[list[str]], groups: dict, with_ensemble: bool = False) -> dict:
    """``{label: {"seeds", "mean", "std", "per_seed", "folds", "trials"}}`` for ``groups``
    ``{label: [[run of fold 1, run of fold 2, ...] for each seed]}``; ``with_ensemble`` adds,
    for a configuration of several seeds, the row of its seeds' averaged estimate
    (:func:`.seeds.ensemble`; each fold's seeds on the fold's trials), marked ``"ensemble"``."""
    rows = {}
    for label, seeds in groups.items():
        per_seed, estimates = [], {}
        for runs in seeds:
            scores = {}
            for run, names in zip(runs, held):
                fold = [trials[n] for n in names]
                for t, q in zip(fold, run_estimates(run, "val", fold)):
                    scores[t.name] = rmse(q, t.quat, t.movement)
                    estimates.setdefault(t.name, []).append(q)
            per_seed.append(scores)
        figures = [{m: float(np.mean([s[n][m] for n in s])) for m in METRICS} for s in per_seed]
        rows[label] = {
            "seeds": [[str(r) for r in runs] for runs in seeds],
            "mean": {m: float(np.mean([f[m] for f in figures])) for m in METRICS},
            "std": {m: float(np.std([f[m] for f in figures], ddof=1)) if len(figures) > 1
                    else None for m in METRICS},  # fmt: skip
            "per_seed": figures,
            "folds": [float(np.mean([s[n]["total"] for s in per_seed for n in names]))
                      for names in held],  # fmt: skip
            "trials": {n: float(np.mean([s[n]["total"] for s in per_seed]))
                       for names in held for n in names},  # fmt: skip
        }
        if with_ensemble and len(seeds) > 1:
            per = {n: rmse(ensemble(qs), trials[n].quat, trials[n].movement)
                   for n, qs in estimates.items()}  # fmt: skip
            rows[f"{label} (ensemble of {len(seeds)})"] = {
                "seeds": [[str(r) for r in runs] for runs in seeds], "std": None, "ensemble": True,
                "mean": {m: float(np.mean([v[m] for v in per.values()])) for m in METRICS},
                "folds": [float(np.mean([per[n]["total"] for n in names])) for names in held],
                "trials": {n: v["total"] for n, v in per.items()},
            }
    return rows


def _table(rows: dict, held: list[list[str]], chosen: str) -> str:
    names = [n for names in held for n in names]
    head = ["configuration", "seeds", *METRICS, *[f"fold {k + 1}" for k in range(len(held))],
            *[n[:2] for n in names]]  # fmt: skip
    lines = [f"### {len(held)}-fold cross-validation over {len(names)} BROAD trials", "",
             "RMSE in degrees over the movement phases, each trial estimated by the run that did "
             "not train on it: mean over the trials (± the sample std over the seeds), each "
             "fold's mean total, then each trial's total (means over the seeds). Folds: "
             + "; ".join(f"{k + 1}: " + ", ".join(n[:2] for n in f) for k, f in enumerate(held))
             + f". Lowest mean total (the selection rule): **{chosen}**.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, r in rows.items():
        std = r.get("std") or {}
        cells = [f"{r['mean'][m]:.2f}" + (f" ± {std[m]:.2f}" if std.get(m) is not None else "")
                 for m in METRICS]  # fmt: skip
        lines.append("| " + " | ".join([
            label, str(len(r["seeds"])) if r["seeds"] else "-", *cells,
            *[f"{v:.2f}" for v in r["folds"]], *[f"{r['trials'][n]:.2f}" for n in names]]) + " |")
    return "\n".join(lines + ["", ATTRIBUTION, ""])


def _groups(items: list[str], n_folds: int) -> dict:
    out: dict = {}
    for item in items:
        label, sep, runs = item.partition("=")
        runs = [Path(r) for r in runs.split(",") if r]
        if not sep or not label or label == "vqf" or len(runs) != n_folds:
            raise ValueError(f"--runs takes LABEL=RUN,... with one run per fold ({n_folds}) and a "
                             f"label other than 'vqf', got {item!r}.")
        missing = [str(r) for r in runs if not r.is_dir()]
        if missing:
            raise ValueError(f"--runs {label}: no such run folder(s) {missing}.")
        out.setdefault(label, []).append(runs)
    if not out:
        raise ValueError("give at least one --runs LABEL=RUN,... (one run per fold).")
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--folds", required=True, help="the folds' split files, comma-separated")
    p.add_argument("--runs", action="append", default=[], metavar="LABEL=RUN,RUN,...")
    p.add_argument("--ensemble", action="store_true",
                   help="add each configuration's seed ensemble (not among the rule's choices)")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--threads", type=int, default=None)
    a = p.parse_args(argv)
    try:
        use_threads(a.threads)
        folds = [f for f in a.folds.split(",") if f]
        default_dir, held = fold_trials(folds)
        groups = _groups(a.runs, len(folds))
        for seeds in groups.values():
            for runs in seeds:
                for k, (run, names) in enumerate(zip(runs, held)):
                    check_run_fold(run, names, folds[k])
        out = check_destination(a.out, folder=True)
        names = [n for f in held for n in f]
        trials = {t.name: t for t in read_trials(a.data_dir or default_dir, names)}
        rows = cv_rows(trials, held, groups, a.ensemble)
        single = [k for k in rows if not rows[k].get("ensemble")]  # the rule chooses among these
        chosen = min(single, key=lambda k: rows[k]["mean"]["total"])
        from .reference import vqf_9d

        ordered = [trials[n] for n in names]
        per = {t.name: rmse(q, t.quat, t.movement) for t, q in zip(ordered, vqf_9d(ordered))}
        rows = {"vqf": {"seeds": [], "std": None,
                        "mean": {m: float(np.mean([v[m] for v in per.values()])) for m in METRICS},
                        "folds": [float(np.mean([per[n]["total"] for n in f])) for f in held],
                        "trials": {n: v["total"] for n, v in per.items()}}, **rows}  # fmt: skip
        text = _table(rows, held, chosen)
        out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(out / "table.md", text)
        write_text_atomic(out / "metrics.json", json.dumps({"chosen": chosen, "rows": rows},
                                                           indent=1) + "\n")  # fmt: skip
        print(text)
    except (ValueError, OSError) as err:
        raise SystemExit(f"error: {err}") from None


if __name__ == "__main__":
    main()
