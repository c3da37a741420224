"""Temporaries that a killed writer leaves behind are removed by the next write of the same
target, and a live writer's temporary is never touched."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from manifold_nets import atomic
from manifold_nets.atomic import atomic_open, write_text_atomic

ATOMIC_PY = Path(atomic.__file__)

# A writer that is killed (SIGKILL) half way through a write: it loads atomic.py on its own
# (no torch import, so it starts fast), writes half a file and waits to be killed.
WRITER = f"""
import importlib.util, sys, time
spec = importlib.util.spec_from_file_location("atomic", {str(ATOMIC_PY)!r})
atomic = importlib.util.module_from_spec(spec)
spec.loader.exec_module(atomic)
with atomic.atomic_open(sys.argv[1], "wb") as f:
    f.write(b"half of a new file")
    f.flush()
    print("writing", flush=True)
    time.sleep(600)
"""


def temporaries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


@pytest.mark.skipif(os.name != "posix", reason="kill -9 and the pid check are POSIX")
def test_kill_9_mid_write_keeps_the_old_file_and_the_next_write_cleans_up(tmp_path):
    target = tmp_path / "d.npz"
    write_text_atomic(target, "old, whole")
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(target)], stdout=subprocess.PIPE)
    try:
        assert proc.stdout.readline() == b"writing\n"
        [left] = temporaries(tmp_path)
        assert left.startswith(".d.npz.") and f".{proc.pid}." in left  # recognisable
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert target.read_text() == "old, whole"  # the previous file stays whole
    assert temporaries(tmp_path) == [left]  # the leftover a kill -9 leaves today
    write_text_atomic(target, "new")
    assert target.read_text() == "new"
    assert temporaries(tmp_path) == []  # removed by the next write of the same target


def test_stale_removed_live_kept(tmp_path, caplog):
    target = tmp_path / "ckpt.pt"
    host = getattr(atomic, "_HOST", "thishost")  # this host's name as temporaries spell it
    dead = tmp_path / f".ckpt.pt.{host}.{dead_pid()}.0123456789ab.tmp"  # its writer is gone
    old_style = tmp_path / ".ckpt.pt.k3j_x9q2.tmp"  # from before the pid was in the name
    other_host = tmp_path / f".ckpt.pt.elsewhere-{host}.4242.0123456789ab.tmp"
    live = tmp_path / f".ckpt.pt.{host}.{os.getpid()}.0123456789ab.tmp"  # a live writer
    live_old = tmp_path / f".ckpt.pt.{host}.{os.getppid()}.ba9876543210.tmp"  # live, quiet 2 h
    fresh_other_host = tmp_path / f".ckpt.pt.elsewhere-{host}.4242.ffffffffffff.tmp"
    other_target = tmp_path / f".last.pt.{host}.{dead_pid()}.0123456789ab.tmp"
    for p in (dead, old_style, other_host, live, live_old, fresh_other_host, other_target):
        p.write_bytes(b"x")
    two_hours_ago = time.time() - 7200
    for p in (old_style, other_host, live_old):
        os.utime(p, (two_hours_ago, two_hours_ago))
    with caplog.at_level(logging.INFO, logger="manifold_nets.atomic"):
        with atomic_open(target, "wb") as f:
            f.write(b"new")
    assert target.read_bytes() == b"new"
    assert f"removed {old_style}, left by an interrupted write of {target}" in caplog.messages
    remaining = set(temporaries(tmp_path))
    assert old_style.name not in remaining and other_host.name not in remaining
    assert {live.name, fresh_other_host.name, other_target.name} <= remaining
    if os.name == "posix":  # where the writer's pid can be checked
        assert dead.name not in remaining and live_old.name in remaining


def test_a_new_file_follows_the_umask_and_a_replaced_one_keeps_its_mode(tmp_path):
    import os
    import stat

    from manifold_nets.atomic import write_text_atomic

    old = os.umask(0o077)
    try:
        write_text_atomic(tmp_path / "new.txt", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE(os.stat(tmp_path / "new.txt").st_mode) == 0o600
    kept = tmp_path / "kept.txt"
    kept.write_text("old")
    os.chmod(kept, 0o640)
    write_text_atomic(kept, "new")
    assert kept.read_text() == "new" and stat.S_IMODE(os.stat(kept).st_mode) == 0o640
