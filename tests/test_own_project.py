"""A user's own project outside the repository: docs/your_own_project.md, run as a user runs it.

The page's folder (a group of one's own, a system on it, their tests, the configs, a
``pyproject.toml`` declaring the system, a deployment script) is written into ``tmp_path`` from
the page's own blocks, so the page cannot drift from working files. A throwaway virtual
environment that sees the development one gets the console scripts pip would write (``mn-train``,
..., ``pip``); the page's commands (its sections 5, 7 and 9: ``pip install -e .``, the
user's tests, train, evaluate, a sweep over two seeds and its tables, ``mn-apply``, ``python
deploy.py``) then runs from the folder with that environment first on ``PATH``, no
``PYTHONPATH`` and ``debug=tiny``: ``docs/examples/own_project.py``, the script that runs the
same commands from a freshly built wheel.
"""

from __future__ import annotations

import csv
import importlib.metadata
import importlib.util
import site
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from manifold_nets.builders import build_system

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("own_project", ROOT / "docs/examples/own_project.py")
own_project = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(own_project)


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _script(bin_dir: Path, name: str, module: str, attr: str) -> None:
    """A console script as pip writes it, for this environment's interpreter."""
    path = bin_dir / name
    path.write_text(
        f"#!{bin_dir / 'python'}\nimport sys\nfrom {module} import {attr}\n"
        f"if __name__ == '__main__':\n    sys.exit({attr}())\n"
    )
    path.chmod(0o755)


def _user_environment(where: Path) -> dict[str, str]:
    """A virtual environment in ``where`` that sees the development environment's packages
    (a ``.pth`` file), with the distribution's console scripts and ``pip``; pip installs into
    it, offline, building with the development environment's setuptools."""
    venv = where / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", venv], check=True)
    (purelib,) = (venv / "lib").glob("python*/site-packages")
    dev_sites = [p for p in site.getsitepackages() if Path(p).is_dir()]
    (purelib / "development.pth").write_text(
        "".join(f"import site; site.addsitedir({p!r})\n" for p in dev_sites)
    )
    scripts = [e for e in importlib.metadata.distribution("manifold_nets").entry_points
               if e.group == "console_scripts"]  # fmt: skip
    for e in scripts:
        _script(venv / "bin", e.name, e.module, e.attr)
    _script(venv / "bin", "pip", "pip._internal.cli.main", "main")
    env = own_project.user_env(venv / "bin")
    env.update(PIP_NO_INDEX="1", PIP_NO_BUILD_ISOLATION="0", PIP_DISABLE_PIP_VERSION_CHECK="1")
    return env


@pytest.fixture(scope="module")
def walked(tmp_path_factory):
    """The page's commands, run once as one script: ``(project folder, environment, its output)``."""
    where = tmp_path_factory.mktemp("user")
    assert ROOT not in where.parents  # outside the repository, as a user's folder is
    project = own_project.write_project(where)
    env = _user_environment(where)
    done = own_project.run_walk(own_project.walk(tiny=True), where, env, timeout=600)
    assert done.returncode == 0, done.stdout[-6000:]
    return project, env, done.stdout


def test_the_page_is_a_whole_package():
    where = Path("zoomtable")
    files = {Path(p) for p, _ in own_project.FILE_BLOCK.findall(own_project.PAGE.read_text())}
    assert files == {where / "pyproject.toml", where / "deploy.py",
                     where / "src/zoomtable/__init__.py", where / "src/zoomtable/group.py",
                     where / "src/zoomtable/system.py", where / "tests/test_zoomtable.py",
                     where / "conf/system/zoomtable.yaml",
                     where / "conf/experiment/zoomtable.yaml"}  # fmt: skip
    script = own_project.walk(tiny=True)
    for command in ("pip install -e .", "python -m pytest", "mn-train -m", "mn-evaluate",
                    "mn-sweep", "mn-apply", "python deploy.py"):  # fmt: skip
        assert command in script, command
    assert "PYTHONPATH" not in script and "python -m manifold_nets" not in script


def test_the_users_tests_train_evaluate_and_sweep(walked):
    project, _, out = walked
    assert "2 passed" in out  # the axiom suite on RxSO(2), check_system on the system
    runs = sorted((project / "outputs" / "zoomtable").iterdir())
    assert len(runs) == 2  # the training, then the evaluation
    run, evaluation = runs
    res = run / "results"
    for name in ("table.csv", "table.md", "metrics.json", "curves.json", "errors_sigma0.1.png"):
        assert (res / name).is_file(), name
    (row,) = _rows(res / "table.csv")
    assert row["sigma"] == "0.1" and row["method"] == "learned" and row["steps"] == "16"
    assert float(row["membership max"]) < 1e-12  # the estimate stayed on RxSO(2)
    rows = _rows(evaluation / "results" / "table.csv")
    assert [r["sigma"] for r in rows] == ["0.1", "0.3"]
    assert rows[0]["x est"] == row["x est"]  # the same weights, the same inference set

    (sweep,) = (project / "multirun" / "zoomtable").iterdir()
    assert [r["seed"] for r in _rows(sweep / "sweep.csv")] == ["0", "1"]
    (summary,) = _rows(sweep / "sweep_summary.csv")  # one sigma: mean and std over 2 seeds
    assert summary["seeds"] == "2" and summary["method"] == "learned"
    assert f"{sweep.relative_to(project) / 'sweep_summary.csv'}" in out  # mn-sweep names it


def test_apply_and_export_find_the_system_by_its_entry_point(walked):
    project, _, out = walked
    with np.load(project / "estimates.npz") as f:
        estimates = f["estimates"]
    assert estimates.shape == (4, 17, 2, 2)  # (N, T+1, 2, 2) from the identity
    a, b, c, d = (estimates[..., i, j] for i in (0, 1) for j in (0, 1))
    assert np.abs(a - d).max() < 1e-12 and np.abs(b + c).max() < 1e-12  # on RxSO(2)
    assert (project / "step.pt2").is_file() and (project / "step.onnx").is_file()
    deploy = out[out.index("python deploy.py") :].splitlines()[1:]  # what it printed
    assert deploy[0].startswith("tensor([[") and len(deploy) == 2, deploy  # the estimate alone


def test_help_lists_the_users_configs_next_to_the_librarys(walked):
    project, env, _ = walked
    text = subprocess.run(["mn-train", "--config-dir", "conf", "--help"], cwd=project, env=env,
                          capture_output=True, text=True, check=True).stdout  # fmt: skip
    groups = dict(line.split(": ", 1) for line in text.splitlines() if ": " in line)
    assert {"zoomtable", "rigid_body"} <= set(groups["system"].split(", "))
    assert {"zoomtable", "default"} <= set(groups["experiment"].split(", "))


def test_a_run_refused_before_any_work_leaves_no_folder(walked):
    project, env, _ = walked
    before = set((project / "outputs" / "zoomtable").iterdir())
    cmd = ["mn-train", "--config-dir", "conf", "experiment=zoomtable", "debug=tiny",
           "train.grad_clip=-1"]  # fmt: skip
    out = subprocess.run(cmd, cwd=project, env=env, capture_output=True, text=True, check=False)
    assert out.returncode == 1 and "train.grad_clip must be > 0" in out.stderr
    assert set((project / "outputs" / "zoomtable").iterdir()) == before


def test_a_system_that_cannot_be_imported_names_the_fix():
    with pytest.raises(ValueError, match="turntable.Turntable.*could not be imported.*PYTHONPATH"):
        build_system({"_target_": "turntable.Turntable"})
