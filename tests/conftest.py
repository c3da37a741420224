"""Shared pytest setup for the whole suite.

* hypothesis profiles: ``ci`` (the default: derandomized, so a CI run is reproducible, no
  per-example deadline, which a loaded 2-core runner would trip, no example database on disk)
  and ``dev`` (random examples, more of them) for hunting bugs locally:
  ``pytest --hypothesis-profile=dev`` or ``HYPOTHESIS_PROFILE=dev pytest``.
* One torch thread per process: tensors in tests are small, and ``pytest -n 2`` on two cores
  would otherwise oversubscribe them (each worker starting one thread per core).
"""

from __future__ import annotations

import os

import torch
from hypothesis import settings

settings.register_profile("ci", derandomize=True, deadline=None, database=None)
settings.register_profile("dev", deadline=None, max_examples=300)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

torch.set_num_threads(1)
