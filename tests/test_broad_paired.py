"""The paired comparison of ``benchmarks/broad_paired.py`` (learned - VQF over trials): the exact
sign-flip p-value against brute force over every sign pattern, and the t-interval against
scipy's, on differences made up here (the BROAD data are not needed)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import stats


@pytest.fixture(scope="module")
def bp(load_script):
    return load_script("benchmarks/broad_paired.py")


def _brute(d: np.ndarray) -> float:
    t = abs(d.sum())
    sums = [abs(np.dot(s, d)) for s in itertools.product((1.0, -1.0), repeat=len(d))]
    return float(np.mean([x >= t - 1e-12 for x in sums]))


@pytest.mark.parametrize("n", [1, 2, 3, 8, 13])
def test_the_sign_flip_p_value_counts_every_sign_pattern(bp, n):
    rng = np.random.default_rng(n)
    for shift in (0.0, 0.5, 2.0):
        d = rng.normal(shift, 1.0, n)
        assert bp.sign_flip_p(d) == pytest.approx(_brute(d), abs=1e-12)


def test_the_sign_flip_p_value_pins_its_edges(bp):
    # all of one sign: only the pattern and its mirror reach the sum
    assert bp.sign_flip_p(np.full(10, 0.3)) == pytest.approx(2 / 2**10)
    # ties count as at least as extreme (equal magnitudes: half the patterns sum to zero here)
    assert bp.sign_flip_p(np.array([1.0, -1.0])) == 1.0
    assert bp.sign_flip_p(np.zeros(5)) == 1.0


def test_paired_figures_follow_their_definitions(bp):
    rng = np.random.default_rng(0)
    names = [f"{k:02d}" for k in range(12)]
    ref = {k: float(x) for k, x in zip(names, rng.uniform(0.3, 1.0, 12))}
    learned = {k: ref[k] + float(x) for k, x in zip(names, rng.normal(-0.05, 0.1, 12))}
    r = bp.paired(learned, ref)
    d = np.array([learned[k] - ref[k] for k in names])
    lo, hi = stats.t.interval(0.95, len(d) - 1, loc=d.mean(), scale=stats.sem(d))
    assert r["trials"] == 12 and r["lower"] == int((d < 0).sum())
    assert r["difference"] == pytest.approx(d.mean())
    assert r["ci95"] == pytest.approx([lo, hi])
    assert r["learned"] - r["reference"] == pytest.approx(d.mean())
    assert r["p_sign_flip"] == pytest.approx(_brute(d))
    with pytest.raises(ValueError, match="different trials"):
        bp.paired({**learned, "99": 1.0}, ref)


def test_it_needs_the_folds_ensembles(bp, capsys):
    with pytest.raises(SystemExit):
        bp.main([])
    assert "--scratch-runs" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="one ensemble folder per fold"):
        bp.main(["--scratch-runs", "a,b"])


def test_the_6d_rows_alone_read_the_six_d_tables(bp, tmp_path, capsys):
    import json

    rng = np.random.default_rng(1)
    for split, names in (("val", ["09", "14"]), ("test", ["02", "05", "07"])):
        rows = {m: {n: float(x) for n, x in zip(names, rng.uniform(0.3, 1.0, len(names)))}
                for m in ("vqf_6d", "A")}
        rows = {m: {**r, "mean": float(np.mean(list(r.values())))} for m, r in rows.items()}
        (tmp_path / f"t6_{split}").mkdir()
        (tmp_path / f"t6_{split}" / "metrics.json").write_text(json.dumps({"inclination": rows}))
        if split == "test":
            test = rows
    out = tmp_path / "paired.md"
    bp.main(["--docs", str(tmp_path), "--six-d", "t6:A", "--write", str(out)])
    got = json.loads(out.with_suffix(".json").read_text())
    assert list(got) == ["6-D A, 2 validation trials, unseen", "6-D A, 3 test trials, unseen",
                         "6-D A, the 5 unseen"]
    want = bp.paired({n: test["A"][n] for n in ("02", "05", "07")},
                     {n: test["vqf_6d"][n] for n in ("02", "05", "07")})
    r = got["6-D A, 3 test trials, unseen"]["inclination"]
    assert r["ci95"] == pytest.approx(want.pop("ci95"))
    assert {k: r[k] for k in want} == pytest.approx(want)
    assert got["6-D A, the 5 unseen"]["inclination"]["trials"] == 5
    assert "--six-d t6:A" in out.read_text()
    with pytest.raises(SystemExit, match="has no row 'B'"):
        bp.main(["--docs", str(tmp_path), "--six-d", "t6:B"])
    with pytest.raises(SystemExit, match="DIR:ROW"):
        bp.main(["--docs", str(tmp_path), "--six-d", "t6"])
