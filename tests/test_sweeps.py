"""Sweeps through the real command line: hydra's Optuna sweeper, the joblib and submitit launchers.

Each runs ``python -m manifold_nets.cli.train -m ...`` on ``debug=tiny`` in a subprocess, as
``docs/sweeps.md`` shows. The plugins are the ``sweeps`` extra (in ``dev``); a test whose
plugin is not installed is skipped, naming the extra.
"""

from __future__ import annotations

import importlib.util
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from manifold_nets.cli import sweep

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
