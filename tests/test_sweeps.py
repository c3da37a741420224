"""Sweeps through the real command line: hydra's Optuna sweeper, the joblib and submitit launchers.

Each runs ``python -m manifold_nets.cli.train -m ...`` on ``debug=tiny`` in a subprocess, as
``docs/sweeps.md`` shows. The plugins are the ``sweeps`` extra (in ``dev``); a test whose
plugin is not installed is skipped, naming the extra.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from manifold_nets.cli import common, sweep

ROOT = Path(__file__).resolve().parents[1]


def _needs(module: str) -> None:
    if importlib.util.find_spec(module) is None:
        pytest.skip(f"{module} is not installed: pip install 'manifold_nets[sweeps]'")


def _multirun(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    cmd = [
        sys.executable, "-m", "manifold_nets.cli.train", "-m",
        "experiment=default", "debug=tiny", "train.epochs=1", "eval.plots=false",
        f"dataset.cache_dir={tmp_path / 'data'}", f"hydra.sweep.dir={tmp_path / 'sweep'}",
        *overrides,
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=420, check=False
    )
    assert out.returncode == 0, (out.stdout[-2000:], out.stderr[-4000:])
    return out


def _jobs(tmp_path: Path) -> list[Path]:
    return sorted(p.parent.parent for p in (tmp_path / "sweep").glob("*/results/metrics.json"))


def test_an_optuna_search_of_two_trials(tmp_path):
    _needs("hydra_plugins.hydra_optuna_sweeper")
    _multirun(
        tmp_path, "hydra/sweeper=optuna", "hydra.sweeper.n_trials=2",
        "hydra.sweeper.sampler.seed=0", "train.lr=interval(1e-4,1e-2)",
    )  # fmt: skip
    results = OmegaConf.load(tmp_path / "sweep" / "optimization_results.yaml")
    assert results.name == "optuna" and math.isfinite(results.best_value)
    assert 1e-4 <= results.best_params["train.lr"] <= 1e-2
    assert len(_jobs(tmp_path)) == 2
    # the best value is the best of the trials' objectives (best_val_loss by default)
    losses = [OmegaConf.load(j / "results" / "metrics.json").best_val_loss for j in _jobs(tmp_path)]
    assert results.best_value == pytest.approx(min(losses))


def test_a_local_parallel_sweep_with_the_joblib_launcher(tmp_path):
    _needs("hydra_plugins.hydra_joblib_launcher")
    out = _multirun(tmp_path, "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "seed=0,1")
    assert "Joblib.Parallel(n_jobs=2" in out.stdout + out.stderr
    assert len(_jobs(tmp_path)) == 2
    # both jobs needed the same datasets: each was generated once (the cache's file lock)
    logs = "".join((j / "train.log").read_text() for j in _jobs(tmp_path))
    assert logs.count("generated ") == 2  # the training set and the inference set, once each
    assert sweep.main([str(tmp_path / "sweep")]) == 0
    assert (tmp_path / "sweep" / "sweep_summary.md").is_file()  # mean and std over the seeds


def test_a_slurm_sweep_through_submitit_on_its_local_executor(tmp_path):
    _needs("hydra_plugins.hydra_submitit_launcher")
    if sys.platform == "win32":
        pytest.skip("submitit runs on POSIX systems only")
    _multirun(tmp_path, "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=5", "seed=0,1")
    assert len(_jobs(tmp_path)) == 2
    assert list((tmp_path / "sweep" / ".submitit").iterdir())  # submitit's job folders
    assert sweep.main([str(tmp_path / "sweep")]) == 0


def test_a_launcher_whose_plugin_is_missing_names_the_extra(tmp_path):
    """hydra's own error ("Could not find 'hydra/launcher/joblib'") names no package: the
    command stops first, naming the plugin and the extra, and makes no folder."""
    hide = (
        "import importlib.util as u, sys\n"
        "find = u.find_spec\n"
        "u.find_spec = lambda name, *a: None if name.startswith('hydra_plugins') else find(name, *a)\n"
        "sys.argv = ['mn-train', '-m', 'hydra/launcher=joblib', 'experiment=default', 'seed=0,1']\n"
        "from manifold_nets.cli.train import main\n"
        "main()\n"
    )  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", hide], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=120, check=False)  # fmt: skip
    assert out.returncode == 1, out.stderr
    assert out.stderr.strip() == (
        "error: hydra/launcher=joblib needs hydra's plugin hydra-joblib-launcher, which is not "
        "installed; it comes with the `sweeps` extra: pip install 'manifold_nets[sweeps]' "
        "(docs/sweeps.md)."
    )
    assert list(tmp_path.iterdir()) == []


def test_the_plugin_check_reads_every_way_of_naming_a_plugin(monkeypatch):
    monkeypatch.setattr(common.importlib.util, "find_spec", lambda name: None)
    for arg in ("hydra/launcher=submitit_slurm", "hydra/sweeper=optuna", "+hydra/launcher=joblib"):
        with pytest.raises(SystemExit, match="the `sweeps` extra"):
            common.check_plugins(["-m", arg, "experiment=default"])
    common.check_plugins(["-m", "hydra/launcher=basic", "seed=0,1"])  # hydra's own: no plugin


def test_the_sweep_command_names_every_file_it_wrote(tmp_path, capsys):
    for seed in (0, 1):
        res = tmp_path / str(seed) / "results"
        res.mkdir(parents=True)
        table = [{"sigma": 0.1, "method": "learned", "R est": 0.1 + seed, "sequences": 2}]
        (res / "metrics.json").write_text(json.dumps({"seed": seed, "table": table}))
    assert sweep.main([str(tmp_path)]) == 0
    wrote = capsys.readouterr().out.splitlines()[-1]
    names = ("sweep.csv", "sweep.md", "sweep_summary.csv", "sweep_summary.md")
    assert wrote == "wrote " + ", ".join(str(tmp_path / n) for n in names)
    assert all((tmp_path / n).is_file() for n in names)
