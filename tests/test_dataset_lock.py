"""Parallel jobs that need the same dataset make it once: ``load_or_generate`` holds a file lock.

Two processes ask for the same file at the same moment (a barrier of marker files); the
simulation is slowed down (1 s) so that without the lock both would generate. With the lock,
one generates, the other waits and reads the file, and both hold identical data.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from manifold_nets.atomic import file_lock

ROOT = Path(__file__).resolve().parents[1]

JOB = textwrap.dedent(
    """
    import contextlib, hashlib, logging, sys, time
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    import manifold_nets.datasets as datasets

    configs, cache, barrier, me, lock = sys.argv[1:6]
    logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(message)s")
    if lock == "off":  # what the test guards against: no lock, both generate
        datasets.file_lock = lambda path: contextlib.nullcontext()
    with initialize_config_dir(config_dir=configs, version_base="1.3"):
        system = instantiate(compose("train", overrides=["experiment=default"]).system)
    simulate = system.simulate

    def slow_simulate(*args, **kwargs):  # long enough for the other job to ask meanwhile
        time.sleep(1.0)
        return simulate(*args, **kwargs)

    system.simulate = slow_simulate
    Path(barrier, me).touch()  # start together: wait for the other job
    while len(list(Path(barrier).iterdir())) < 2:
        time.sleep(0.01)
    cfg = {"num_sequences": 12, "length": 5, "sigma": 0.1, "progress": False}
    parts = datasets.load_or_generate(system, cfg, cache_dir=cache)
    digest = hashlib.sha256()
    for part in parts.values():
        for t in (part.states, part.measurements, part.inputs):
            digest.update(t.numpy().tobytes())
    print("digest", digest.hexdigest())
    """
)


def _two_jobs_at_once(tmp_path: Path, lock: str) -> list[str]:
    cache, barrier = tmp_path / f"data_{lock}", tmp_path / f"barrier_{lock}"
    barrier.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", JOB, str(ROOT / "configs"), str(cache), str(barrier), me, lock],
            cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        for me in ("a", "b")
    ]
    outs = [p.communicate(timeout=180)[0] for p in procs]
    for p, out in zip(procs, outs):
        assert p.returncode == 0, out[-3000:]
    return outs


def _count(outs: list[str], word: str) -> int:
    return sum(line.startswith(word) for out in outs for line in out.splitlines())


def _digests(outs: list[str]) -> set[str]:
    lines = [line for out in outs for line in out.splitlines()]
    return {line.split()[1] for line in lines if line.startswith("digest")}


@pytest.mark.skipif(sys.platform == "win32", reason="file_lock needs fcntl (POSIX)")
def test_two_jobs_asking_for_the_same_dataset_generate_it_once(tmp_path):
    outs = _two_jobs_at_once(tmp_path, "on")
    assert _count(outs, "generated") == 1, outs
    assert _count(outs, "reusing") == 1, outs
    assert len(_digests(outs)) == 1  # both jobs hold the same data
    files = sorted(p.name for p in (tmp_path / "data_on").iterdir())
    assert len(files) == 2 and files[1] == files[0] + ".lock"  # the file and its lock


def test_without_the_lock_both_jobs_would_generate(tmp_path):
    # the check above is meaningful: the same two jobs with the lock taken out both generate
    outs = _two_jobs_at_once(tmp_path, "off")
    assert _count(outs, "generated") == 2, outs
    assert len(_digests(outs)) == 1  # same seed, same bytes: the waste is time, not data


def test_file_lock_is_released_after_the_block_and_leaves_its_file(tmp_path):
    target = tmp_path / "sub" / "x.npz"
    with file_lock(target) as lock_path:
        assert lock_path == tmp_path / "sub" / "x.npz.lock" and lock_path.is_file()
    with file_lock(target):  # released: taken again at once
        pass
    assert lock_path.is_file() and not target.exists()
