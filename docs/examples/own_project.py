"""docs/your_own_project.md, run as a user runs it: the page's folder and its commands.

::

    python docs/examples/own_project.py OUT           # from a fresh wheel, at the page's sizes
    python docs/examples/own_project.py OUT --tiny    # the same with debug=tiny (seconds a run)

It builds the wheel from a copy of this checkout's files, makes a virtual environment
``OUT/venv`` (``python -m venv``), installs ``torch==2.13.0`` there, then the wheel with its
``testing`` and ``export`` extras and pytest (section 1 of the page), writes the page's folder
into ``OUT/zoomtable`` (every file block, verbatim) and runs the page's commands as one
script from ``OUT``, with that environment first on ``PATH`` and no ``PYTHONPATH``: the bash
blocks of sections 5 (install the package, its tests), 7 (train, evaluate, a sweep over two
seeds and its tables, ``mn-apply``) and 9 (``python deploy.py``: load, ``torch.export``, ONNX).
Every command is echoed with the seconds since the script started.
``docs/examples/own_project_from_wheel.log`` is its output.

``tests/test_own_project.py`` runs the same script (:func:`write_project`, :func:`walk`,
:func:`run_walk`) on debug=tiny in an environment that sees the development one.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "your_own_project.md"
#: A file of the page: its path in bold, a blank line, then its block.
FILE_BLOCK = re.compile(r"\*\*`(zoomtable/[^`]+)`\*\*\n\n```(?:python|yaml|toml)\n(.*?)```", re.S)
#: Echo each command with the seconds since the script started.
_ECHO = "PS4='+ [${SECONDS} s] '; set -x\n"
#: pip's lines about the package indexes this machine is set up with, left out of the output.
_PIP_INDEX = re.compile(r"(Looking in indexes|Looking in links|WARNING: Location)\b")
#: The sections whose bash blocks are the walk, in order.
WALK_SECTIONS = ("## 5.", "## 7.", "## 9.")


def write_project(where: Path) -> Path:
    """Writes every file block of the page under ``where``; returns ``where / "zoomtable"``."""
    for path, text in FILE_BLOCK.findall(PAGE.read_text()):
        (where / path).parent.mkdir(parents=True, exist_ok=True)
        (where / path).write_text(text)
    return where / "zoomtable"


def walk(tiny: bool = False) -> str:
    """The bash blocks of the page's sections 5, 7 and 9, one script run from the folder
    above ``zoomtable/``; ``tiny`` adds ``debug=tiny`` to every ``mn-train`` and
    ``mn-evaluate``."""
    page = PAGE.read_text()
    blocks = []
    for heading in WALK_SECTIONS:
        start = page.index("\n" + heading)
        end = page.find("\n## ", start + 1)
        blocks += re.findall(r"```bash\n(.*?)```", page[start : end if end > 0 else None], re.S)
    lines = "".join(blocks).splitlines()
    if tiny:
        lines = [
            line.split(" #")[0] + " debug=tiny" if line.startswith(("mn-train", "mn-evaluate"))
            else line
            for line in lines
        ]  # fmt: skip
    return "\n".join(lines) + "\n"


def user_env(bin_dir: Path) -> dict[str, str]:
    """The environment of a user's shell: ``bin_dir`` first on ``PATH``, no ``PYTHONPATH``."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = str(bin_dir.parent)
    return env


def run_walk(script: str, cwd: Path, env: dict[str, str], timeout: float):
    """``script`` in ``bash -euo pipefail`` in ``cwd``, every command echoed with the seconds
    since the start (``set -x``); stops at the first that fails. ``stdout`` holds everything it
    printed (``stderr`` too)."""
    return subprocess.run(
        ["bash", "-euo", "pipefail", "-c", _ECHO + script], cwd=cwd, env=env, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True, timeout=timeout, check=False,
    )  # fmt: skip


def _checkout_copy(dest: Path) -> None:
    """The checkout's tracked and untracked, not ignored files (what a clone would build)."""
    files = subprocess.run(
        ["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, capture_output=True,
        text=True, check=True,
    ).stdout.splitlines()  # fmt: skip
    for name in files:
        if (ROOT / name).is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, dest / name)


def _step(what: str, cmd: list) -> None:
    """Runs ``cmd``, printing it and its wall time; its output only when it fails."""
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    print(f"## {what}: {time.perf_counter() - t0:.0f} s\n$ {' '.join(map(str, cmd))}", flush=True)
    if done.returncode:
        sys.exit(f"{done.stdout}{done.stderr}\nexit status {done.returncode}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="an empty folder for the wheel, venv and project")
    ap.add_argument("--tiny", action="store_true", help="debug=tiny on every run")
    args = ap.parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    if any(out.iterdir()):
        ap.error(f"{out} is not empty")
    _checkout_copy(out / "checkout")
    _step("the wheel", [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w",
                        out / "dist", out / "checkout"])  # fmt: skip
    (wheel,) = (out / "dist").glob("manifold_nets-*.whl")
    _step("a virtual environment", [sys.executable, "-m", "venv", out / "venv"])
    pip = [out / "venv" / "bin" / "pip", "install", "-q"]
    _step("torch", [*pip, "torch==2.13.0"])
    _step("the wheel, its extras, pytest", [*pip, f"{wheel}[testing,export]", "pytest"])
    write_project(out)
    script = walk(args.tiny)
    print(f"## the page's commands, run from {out}:\n{script}", flush=True)
    t0 = time.perf_counter()
    done = run_walk(script, out, user_env(out / "venv" / "bin"), timeout=3600)
    print("".join(line for line in done.stdout.splitlines(True) if not _PIP_INDEX.match(line)))
    print(f"## exit status {done.returncode}, {time.perf_counter() - t0:.0f} s")
    return done.returncode


if __name__ == "__main__":
    raise SystemExit(main())
