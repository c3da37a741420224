"""``broad.apply`` on an hour-long recording: wall and CPU time, peak memory.

Run by hand from the repository root (not by CI), with BROAD's ``.mat`` files where the split
file says (``configs/broad/trials.yaml``)::

    python benchmarks/bench_broad_apply_hour.py --write     # writes results/broad_apply_hour.md
    python benchmarks/bench_broad_apply_hour.py --observer zoo:broad/attitude_6d \
        --write benchmarks/results/broad_apply_hour_6d.md      # the 6-D entry

The recording is BROAD's 23 trials joined end to end (their IMU readings only: no reference,
so nothing is scored) and cut to 999,992 samples, 58.3 minutes at 285.7 Hz, just under the
command's ``MAX_SAMPLES``; it is written to a temporary folder, then
``python -m manifold_nets_examples.broad.apply OBSERVER <file> --out q.npy`` (``--observer``,
default ``zoo:broad/attitude``) runs in a child process (one thread, as the command's default),
timed with ``resource.getrusage``.
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.io

from manifold_nets.atomic import write_text_atomic
from manifold_nets_examples.broad.data import read_trials, split_trials

SAMPLES = 999_992  # a multiple of the observer's 8 samples, under MAX_SAMPLES = 1,000,000
HERE = Path(__file__).parent
DEFAULT_OBSERVER, DEFAULT_OUT = "zoo:broad/attitude", str(HERE / "results" / "broad_apply_hour.md")


def recording(path: Path) -> float:
    """Writes the recording; returns its sampling rate."""
    data_dir, split = split_trials(None)
    trials = read_trials(data_dir, split["train"] + split["val"] + split["test"])
    arrays = {k: np.concatenate([getattr(t, k) for t in trials])[:SAMPLES]
              for k in ("gyr", "acc", "mag")}  # fmt: skip
    assert len(arrays["gyr"]) == SAMPLES, "the 23 trials hold fewer samples than an hour"
    scipy.io.savemat(path, {f"imu_{k}": v for k, v in arrays.items()} | {
        "sampling_rate": trials[0].rate})
    return trials[0].rate


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--observer", default=DEFAULT_OBSERVER, help="what broad.apply runs")
    p.add_argument("--write", nargs="?", const=DEFAULT_OUT, default=None, metavar="PATH",
                   help="write the table (default path: benchmarks/results/broad_apply_hour.md)")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        rate = recording(Path(tmp) / "hour.mat")
        cmd = [sys.executable, "-m", "manifold_nets_examples.broad.apply", a.observer,
               str(Path(tmp) / "hour.mat"), "--out", str(Path(tmp) / "q.npy")]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        wall = time.perf_counter() - t0
        q = np.load(Path(tmp) / "q.npy")
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    minutes = SAMPLES / rate / 60
    with open("/proc/loadavg") as f:
        load = f.read().split()[:3]
    text = "\n".join([
        "# `broad.apply` on an hour-long recording", "",
        "`python benchmarks/bench_broad_apply_hour.py"
        + (f" --observer {a.observer}" if a.observer != DEFAULT_OBSERVER else "")
        + (" --write" if a.write == DEFAULT_OUT else f" --write {a.write}")
        + f"`: BROAD's 23 trials joined end to end, {SAMPLES:,} samples ({minutes:.1f} min at "
        f"{rate:.3f} Hz), `{a.observer}`, one thread; load average {' '.join(load)} (2 cores).",
        "",
        "| wall | CPU (user + system) | real-time factor | peak memory | quaternions |",
        "|---|---|---|---|---|",
        f"| {wall:.1f} s | {use.ru_utime + use.ru_stime:.1f} s | {minutes * 60 / wall:.0f}x | "
        f"{use.ru_maxrss / 2**20:.2f} GiB | {len(q):,}, all finite: {bool(np.isfinite(q).all())} |",
        "", "Data: BROAD (D. Laidig, M. Caruso, A. Cereatti, T. Seel, Data 6(7):72, 2021, "
        "https://doi.org/10.3390/data6070072), CC-BY-4.0.", ""])
    print(text)
    if a.write:
        write_text_atomic(Path(a.write), text)


if __name__ == "__main__":
    main()
