"""Shared pytest setup for the whole suite.

* hypothesis profiles: ``ci`` (the default: derandomized, so a CI run is reproducible, no
  per-example deadline, which a loaded 2-core runner would trip, no example database on disk)
  and ``dev`` (random examples, more of them) for hunting bugs locally:
  ``pytest --hypothesis-profile=dev`` or ``HYPOTHESIS_PROFILE=dev pytest``.
* One torch thread per process: tensors in tests are small, and ``pytest -n 2`` on two cores
  would otherwise oversubscribe them (each worker starting one thread per core).
* ``load_script``: imports a script of the checkout that is not a package module (a benchmark)
  by its path from the repository root.
* ``--device`` (or ``MN_TEST_DEVICE``): where the device-agnostic tests put their tensors
  (the fixture ``device``; default ``cpu``, which CI uses). ``pytest --device cuda
  tests/test_group_axioms.py tests/test_device.py`` runs the group axioms, the observer, training,
  resume and evaluation on a GPU against the CPU (benchmarks/gpu/run.sh).
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest
import torch
from hypothesis import settings

settings.register_profile("ci", derandomize=True, deadline=None, database=None)
settings.register_profile("dev", deadline=None, max_examples=300)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

torch.set_num_threads(1)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--device", default=os.environ.get("MN_TEST_DEVICE", "cpu"),
        help="torch device of the device-agnostic tests (fixture `device`): cpu (default), "
        "cuda, cuda:1, ...; also MN_TEST_DEVICE",
    )


def pytest_configure(config: pytest.Config) -> None:
    name = config.getoption("--device")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError, ValueError):
        raise pytest.UsageError(f"--device {name!r} is not a torch device (cpu, cuda, cuda:1)")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise pytest.UsageError(f"--device {name!r}, but CUDA is not available here; use cpu")


@pytest.fixture(scope="session")
def device(request: pytest.FixtureRequest) -> torch.device:
    """The device the device-agnostic tests run on (``--device``; default cpu)."""
    return torch.empty(0, device=request.config.getoption("--device")).device


@pytest.fixture(scope="session")
def load_script():
    """``load_script("benchmarks/x.py")``: the script imported as a module of its own name."""
    root = Path(__file__).resolve().parents[1]

    def load(relative: str):
        path = root / relative
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
