"""A user's own project outside the repository: docs/your_own_project.md, run as a user runs it.

The folder (a system on SO(2) in one Python file, its ``conf/system`` and ``conf/experiment``
files) is written into ``tmp_path`` from the page's own blocks, so the page cannot drift from
working files; then the installed commands train, evaluate and sweep it from that folder with
``--config-dir conf`` and the library's ``debug=tiny``, as subprocesses that see the installed
distribution only (no ``PYTHONPATH`` into the checkout).
"""

from __future__ import annotations

import csv
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from manifold_nets.builders import build_system

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "your_own_project.md"
#: A file of the page: its path in bold, a blank line, then its block.
FILE_BLOCK = re.compile(r"\*\*`(my_turntable/[^`]+)`\*\*\n\n```(?:python|yaml)\n(.*?)```", re.S)


def _write_project(where: Path) -> Path:
    files = FILE_BLOCK.findall(DOC.read_text())
    assert sorted(path for path, _ in files) == [
        "my_turntable/conf/experiment/turntable.yaml",
        "my_turntable/conf/system/turntable.yaml",
        "my_turntable/turntable.py",
    ]
    for path, text in files:
        (where / path).parent.mkdir(parents=True, exist_ok=True)
        (where / path).write_text(text)
    return where / "my_turntable"


def _command(cwd: Path, module: str, *args: str) -> str:
    """``python -m <module> <args>`` in ``cwd``; its stdout, or a failure showing stderr."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run(
        [sys.executable, "-m", module, *args],
        cwd=cwd, env=env, capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert out.returncode == 0, f"{module} {args}:\n{out.stderr[-3000:]}"
    return out.stdout


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    where = tmp_path_factory.mktemp("user")
    assert ROOT not in where.parents  # outside the repository, as a user's folder is
    return _write_project(where)


def test_help_lists_the_users_configs_next_to_the_librarys(project):
    text = _command(project, "manifold_nets.cli.train", "--config-dir", "conf", "--help")
    groups = dict(line.split(": ", 1) for line in text.splitlines() if ": " in line)
    assert {"turntable", "rigid_body"} <= set(groups["system"].split(", "))
    assert {"turntable", "default"} <= set(groups["experiment"].split(", "))


def test_train_evaluate_and_sweep_from_the_users_folder(project):
    tiny = ("--config-dir", "conf", "experiment=turntable", "debug=tiny")
    _command(project, "manifold_nets.cli.train", *tiny)
    (run,) = (project / "outputs" / "turntable").iterdir()
    res = run / "results"
    for name in ("table.csv", "table.md", "metrics.json", "curves.json", "errors_sigma0.1.png"):
        assert (res / name).is_file(), name
    assert (run / "checkpoints" / "best.pt").is_file()
    (row,) = _rows(res / "table.csv")
    assert row["sigma"] == "0.1" and row["method"] == "turntable" and row["steps"] == "16"
    assert float(row["membership max"]) < 1e-12  # the estimate stayed on SO(2)
    assert list((project / "data").glob("turntable_*.npz"))  # the cache, in the user's folder

    # the trained run evaluated again, at two noise levels, into a run folder of its own
    _command(
        project, "manifold_nets.cli.evaluate", *tiny,
        f"eval.checkpoint=outputs/turntable/{run.name}", "eval.sigmas=[0.1,0.3]",
    )  # fmt: skip
    (evaluation,) = {p for p in (project / "outputs" / "turntable").iterdir()} - {run}
    rows = _rows(evaluation / "results" / "table.csv")
    assert [r["sigma"] for r in rows] == ["0.1", "0.3"]
    assert rows[0]["x est"] == row["x est"]  # the same weights, the same inference set

    # a 2-job sweep over seeds, then its table
    _command(project, "manifold_nets.cli.train", "-m", *tiny, "seed=0,1")
    (sweep,) = (project / "multirun" / "turntable").iterdir()
    for job in ("0", "1"):
        assert (sweep / job / "results" / "metrics.json").is_file(), job
    _command(project, "manifold_nets.cli.sweep", str(sweep))
    assert [r["seed"] for r in _rows(sweep / "sweep.csv")] == ["0", "1"]
    assert len(_rows(sweep / "sweep_summary.csv")) == 1  # one sigma, mean and std over 2 seeds


def test_a_system_that_cannot_be_imported_names_the_fix():
    with pytest.raises(ValueError, match="turntable.Turntable.*could not be imported.*PYTHONPATH"):
        build_system({"_target_": "turntable.Turntable"})
