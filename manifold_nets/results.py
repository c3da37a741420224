"""Results of finished runs gathered: a sweep summarized over seeds, methods compared per sigma.

Every run of the train (or evaluate) command writes ``results/metrics.json`` (one table row per
sigma) and ``results/curves.json`` (mean error against the step), whatever its ``method=``.

* :func:`collect` and :func:`summarize`: the rows of every job of a hydra multirun, prefixed by
  the job's overrides, and their mean and standard deviation over seeds;
* :func:`collect_runs`, :func:`comparison_rows` and :func:`step_curves`: runs of several
  methods (the learned observer, ablations, baselines, filters) as one table per sigma with
  ``<method> / <reference>`` error ratios, and their per-step curves. A run's table says its
  method (``learned``, ``ekf``, ...); a comparison names a trained observer by its experiment
  (``paper_cpu``, the ``label`` of its ``metrics.json``), so that two experiments stay apart.

The commands ``manifold_nets.cli.sweep`` and ``manifold_nets.cli.compare`` write them out.
"""

from __future__ import annotations

import json
import math
import statistics
from collections.abc import Sequence
from pathlib import Path

__all__ = [
    "collect", "summarize", "collect_runs", "comparison_rows", "horizon_rows", "read_metrics",
    "step_curves",
]


def _overrides(job: Path) -> dict[str, str]:
    path = job / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return {}
    from omegaconf import OmegaConf

    out = {}
    for item in OmegaConf.to_container(OmegaConf.load(path)) or []:
        key, _, value = str(item).partition("=")
        out[key.lstrip("+~")] = value
    return out


def collect(root: str | Path) -> list[dict]:
    """One row per (job, sigma) for every ``results/metrics.json`` under ``root``."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(
            f"{root} is not a folder; pass a multirun folder (multirun/<name>/<id>)."
        )
    rows = []
    for metrics_path in sorted(root.rglob("results/metrics.json"), key=lambda p: str(p)):
        job = metrics_path.parent.parent
        metrics = read_metrics(metrics_path)
        over = {k: v for k, v in _overrides(job).items() if k != "seed"}
        base = {"job": str(job.relative_to(root)) or ".", **over, "seed": metrics.get("seed")}
        for key in ("best_epoch", "best_val_loss", "test_loss"):
            if metrics.get(key) is not None:
                base[key] = metrics[key]
        for r in metrics.get("table", []):
            rows.append({**base, **r})
    if not rows:
        raise FileNotFoundError(
            f"no results/metrics.json under {root}: did the jobs finish? (a job writes it last)"
        )
    return rows


def read_metrics(path: str | Path) -> dict:
    """A run's ``results/metrics.json``, its table's undefined values (written as ``null``, e.g.
    a reduction against a measurement error of 0) read back as NaN, as the run had them."""
    metrics = json.loads(Path(path).read_text())
    metrics["table"] = [
        {k: math.nan if v is None else v for k, v in r.items()} for r in metrics.get("table", [])
    ]
    return metrics


_KEYS = ("job", "seed", "best_epoch", "best_val_loss", "test_loss", "sequences", "steps", "seconds")


def summarize(rows: list[dict]) -> list[dict]:
    """Mean and std over seeds of every numeric metric, grouped by everything else that is set."""
    metric_cols = [
        c
        for c in rows[0]
        if c not in _KEYS and isinstance(rows[0][c], (int, float)) and c != "sigma"
    ]
    group_cols = [
        c for c in {c for r in rows for c in r} if c not in metric_cols and c not in _KEYS
    ]
    group_cols.sort(key=lambda c: (c != "sigma", c))
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(str(r.get(c, "")) for c in group_cols), []).append(r)
    out = []
    for members in groups.values():
        row = {c: members[0].get(c, "") for c in group_cols}
        row["seeds"] = len(members)
        for c in metric_cols:
            vals = [
                float(m[c])
                for m in members
                if isinstance(m.get(c), (int, float)) and not math.isnan(float(m[c]))
            ]
            if vals:
                row[f"{c} mean"] = statistics.fmean(vals)
                row[f"{c} std"] = statistics.stdev(vals) if len(vals) > 1 else 0.0
        out.append(row)
    return out


def collect_runs(paths: Sequence[str | Path]) -> list[dict]:
    """``[{"dir", "metrics", "curves", "label"}]`` for every ``results/metrics.json`` under
    ``paths``; the label is the run's method, made distinct where several share one."""
    runs = []
    for root in map(Path, paths):
        if not root.exists():
            raise FileNotFoundError(f"{root} does not exist; pass run folders or multirun folders.")
        found = sorted(root.rglob("results/metrics.json"), key=str)
        if (root / "results" / "metrics.json").is_file():
            found = [root / "results" / "metrics.json"]
        if not found:
            raise FileNotFoundError(
                f"no results/metrics.json under {root}: did the run finish? (it is written last)"
            )
        for path in found:
            metrics = read_metrics(path)
            cpath = path.with_name("curves.json")
            curves = json.loads(cpath.read_text()) if cpath.is_file() else {}
            runs.append({"dir": str(path.parent.parent), "metrics": metrics, "curves": curves})
    return _name_runs(runs)


def _label(run: dict) -> str:
    return run.get("label") or _run_label(run["metrics"])


def _run_label(metrics: dict) -> str:
    """What a run is called in a comparison: the ``label`` its ``metrics.json`` records (a
    trained observer's experiment, ``paper_cpu``; a baseline's method, ``ekf``), else its
    ``method``."""
    return str(metrics.get("label") or metrics.get("method") or "learned")


def _name_runs(runs: list[dict]) -> list[dict]:
    """Gives each run a distinct ``label``: its :func:`_run_label`, with `` seed <s>`` added
    where runs of one label differ in seed (a seed sweep), and `` #<i>`` where even that
    repeats."""
    base = [_run_label(r["metrics"]) for r in runs]
    labels = list(base)
    for i, run in enumerate(runs):
        if base.count(base[i]) > 1 and "seed" in run["metrics"]:
            labels[i] = f"{base[i]} seed {run['metrics']['seed']}"
    seeded = list(labels)
    for i, label in enumerate(seeded):
        if seeded.count(label) > 1:
            labels[i] = f"{label} #{seeded[: i + 1].count(label)}"
    for run, label in zip(runs, labels):
        run["label"] = label
    return runs


def _metric_names(rows: Sequence[dict]) -> list[str]:
    names: list[str] = []
    for r in rows:
        for k in r:
            if k.endswith(" est") and k[:-4] not in names:
                names.append(k[:-4])
    return names


def comparison_rows(runs: Sequence[dict], reference: str = "ekf") -> list[dict]:
    """The comparison table (module docstring), sorted by sigma, methods in the order given."""
    by_sigma: dict[float, list[tuple[dict, dict]]] = {}
    for run in runs:
        for row in run["metrics"].get("table", []):
            by_sigma.setdefault(float(row["sigma"]), []).append((run, row))
    out: list[dict] = []
    for sigma in sorted(by_sigma):
        pairs = by_sigma[sigma]
        sizes = {(r.get("sequences"), r.get("steps")) for _, r in pairs}
        if len(sizes) > 1:
            raise ValueError(
                f"sigma {sigma:g}: the runs were evaluated on sets of different sizes "
                f"{sorted(sizes, key=str)} (sequences, steps); evaluate them with the same eval.*."
            )
        names = _metric_names([r for _, r in pairs])
        block = []
        for run, r in pairs:
            row = {"sigma": sigma, "method": _label(run)}
            row.update({n: r.get(f"{n} est", math.nan) for n in names})
            row["membership mean"] = r.get("membership mean", math.nan)
            row["membership max"] = r.get("membership max", math.nan)
            if "us/step" in r:
                row["us/step"] = r["us/step"]
            row["trained"] = "checkpoint" in run["metrics"]
            block.append(row)
        if not any(b["method"] == "raw" for b in block):  # the raw measurement as a reference row
            r0 = pairs[0][1]
            meas = {n: r0[f"{n} meas"] for n in names if f"{n} meas" in r0}
            if meas:
                block.insert(0, {"sigma": sigma, "method": "measurement", **meas, "trained": False})
        ref = next((b for b in block if b["method"] == reference), None)
        ratios = []
        if ref is not None:
            for b in block:
                if b["trained"] and b is not ref:
                    q = {"sigma": sigma, "method": f"{b['method']} / {reference}"}
                    for n in names:
                        if isinstance(ref.get(n), float) and ref[n] > 0:
                            q[n] = b[n] / ref[n]
                    ratios.append(q)
        for b in block:
            b.pop("trained")
        out += block + ratios
    return out


def step_curves(runs: Sequence[dict], sigma: float) -> tuple[dict, int]:
    """``{method: {metric: curve}}`` of the estimates at ``sigma`` and the runs' skip."""
    out: dict[str, dict] = {}
    skip = 10
    for run in runs:
        c = run["curves"].get(f"{sigma:g}")
        if not c:
            continue
        out[_label(run)] = {
            k.removesuffix(" est"): v
            for k, v in c.items()
            if not k.endswith(" meas")
        }
        skip = int(run["metrics"].get("skip_steps", skip))
    return out, skip


def horizon_rows(runs: Sequence[dict], steps: Sequence[int], window: int = 10) -> list[dict]:
    """The error of every method at chosen steps: does it grow past the training length?

    One row per sigma and method: for each metric of the curves (``R``, ``p``, ...) and each
    step ``k`` of ``steps``, ``"<metric>@<k>"``, the mean of the step curve over
    ``k - window .. k + window`` (clipped to the curve; the curves are already means over the
    sequences), and ``"<metric> <last>/<first>"``, the ratio of the last step's value to the
    first's (at most 1: the error does not grow). Steps beyond a curve are left out.
    """
    steps = sorted({int(k) for k in steps})
    if not steps or steps[0] < 0:
        raise ValueError(f"steps must be step indices >= 0, e.g. 100 1000; got {list(steps)}.")
    rows = []
    sigmas = sorted({float(s) for run in runs for s in run["curves"]})
    for sigma in sigmas:
        curves, _ = step_curves(runs, sigma)
        for method, metrics in curves.items():
            row: dict = {"sigma": sigma, "method": method}
            for name, curve in metrics.items():
                if name == "membership":
                    continue
                found = []
                for k in steps:
                    if k >= len(curve):
                        continue
                    part = curve[max(0, k - window) : k + window + 1]
                    row[f"{name}@{k}"] = sum(part) / len(part)
                    found.append(k)
                if len(found) >= 2 and row[f"{name}@{found[0]}"] > 0:
                    a, b = found[0], found[-1]
                    row[f"{name} {b}/{a}"] = row[f"{name}@{b}"] / row[f"{name}@{a}"]
            rows.append(row)
    return rows
