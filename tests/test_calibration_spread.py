"""``benchmarks/calibration_spread.py``: the spread of ``NEES / d`` over sequences tells errors
Gaussian under their covariance (``var q = 2 / d``, ceiling near 95 %) from a covariance too
narrow for some sequences and too wide for others (the body spreads; a cap changes nothing) and
from rare huge values (the cap takes them out)."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def cs(load_script):
    return load_script("benchmarks/calibration_spread.py")


def _q(scale: np.ndarray, rng) -> np.ndarray:
    """``NEES / 3`` of Gaussian errors with per-sequence standard deviations ``scale`` ``(n, 1)``
    under a unit covariance: ``(n, 400)``."""
    errors = rng.standard_normal((len(scale), 400, 3)) * scale[..., None]
    return (errors ** 2).mean(-1)


def test_gaussian_errors_spread_as_the_chi_square(cs):
    r = cs.spread(_q(np.ones((1000, 1)), np.random.default_rng(0)), cap=10.0)
    assert r["var q"] == pytest.approx(2 / 3, rel=0.03)
    assert r["ceiling"] == pytest.approx(0.95, abs=0.01)
    assert r["ceiling capped"] == pytest.approx(r["ceiling"], abs=1e-3)
    assert r["cut"] < 1e-4 and r["anees"] == pytest.approx(1.0, abs=0.01)


def test_a_covariance_wrong_per_sequence_spreads_the_body(cs):
    """Half the sequences with errors 20 % larger than their covariance, half 20 % smaller (scaled
    to keep the ANEES at 1): the spread grows, the ceiling falls, and a cap at 10 does not mend it."""
    rng = np.random.default_rng(1)
    scale = np.where(rng.random((1000, 1)) < 0.5, 1.2, 0.8) / np.sqrt((1.44 + 0.64) / 2)
    r = cs.spread(_q(scale, rng), cap=10.0)
    assert r["anees"] == pytest.approx(1.0, abs=0.02)
    assert r["var q"] > 0.8 and r["ceiling"] < 0.92
    assert r["ceiling capped"] - r["ceiling"] < 0.005 and r["cut"] < 1e-3


def test_rare_huge_values_are_what_the_cap_takes_out(cs):
    rng = np.random.default_rng(2)
    q = _q(np.ones((1000, 1)), rng)
    q[rng.random(q.shape) < 0.002] = 200.0  # one value in 500 an unwidened outlier
    r = cs.spread(q, cap=10.0)
    assert r["var q"] > 10 * (2 / 3) and r["var q capped"] < 1.0
    assert r["ceiling capped"] > r["ceiling"] + 0.2
    with pytest.raises(ValueError, match="cap must be > 0"):
        cs.spread(q, cap=0.0)


def test_the_command_writes_a_row_per_factor_and_refuses_a_cap_of_zero(cs, tmp_path):
    import json

    out = tmp_path / "spread"
    cs.main(["--cases", "nominal", "--sigmas", "0.1", "--test", "4", "--write", str(out)])
    rows = json.loads(out.with_suffix(".json").read_text())["cases"]["nominal"]
    assert sorted(rows) == ["R 0.1", "p 0.1"]
    assert all(0 <= r["cut"] <= 1 and r["var q"] >= r["var q capped"] >= 0 for r in rows.values())
    assert "| nominal | p | 0.1 |" in out.with_suffix(".md").read_text()
    with pytest.raises(SystemExit):
        cs.main(["--cap", "0", "--cases", "nominal"])
