"""One table of every rigid-body readout variant scored by ``calibration_in_band.py``: how close
each is to calibrated at the paper's five noise levels and between them.

It reads the committed result files (``benchmarks/results/calibration_in_band*.json``; each file's
own command is in it) and, per variant, reports over its cells (a case, a factor, a noise level):
the range of the ANEES, the range of the share of steps in the 95 % band, how many cells reach
the goal's 90 %, and in how many the share in band is above / below the first variant's (the
residual readouts) on the same sets. ``outliers p 0.5`` is left out of every count: one of its
1000 sequences loses its position (``docs/calibration.md``), which no readout repairs. A variant
may join parts of several files (``(file, key, cases)``: only those cases of that file), as the
first row scored with the sensor errors' own readout does::

    python benchmarks/calibration_variants.py --write benchmarks/results/calibration_variants

Nothing is simulated; it runs in a second.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
#: label -> (result file, the key its ANEES and share are under: "" for the readouts themselves,
#: "level scale" for the level scale scored beside them)
FIVE = {
    "residual readouts (the calibration command's default)": (
        "calibration_in_band_residual_readouts", ""),
    "residual readouts + level scale fitted at the five levels": (
        "calibration_in_band_residual_readouts", "level scale"),
    "residual readouts + level scale fitted on 0.10-0.50": ("calibration_in_band_continuous", "level scale"),
    "residual readouts + level scale fitted on 0.06-0.60": ("calibration_in_band_extended", "level scale"),
    "residual readouts fitted on 0.10-0.50": ("calibration_in_band_continuum_readouts", ""),
    "residual readouts fitted on 0.10-0.50, 0.10 twice": ("calibration_in_band_w01_readouts", ""),
    "residual readouts fitted on 0.06-0.60": ("calibration_in_band_extended_readouts", ""),
    "residual readouts fitted on 0.06-0.60 + level scale fitted on 0.06-0.60": (
        "calibration_in_band_extended_readouts_level_scale", "level scale"),
    "log-size readouts (the five levels)": ("calibration_in_band_size_readouts", ""),
    "log-size readouts + level scale fitted at the five levels": (
        "calibration_in_band_size_readouts_level_scale", "level scale"),
    "log-size readouts + level scale fitted on 0.10-0.50": (
        "calibration_in_band_size_readouts_continuous", "level scale"),
}
#: readouts with their level scales, the sensor errors scored by their own readout (fitted on
#: that system, as the zoo's ``covariance_sensor.pt`` is): the five-level log-size readouts with
#: level scales fitted on three ranges, then the log-size readouts fitted on 0.06-0.60 with level
#: scales fitted on 0.06-0.60: 100 sequences a level and 8 knots (with an outliers readout of more
#: memory or more sequences beside them), 16 and 32 knots, 400 sequences a level with 8 knots, 800
#: with 16, 400 with 16 and the level averaged over 25 steps, and 400 sequences a level with 16
#: knots (the zoo's)
_RIGID = ("nominal", "outliers", "correlated", "bias_walk")
_WIDE = "log-size readouts fitted on 0.06-0.60 + level scale fitted on 0.06-0.60"
_NOT_OUTLIERS = ("nominal", "sensor", "correlated", "bias_walk")
FIVE |= {
    "log-size readouts + level scale fitted on 0.10-0.50, own sensor readout": [
        ("calibration_in_band_size_readouts_continuous", "level scale", _RIGID),
        ("calibration_in_band_sensor_readout", "level scale", ("sensor",))],
    "log-size readouts + level scale fitted on 0.06-0.60, own sensor readout": (
        "calibration_in_band_size_readouts_extended", "level scale"),
    "log-size readouts + level scale fitted on 0.10-0.60, own sensor readout": (
        "calibration_in_band_size_readouts_upper", "level scale"),
    "log-size readouts fitted on 0.06-0.60": ("calibration_in_band_wide_size_readouts", ""),
    "log-size readouts fitted on 0.06-0.60 + level scale fitted on 0.10-0.60": (
        "calibration_in_band_wide_size_readouts_upper", "level scale"),
    _WIDE: ("calibration_in_band_wide_size_readouts", "level scale"),
    f"{_WIDE}, the outliers readout with a GRU of 64": [
        ("calibration_in_band_wide_size_readouts", "level scale", _NOT_OUTLIERS),
        ("calibration_in_band_wide_size_readouts_outliers_memory64", "level scale", ("outliers",))],
    f"{_WIDE}, the outliers readout fitted on three times the sequences": [
        ("calibration_in_band_wide_size_readouts", "level scale", _NOT_OUTLIERS),
        ("calibration_in_band_wide_size_readouts_outliers_sequences3x", "level scale", ("outliers",))],
    f"{_WIDE}, 16 knots": (
        "calibration_in_band_wide_size_readouts_knots16", "level scale"),
    f"{_WIDE}, 32 knots": (
        "calibration_in_band_wide_size_readouts_knots32", "level scale"),
    f"{_WIDE}, 400 sequences a level": (
        "calibration_in_band_wide_size_readouts_heldout400", "level scale"),
    f"{_WIDE}, 800 sequences a level (every sixth step), 16 knots": (
        "calibration_in_band_wide_size_readouts_knots16_heldout800", "level scale"),
    f"{_WIDE}, 400 sequences a level, 16 knots, the level averaged over 25 steps": (
        "calibration_in_band_wide_size_readouts_knots16_tau25", "level scale"),
    f"**{_WIDE}, 400 sequences a level, 16 knots (the zoo's)**": (
        "calibration_in_band_wide_size_readouts_knots16_heldout400", "level scale"),
}
#: the first row that scores the sensor errors with their own readout (it and every row after)
OWN_SENSOR_FROM = "log-size readouts + level scale fitted on 0.10-0.50, own sensor readout"


def _twin(name: str) -> str:
    return name.replace("calibration_in_band", "calibration_in_band_between", 1)


def _between(spec):
    """A variant's ``_between`` twin (``--seed 9000``: the same files' names after
    ``calibration_in_band_between``; the sensor errors are not scored between the levels)."""
    if isinstance(spec, tuple):
        return _twin(spec[0]), spec[1]
    return [(_twin(name), key, cases) for name, key, cases in spec if cases != ("sensor",)]


#: the same variants between the levels
BETWEEN = {label: _between(spec) for label, spec in FIVE.items()}
EXCLUDED = {("outliers", "p 0.5")}


def cells(path: Path, key: str, cases=None) -> dict[tuple[str, str], tuple[float, float]]:
    """(case, "factor sigma") -> (ANEES, share in band) of one result file, under ``key``
    (only ``cases``, when given)."""
    found = json.loads(path.read_text())["cases"]
    anees, share = (f"{key} anees", key) if key else ("anees", "in band")
    return {(case, cell): (r[anees], r[share]) for case, rows in found.items()
            if cases is None or case in cases
            for cell, r in rows.items() if (case, cell) not in EXCLUDED and share in r}


def _variant_cells(spec, results: Path):
    """``(file label, cells)`` of a variant (``(file, key)`` or a list of ``(file, key,
    cases)``), or ``None`` when a file is missing."""
    parts = [(spec[0], spec[1], None)] if isinstance(spec, tuple) else spec
    if not all((results / f"{name}.json").exists() for name, _, _ in parts):
        return None
    got = {}
    for name, key, cases in parts:
        got |= cells(results / f"{name}.json", key, cases)
    return " + ".join(name for name, _, _ in parts), got


def summary(variants: dict, results: Path) -> list[dict]:
    """One row per variant whose result file exists, compared with the first variant's cells."""
    rows, reference = [], None
    for label, spec in variants.items():
        found = _variant_cells(spec, results)
        if found is None or not found[1]:
            continue
        name, got = found
        if reference is None:
            reference = got
        anees = [a for a, _ in got.values()]
        share = [s for _, s in got.values()]
        common = [c for c in got if c in reference]
        rows.append({
            "variant": label, "file": name, "cells": len(got),
            "anees": (min(anees), max(anees)), "in band": (min(share), max(share)),
            "at 90 %": sum(s >= 0.9 for s in share),
            "above reference": sum(got[c][1] > reference[c][1] for c in common),
            "below reference": sum(got[c][1] < reference[c][1] for c in common),
        })
    return rows


def _table(title: str, rows: list[dict]) -> list[str]:
    lines = [f"## {title}", "",
             "| variant | cells | ANEES | in band | cells at 90 % | above / below the residual readouts | file |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(
            f"| {r['variant']} | {r['cells']} | {r['anees'][0]:.3f}-{r['anees'][1]:.3f} | "
            f"{100 * r['in band'][0]:.0f}-{100 * r['in band'][1]:.0f} % | {r['at 90 %']} | "
            f"{r['above reference']} / {r['below reference']} | `{r['file']}` |")
    return lines + [""]


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--results", type=Path, default=RESULTS, help="the folder of result files")
    p.add_argument("--write", type=Path, default=None, help="also write PATH.md and PATH.json")
    args = p.parse_args(argv)
    five, between = summary(FIVE, args.results), summary(BETWEEN, args.results)
    text = "\n".join(
        ["# Every readout variant's calibration, at the five noise levels and between them", "",
         "`python benchmarks/calibration_variants.py --write benchmarks/results/calibration_variants`",
         "", "Fresh sequences of 1000 steps, 1000 per noise level; a cell is a case, a factor "
         "(`R`, `p`) and a noise level; `outliers p 0.5` is left out (one sequence loses its "
         "position). The nominal readout serves the sensor errors in every variant but the "
         f"last {len(FIVE) - list(FIVE).index(OWN_SENSOR_FROM)}, which score them with a "
         "readout of their own, fitted on that system as the zoo's `covariance_sensor.pt` is.", ""]
        + _table("At the paper's five noise levels (seeds 8000 + i)", five)
        + _table("Between them: sigma 0.15, 0.25, 0.35, 0.45 (seeds 9000 + i; nominal, "
                 "outliers, AR(1) noise)", between))
    if args.write is not None:
        args.write.with_suffix(".json").write_text(
            json.dumps({"five levels": five, "between": between}, indent=1))
        args.write.with_suffix(".md").write_text(text)
    print(text)


if __name__ == "__main__":
    sys.exit(main())
