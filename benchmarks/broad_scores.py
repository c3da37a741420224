"""What the BROAD prior benchmarks share (imported by the scripts beside this file): a split's
trials, the benchmark's metric over one estimate per trial, and VQF's row beside them."""

from __future__ import annotations

import numpy as np

from manifold_nets_examples.broad.data import read_trials, split_trials
from manifold_nets_examples.broad.metric import rmse


def split_of(name: str, data_dir: str | None = None) -> list:
    """The trials of split ``name`` of ``configs/broad/trials.yaml``, read from ``data_dir``
    (default: where the split file says)."""
    default_dir, split = split_trials(None)
    return read_trials(data_dir or default_dir, split[name])


def scores(quats, trials, column: str) -> dict:
    """The metric's means over ``trials`` (``total``, ``heading``, ``inclination``, over the
    movement phases where the reference is known) and, under ``trials``, each trial's ``column``
    by its two-digit number."""
    per = [rmse(q, t.quat, t.movement & t.known) for q, t in zip(quats, trials)]
    return {**{k: float(np.mean([p[k] for p in per])) for k in ("total", "heading", "inclination")},
            "trials": {t.name[:2]: p[column] for t, p in zip(trials, per)}}


def vqf_scores(trials, column: str, six_d: bool = False) -> dict | None:
    """:func:`scores` of VQF (online, default settings; 9-D, or 6-D: its tilt) on ``trials``, or
    ``None`` without the ``vqf`` package."""
    try:
        from manifold_nets_examples.broad.reference import vqf_6d, vqf_9d

        quats = (vqf_6d if six_d else vqf_9d)(trials)
    except ImportError:
        return None
    return scores(quats, trials, column)
