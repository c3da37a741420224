"""The machine a benchmark ran on, in one line for its results file (imported by the scripts
beside this file)."""

from __future__ import annotations

import os
import platform
from pathlib import Path


def describe() -> str:
    """``<CPU model>, <n> logical cores, <OS> <release>``."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} logical cores, {platform.system()} {platform.release()}"
