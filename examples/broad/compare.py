"""The BROAD comparison: per-trial and mean RMSE (total, heading, inclination; degrees) of each
method, a markdown table per split, a figure per trial, and the command that writes them::

    python -m manifold_nets_examples.broad.compare --data-dir ../shared/broad/data_mat \\
        --out results/broad [--split test[,all]] [--methods complementary,ekf,vqf,...] \\
        [--tuned FILE] [--learned LABEL=RUN ...]

Classical rows: ``complementary`` and ``ekf`` (:mod:`.filters`, gains tuned on the train split
only, or read from ``--tuned``; the tuned gains are written to ``OUT/tuned.json``), ``vqf``,
``madgwick``, ``mahony`` (:mod:`.reference`, the ahrs rows at the BROAD authors' gains) and the
authors' published numbers (``--published DIR``, default ``DATA_DIR/../published``). Learned
observers' rows: ``--learned LABEL=RUN`` (a run folder of :mod:`.train`; repeatable), estimated
on whole trials like the filters; from Python, :func:`write_results`'s ``extra``
(``{method: {trial: (T, 4) quaternions}}``).

Every argument is checked before any work (split and method names, ``--learned``, ``--tuned``,
that ``--out`` is a folder that can be written); every file is written atomically; errors end
the command with ``error: ...``. Figures and tables derived from BROAD carry its attribution
(CC-BY-4.0, Laidig et al. 2021).
"""

from __future__ import annotations

import argparse
import io
import json
import time
from pathlib import Path

import numpy as np

from manifold_nets.atomic import atomic_open, write_text_atomic
from manifold_nets.destination import check_destination
from manifold_nets.plugins import locate
from manifold_nets.threads import use_threads

from .data import BroadFormatError, Trial, read_trials, split_trials
from .metric import errors, rmse

__all__ = ["comparison", "markdown_table", "plot_trial", "classical_estimates", "write_results",
           "main"]  # fmt: skip

METRICS = ("total", "heading", "inclination")
CLASSICAL = ("complementary", "ekf", "vqf", "madgwick", "mahony", "published")
ATTRIBUTION = (
    "Data: BROAD (D. Laidig, M. Caruso, A. Cereatti, T. Seel, Data 6(7):72, 2021, "
    "https://doi.org/10.3390/data6070072), CC-BY-4.0."
)


def comparison(trials: list[Trial], estimates: dict, published: dict | None = None) -> list[dict]:
    """Rows ``{"method", "trial", "total", "heading", "inclination"}`` (degrees).

    ``estimates``: ``{method: [(T, 4) quaternions, one per trial]}``; ``published``: ``{method:
    {trial: {metric: deg}}}`` (rows known only as numbers). Each method gets one row per trial
    and a ``"mean"`` row (the mean over the trials it has, as the benchmark averages).
    """
    rows = []
    for method, quats in estimates.items():
        if len(quats) != len(trials):
            raise ValueError(f"{method}: {len(quats)} estimates for {len(trials)} trials.")
        per = {t.name: rmse(q, t.quat, t.movement) for t, q in zip(trials, quats)}
        rows += _method_rows(method, per)
    for method, per in (published or {}).items():
        have = {t.name: per[t.name] for t in trials if t.name in per}
        if have:
            rows += _method_rows(method, have)
    return rows


def _method_rows(method: str, per: dict) -> list[dict]:
    rows = [{"method": method, "trial": name, **vals} for name, vals in per.items()]
    mean = {m: float(np.mean([v[m] for v in per.values()])) for m in METRICS}
    return rows + [{"method": method, "trial": "mean", **mean}]


def markdown_table(rows: list[dict], title: str) -> str:
    """A markdown table: one line per method, the mean of each metric, then each trial's total."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    names = list(dict.fromkeys(r["trial"] for r in rows if r["trial"] != "mean"))
    by = {(r["method"], r["trial"]): r for r in rows}
    head = ["method", "total", "heading", "inclination", *[n[:2] for n in names]]
    lines = [f"### {title}", "", "RMSE in degrees over the movement phases; mean over trials, "
             "then each trial's total (columns: trial numbers).", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]  # fmt: skip
    for m in methods:
        mean = by[(m, "mean")]
        cells = [f"{mean[k]:.2f}" for k in METRICS]
        cells += [f"{by[(m, n)]['total']:.2f}" if (m, n) in by else "-" for n in names]
        lines.append("| " + " | ".join([m, *cells]) + " |")
    return "\n".join(lines + ["", ATTRIBUTION, ""])


def plot_trial(trial: Trial, estimates: dict, path: str | Path) -> None:
    """The total error (deg) against time of each method in ``estimates`` ``{method: (T, 4)}``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    time_s = np.arange(len(trial)) / trial.rate
    fig, ax = plt.subplots(figsize=(10, 3.5))
    for method, q in estimates.items():
        err = np.degrees(errors(q, trial.quat)["total"])
        ax.plot(time_s, err, lw=0.8, label=method)
    ymax = ax.get_ylim()[1]
    ax.fill_between(time_s, 0, ymax, where=~trial.movement, color="0.9", lw=0, label="rest")
    ax.set(xlabel="time (s)", ylabel="total error (deg)", title=trial.name, ylim=(0, ymax))
    ax.legend(loc="upper left", fontsize=7, ncol=4)
    fig.text(0.01, 0.01, ATTRIBUTION, fontsize=5)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, dpi=120, format="png")
    plt.close(fig)
    with atomic_open(path, "wb") as f:
        f.write(buf.getvalue())


def _read_tuned(tuned_path, methods) -> dict | None:
    """The gains of ``--tuned`` (checked before any work), or ``None`` to tune them."""
    if tuned_path is None:
        return None
    try:
        tuned = json.loads(Path(tuned_path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"--tuned {tuned_path}: cannot be read as JSON ({err}).") from None
    need = ["m_ref", *[m for m in ("complementary", "ekf") if m in methods]]
    if not isinstance(tuned, dict) or any(k not in tuned for k in need):
        raise ValueError(f"--tuned {tuned_path}: needs the keys {need} (the tuned.json this "
                         "command writes).")
    return tuned


def _tuned(train: list[Trial], tuned: dict | None, out: Path) -> dict:
    from . import filters

    if tuned is not None:
        return tuned
    m_ref = filters.magnetic_reference(train)
    best_c, _ = filters.tune("complementary", train, m_ref)
    best_e, _ = filters.tune("ekf", train, m_ref)
    tuned = {"m_ref": m_ref.tolist(), "complementary": best_c, "ekf": best_e}
    write_text_atomic(out / "tuned.json", json.dumps(tuned, indent=2))
    return tuned


def classical_estimates(trials: list[Trial], tuned: dict, methods) -> tuple[dict, dict]:
    """``({method: [(T, 4)]}, {method: seconds})`` of the classical filters in ``methods``."""
    from . import filters, reference

    m_ref = np.asarray(tuned["m_ref"])
    runs = {
        "complementary": lambda: filters.complementary(trials, m_ref, **tuned["complementary"]),
        "ekf": lambda: filters.ekf(trials, m_ref, **tuned["ekf"]),
        "vqf": lambda: reference.vqf_9d(trials),
        "madgwick": lambda: reference.madgwick(trials, m_ref),
        "mahony": lambda: reference.mahony(trials, m_ref),
    }
    est, secs = {}, {}
    for m in methods:
        if m in runs:
            t0 = time.perf_counter()
            est[m] = runs[m]()
            secs[m] = time.perf_counter() - t0
            print(f"{m}: {secs[m]:.1f} s for {len(trials)} trial(s)", flush=True)
    return est, secs


def write_results(out, splits: dict, trials: dict, estimates: dict, published=None, extra=None):
    """Writes ``table.md``, ``metrics.json`` and ``figures/<trial>.png`` under ``out``.

    ``splits`` ``{split: [names]}``; ``trials`` ``{name: Trial}``; ``estimates`` and ``extra``
    (the learned observer's hook) ``{method: {name: (T, 4)}}``. Returns the rows per split.
    """
    out = Path(out)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    every = {**estimates, **(extra or {})}
    tables, metrics = [], {}
    for split, names in splits.items():
        ts = [trials[n] for n in names]
        est = {m: [per[n] for n in names] for m, per in every.items()}
        rows = comparison(ts, est, published)
        metrics[split] = rows
        tables.append(markdown_table(rows, f"BROAD, {split} split ({len(ts)} trials)"))
        for t in ts:
            plot_trial(t, {m: per[t.name] for m, per in every.items()}, out / "figures" /
                       f"{t.name}.png")  # fmt: skip
    write_text_atomic(out / "table.md", "\n".join(tables))
    write_text_atomic(out / "metrics.json", json.dumps(metrics, indent=1))
    return metrics


def _parse_learned(items: list[str]) -> dict[str, Path]:
    """``{label: run folder}`` from ``LABEL=RUN`` arguments (``RUN`` a run folder, a checkpoint or
    ``zoo:<entry>``), checked before any work."""
    out = {}
    for item in items:
        label, sep, run = item.partition("=")
        if not sep or not label or not run:
            raise ValueError(f"--learned takes LABEL=RUN (e.g. learned=runs/broad), got {item!r}.")
        if label in CLASSICAL or label in out:
            raise ValueError(f"--learned label {label!r} is taken; choose another.")
        try:
            path = locate(run)  # a run folder, a checkpoint or zoo:<entry>
        except ValueError as err:
            raise ValueError(f"--learned {label}={run}: {err}") from None
        if not path.exists():
            raise ValueError(f"--learned {label}={run}: no such run folder or checkpoint.")
        out[label] = path
    return out


def learned_estimates(run, trials: list[Trial]) -> dict:
    """``{trial name: (T, 4)}`` of the trained observer at ``run`` (a run folder of
    :mod:`.train`, loaded without executing anything it names), whole trials from TRIAD."""
    from manifold_nets import load_observer

    from .evaluate import observer_quaternions

    observer, system, _ = load_observer(run)
    quats = observer_quaternions(observer, system, trials, source=str(run))
    return {t.name: q for t, q in zip(trials, quats)}


def _chosen(a, splits: dict, learned: dict) -> tuple[dict, list[str]]:
    """``({split: names}, methods)`` of ``--split`` and ``--methods``, checked (no method at
    all only with ``--learned`` rows)."""
    every = [n for v in splits.values() for n in v]
    asked = [s for s in a.split.split(",") if s]
    unknown = [s for s in asked if s != "all" and s not in splits]
    if not asked or unknown:
        raise BroadFormatError(f"--split {a.split!r}: unknown or no split {unknown}; choose from "
                               f"{sorted(splits) + ['all']}.")
    methods = [m for m in a.methods.split(",") if m]
    if (not methods and not learned) or any(m not in CLASSICAL for m in methods):
        raise ValueError(f"--methods {a.methods!r}: choose from {list(CLASSICAL)} (learned "
                         "observers come with --learned LABEL=RUN).")
    return {s: every if s == "all" else splits[s] for s in asked}, methods


def main(argv=None) -> None:
    try:
        _main(argv)
    except (ValueError, OSError) as err:
        raise SystemExit(f"error: {err}") from None


def _main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data-dir", default=None, help="folder of the BROAD .mat trials")
    p.add_argument("--out", required=True)
    p.add_argument("--split", default="test",
                   help="train, val, test or all (the 23 trials); several: test,all")
    p.add_argument("--methods", default=",".join(CLASSICAL))
    p.add_argument("--tuned", default=None, help="JSON of tuned gains (skips the grid search)")
    p.add_argument("--published", default=None, help="folder of the authors' results JSON")
    p.add_argument("--config", default=None, help="split file (default configs/broad/trials.yaml)")
    p.add_argument("--learned", action="append", default=[], metavar="LABEL=RUN",
                   help="a trained observer's row: its label and run folder (broad.train); "
                        "repeatable")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: one, or OMP_NUM_THREADS)")
    a = p.parse_args(argv)
    use_threads(a.threads)
    learned = _parse_learned(a.learned)
    default_dir, splits = split_trials(a.config)
    chosen, methods = _chosen(a, splits, learned)
    tuned_gains = _read_tuned(a.tuned, methods)
    out = check_destination(a.out, folder=True)
    data_dir = Path(a.data_dir or default_dir)
    names = list(dict.fromkeys(n for v in chosen.values() for n in v))
    trials = {t.name: t for t in read_trials(data_dir, names)}
    if tuned_gains is None and "train" not in splits:
        raise BroadFormatError(f"{a.config}: tuning the gains needs a 'train' split (or give "
                               "--tuned FILE).")
    train = read_trials(data_dir, splits["train"]) if tuned_gains is None else []
    published = None
    if "published" in methods:
        from .reference import published as read_published

        pub_dir = Path(a.published) if a.published else data_dir.parent / "published"
        published = read_published(pub_dir, names)
    out.mkdir(parents=True, exist_ok=True)
    tuned = _tuned(train, tuned_gains, out)
    est, secs = classical_estimates(list(trials.values()), tuned, methods)
    est = {m: dict(zip(trials, qs)) for m, qs in est.items()}
    for label, run in learned.items():
        t0 = time.perf_counter()
        est[label] = learned_estimates(run, list(trials.values()))
        secs[label] = time.perf_counter() - t0
        print(f"{label}: {secs[label]:.1f} s for {len(trials)} trial(s)", flush=True)
    write_results(out, chosen, trials, est, published)
    write_text_atomic(out / "seconds.json", json.dumps(secs, indent=1))
    print((out / "table.md").read_text())


if __name__ == "__main__":
    main()
