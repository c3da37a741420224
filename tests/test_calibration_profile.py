"""``benchmarks/calibration_profile.py``: each span of steps' ANEES and share in band, so a level
right on average but off along the run shows where."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def cp(load_script):
    return load_script("benchmarks/calibration_profile.py")


def _q(level: np.ndarray, rng) -> np.ndarray:
    """``NEES / 3`` of 1000 sequences of Gaussian errors whose variance is ``level`` ``(steps,)``
    times their covariance's."""
    errors = rng.standard_normal((1000, len(level), 3)) * np.sqrt(level)[None, :, None]
    return (errors ** 2).mean(-1)


def test_a_level_off_in_one_span_shows_there_alone(cp):
    """Steps 200-500 (k from SKIP = 10 on) 5 % overconfident, the rest right: that span's ANEES
    is 1.05 and its steps mostly out of band; the others near 1 and in band."""
    k = np.arange(991) + 10
    level = np.where((k >= 200) & (k < 500), 1.05, 1.0)
    r = cp.profile(_q(level, np.random.default_rng(0)))
    spans = r["spans"]
    assert list(spans) == ["10-20", "20-50", "50-100", "100-200", "200-500", "500-1000"]
    assert spans["200-500"]["anees"] == pytest.approx(1.05, abs=0.005)
    assert spans["200-500"]["in band"] < 0.6
    for name in ("10-20", "20-50", "50-100", "100-200", "500-1000"):
        assert spans[name]["anees"] == pytest.approx(1.0, abs=0.03)  # 10 steps: sd 0.008
        assert spans[name]["in band"] > 0.85
    assert r["anees"] == pytest.approx(np.mean(level), abs=0.003)


def test_the_command_writes_a_row_per_factor(cp, tmp_path):
    import json

    out = tmp_path / "profile"
    cp.main(["--cases", "nominal", "--sigmas", "0.1", "--test", "4", "--write", str(out)])
    rows = json.loads(out.with_suffix(".json").read_text())["cases"]["nominal"]
    assert sorted(rows) == ["R 0.1", "p 0.1"]
    assert all(len(r["spans"]) == 6 for r in rows.values())
    assert "| nominal | p | 0.1 |" in out.with_suffix(".md").read_text()


def test_the_pooled_row_scores_all_the_levels_sequences_together(cp, tmp_path):
    """``--pooled``: one more row per factor over both levels' sequences; with as many of each,
    its ANEES at every step (so over every span) is the two levels' mean."""
    import json

    out = tmp_path / "pooled"
    cp.main(["--cases", "nominal", "--sigmas", "0.1", "0.3", "--test", "4", "--pooled",
             "--write", str(out)])
    rows = json.loads(out.with_suffix(".json").read_text())["cases"]["nominal"]
    assert sorted(rows) == ["R 0.1", "R 0.3", "R pooled", "p 0.1", "p 0.3", "p pooled"]
    for f in ("R", "p"):
        for span, got in rows[f"{f} pooled"]["spans"].items():
            want = (rows[f"{f} 0.1"]["spans"][span]["anees"] + rows[f"{f} 0.3"]["spans"][span]["anees"]) / 2
            assert got["anees"] == pytest.approx(want, rel=1e-12)
    assert "| nominal | p | pooled |" in out.with_suffix(".md").read_text()
    assert "sigma *pooled*" in out.with_suffix(".md").read_text()
