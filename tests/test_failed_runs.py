"""What a failed command leaves: hydra makes the run folder (``.hydra/``, the log) before the run
can check anything. Refused before any work, the run removes it (``tests/test_configs.py``,
``tests/test_own_project.py``); failed after writing a file of its own, it keeps it and says
where."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: one observer of the zoo's BROAD ensemble (a run folder)
MEMBER = ROOT / "examples" / "broad" / "zoo" / "attitude" / "members" / "seed3"


def test_a_run_that_failed_after_writing_keeps_its_folder_and_says_where(tmp_path):
    # the AHRS's observer on the rigid body: refused when the observer is built, after the run
    # wrote its config.yaml
    out_dir = tmp_path / "outputs" / "run"
    cmd = [sys.executable, "-m", "manifold_nets.cli.evaluate", "experiment=default", "debug=tiny",
           f"eval.checkpoint={MEMBER}", f"hydra.run.dir={out_dir}"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert out.returncode == 1 and "does not have; its factors" in out.stderr
    assert f"the run failed; its folder (what it wrote, and hydra's files): {out_dir}" in (
        out.stdout + out.stderr
    )
    assert sorted(p.name for p in out_dir.iterdir()) == [".hydra", "config.yaml", "evaluate.log"]
