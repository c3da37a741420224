"""The summary of ``benchmarks/calibration_variants.py`` on result files made up here: each
variant's cells read under its own key, the excluded cell left out, and the counts against the
first variant's cells."""

from __future__ import annotations

import json

import pytest


@pytest.fixture(scope="module")
def cv(load_script):
    return load_script("benchmarks/calibration_variants.py")


def _row(anees, share, scaled=None):
    row = {"anees": anees, "in band": share}
    if scaled is not None:
        row |= {"level scale anees": scaled[0], "level scale": scaled[1]}
    return row


def test_the_summary_counts_cells_under_each_variant_s_key(cv, tmp_path):
    shipped = {"nominal": {"R 0.1": _row(1.10, 0.10, (1.00, 0.95)), "p 0.1": _row(0.95, 0.80, (0.99, 0.70))},
               "outliers": {"p 0.5": _row(6.0, 0.0, (5.0, 0.0)), "R 0.5": _row(1.0, 0.90, (1.0, 0.90))}}
    other = {"nominal": {"R 0.1": _row(1.02, 0.50), "p 0.1": _row(0.97, 0.85)}}
    (tmp_path / "a.json").write_text(json.dumps({"command": "x", "cases": shipped}))
    (tmp_path / "b.json").write_text(json.dumps({"command": "y", "cases": other}))
    rows = cv.summary({"shipped": ("a", ""), "scaled": ("a", "level scale"), "other": ("b", ""),
                       "absent": ("c", "")}, tmp_path)
    assert [r["variant"] for r in rows] == ["shipped", "scaled", "other"]  # no file, no row
    first, scaled, other_row = rows
    assert first["cells"] == 3 and first["anees"] == (0.95, 1.10)  # outliers p 0.5 left out
    assert first["at 90 %"] == 1 and (first["above reference"], first["below reference"]) == (0, 0)
    assert scaled["anees"] == (0.99, 1.0) and scaled["at 90 %"] == 2
    assert (scaled["above reference"], scaled["below reference"]) == (1, 1)
    assert other_row["cells"] == 2 and (other_row["above reference"], other_row["below reference"]) == (2, 0)
    assert other_row["in band"] == (0.5, 0.85)


def test_a_variant_joins_the_cases_it_names_from_several_files(cv, tmp_path):
    """A row that takes the rigid-body cases from one file and the sensor errors from another
    (their own readout); a part whose file is missing drops the whole row, and the between-levels twin
    leaves the sensor errors' part out."""
    a = {"nominal": {"R 0.1": _row(1.0, 0.95)}, "sensor": {"R 0.1": _row(1.2, 0.10)}}
    b = {"sensor": {"R 0.1": _row(1.01, 0.92)}, "nominal": {"R 0.1": _row(2.0, 0.0)}}
    (tmp_path / "a.json").write_text(json.dumps({"command": "x", "cases": a}))
    (tmp_path / "b.json").write_text(json.dumps({"command": "y", "cases": b}))
    spec = [("a", "", ("nominal",)), ("b", "", ("sensor",))]
    rows = cv.summary({"joined": spec, "half": [("a", "", None), ("c", "", None)]}, tmp_path)
    assert [r["variant"] for r in rows] == ["joined"]
    assert rows[0]["cells"] == 2 and rows[0]["anees"] == (1.0, 1.01) and rows[0]["at 90 %"] == 2
    assert rows[0]["file"] == "a + b"
    assert cv._between(spec) == [("a", "", ("nominal",))]  # no "calibration_in_band" to rename
    assert cv._between(("calibration_in_band_x", "k")) == ("calibration_in_band_between_x", "k")
