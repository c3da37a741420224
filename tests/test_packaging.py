"""The distribution's shape: pyproject.toml lists every package, under names that cannot collide.

The repository's ``examples/`` and ``configs/`` folders are installed as ``manifold_nets_examples``
and ``manifold_nets_configs`` (``package-dir``); ``packages`` is listed by hand, so a new package
folder or config group left out of it would silently be missing from the wheel. Read from the
files, nothing is built (the user's view: ``tests/test_own_project.py`` runs the workflow of
``docs/your_own_project.md`` outside the checkout; ``docs/examples/own_project.py`` runs it from a
freshly built wheel in a new virtual environment).
"""

from __future__ import annotations

import importlib
import importlib.resources
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
SETUPTOOLS = PYPROJECT["tool"]["setuptools"]
#: import name -> folder in the repository
PACKAGE_DIR = {"groups": "groups", "manifold_nets": "manifold_nets",
               "manifold_nets_examples": "examples", "manifold_nets_configs": "configs"}  # fmt: skip


def _folder(package: str) -> Path:
    top, _, rest = package.partition(".")
    return ROOT / PACKAGE_DIR[top] / rest.replace(".", "/")


def _expected_packages() -> set[str]:
    out = set()
    for name, folder in PACKAGE_DIR.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder)
            out.add(".".join((name, *rel.parts)))
    for group in (ROOT / "configs").iterdir():
        if group.is_dir() and list(group.glob("*.yaml")):
            out.add(f"manifold_nets_configs.{group.name}")
    return out


def test_the_folders_are_mapped_to_their_import_names():
    mapped = {k: v for k, v in SETUPTOOLS["package-dir"].items() if k}
    assert mapped == {"manifold_nets_examples": "examples", "manifold_nets_configs": "configs"}
    assert SETUPTOOLS["package-dir"][""] == "."


def test_the_examples_folder_refuses_its_folder_name():
    """``python -m examples.broad.train`` from a checkout would define every class a second time
    under ``examples.*`` and record that name in its run folder, which no loader accepts: the
    import is refused naming the command that works."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", "import examples.broad.simulator"], cwd=ROOT,
                         capture_output=True, text=True)
    assert run.returncode != 0
    assert "python -m manifold_nets_examples.broad.train" in run.stderr, run.stderr[-2000:]
    importlib.import_module("manifold_nets_examples.broad.simulator")  # the installed name works


def test_every_package_and_config_group_is_listed():
    listed = set(SETUPTOOLS["packages"])
    assert listed == _expected_packages()
    assert {p.split(".")[0] for p in listed} == set(PACKAGE_DIR)  # no bare `examples`, `configs`
    for package in listed:
        assert _folder(package).is_dir(), package


def test_the_configs_are_package_data():
    patterns = SETUPTOOLS["package-data"]["manifold_nets_configs"]
    assert "*.yaml" in patterns and "**/*.yaml" in patterns
    configs = importlib.resources.files("manifold_nets_configs")
    assert configs.joinpath("train.yaml").is_file()
    assert configs.joinpath("debug", "tiny.yaml").is_file()


def test_every_zoo_file_is_package_data():
    """A zoo entry's card, config, checkpoint and covariance readout all go into the wheel (the
    readouts once did not: ``load_readout(zoo_path(...) / "covariance.pt")`` failed installed)."""
    examples = ROOT / "examples"
    shipped = {p for pattern in SETUPTOOLS["package-data"]["manifold_nets_examples"]
               for p in examples.glob(pattern)}
    zoo = {p for p in examples.glob("*/zoo/**/*") if p.is_file() and "__pycache__" not in p.parts}
    assert zoo and sorted(map(str, zoo - shipped)) == []
    assert any(p.name == "covariance.pt" for p in shipped)


def test_the_commands_load_the_installed_configs_and_are_console_scripts():
    from manifold_nets.cli import CONFIG_PATH

    assert CONFIG_PATH == "pkg://manifold_nets_configs"
    scripts = PYPROJECT["project"]["scripts"]
    shared = {"__init__", "common", "tasks", "learned_extras"}  # what the commands share, not commands
    commands = [p.stem for p in (ROOT / "manifold_nets" / "cli").glob("*.py") if p.stem not in shared]
    assert set(scripts) == {f"mn-{c}" for c in commands}  # one console script per command
    for name, target in scripts.items():
        module, _, attr = target.partition(":")
        assert module == f"manifold_nets.cli.{name.removeprefix('mn-')}" and attr == "main"
        assert callable(getattr(importlib.import_module(module), attr)), target


def test_torch_is_a_range_not_a_pin():
    """An exact pin breaks every environment that has another torch."""
    (torch,) = [d for d in PYPROJECT["project"]["dependencies"] if d.startswith("torch")]
    assert "==" not in torch and ">=" in torch and "<" in torch, torch


def test_the_extras_a_users_project_installs_bring_what_it_uses():
    """docs/your_own_project.md installs the wheel with ``[testing,export]``: hypothesis for
    ``groups.testing`` (the axiom suite of a group of one's own), onnx, onnxscript and
    onnxruntime for ``export_onnx``."""
    page = (ROOT / "docs" / "your_own_project.md").read_text()
    assert "manifold_nets-0.1.0-py3-none-any.whl[testing,export]" in page
    assert PYPROJECT["project"]["version"] == "0.1.0"  # the wheel's name the page gives
    extras = PYPROJECT["project"]["optional-dependencies"]
    names = {k: {d.split(">")[0].split("=")[0] for d in v} for k, v in extras.items()}
    assert names["testing"] == {"hypothesis"}
    assert names["export"] == {"onnx", "onnxscript", "onnxruntime"}
