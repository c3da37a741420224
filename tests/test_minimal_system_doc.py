"""The tutorial "add your own system" cannot rot: its complete code runs, and every Python block
of ``docs/add_your_own_system.md`` is a verbatim excerpt of ``docs/examples/minimal_system.py``."""

from __future__ import annotations

import re
import runpy
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "docs" / "examples" / "minimal_system.py"
TUTORIAL = ROOT / "docs" / "add_your_own_system.md"


def test_the_script_runs_as_a_program(capsys):
    runpy.run_path(str(SCRIPT), run_name="__main__")
    out = capsys.readouterr().out
    assert "Turntable works" in out and "splits {'train': 80, 'val': 10, 'test': 10}" in out


def test_every_python_block_of_the_tutorial_is_in_the_script():
    code = SCRIPT.read_text()
    blocks = re.findall(r"```python\n(.*?)```", TUTORIAL.read_text(), flags=re.DOTALL)
    assert len(blocks) >= 4
    for block in blocks:
        assert block.rstrip("\n") in code, f"tutorial block not in {SCRIPT.name}:\n{block}"


def test_the_turntable_is_exact_and_on_its_group():
    Turntable = runpy.run_path(str(SCRIPT), run_name="turntable_doc")["Turntable"]
    system = Turntable(dt=0.2)
    data = system.simulate(5, 30, 0.0, torch.Generator().manual_seed(0))
    system.group.check_member(data.states, atol=1e-12)
    theta = torch.atan2(data.states[..., 1, 0], data.states[..., 0, 0])
    turn = torch.remainder(theta[:, 1:] - theta[:, :-1] + torch.pi, 2 * torch.pi) - torch.pi
    # the rate reading (noise-free) is the turn of the step divided by dt
    torch.testing.assert_close(turn / 0.2, data.measurements[..., 2], rtol=0, atol=1e-12)
