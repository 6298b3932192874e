"""The CPU seconds a run's processes spend (``time/cpu``): its workers counted, while alive and after."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from unipolicy_rl.training import process_tree_cpu_seconds

BUSY_CHILD = "import time\nstart = time.process_time()\nwhile time.process_time() - start < 0.6: pass\ntime.sleep(30)"


@pytest.mark.skipif(not Path(f"/proc/{os.getpid()}/task").exists(), reason="reads Linux's /proc")
def test_a_busy_worker_counts_while_alive_and_after_it_ended():
    before = process_tree_cpu_seconds()
    child = subprocess.Popen([sys.executable, "-c", BUSY_CHILD])
    try:
        deadline = time.monotonic() + 20
        while process_tree_cpu_seconds(child.pid) < 0.6 and time.monotonic() < deadline:
            time.sleep(0.05)
        alive = process_tree_cpu_seconds() - before
        # the live child's work (and its interpreter's start-up), counted through /proc (in ticks: a
        # difference of two sums may land a rounding error below 0.6)
        assert alive >= 0.6 - 1e-9
    finally:
        child.kill()
        child.wait()
    # Once reaped, its seconds move into this process's count of ended children: none is lost.
    assert process_tree_cpu_seconds() - before >= alive - 0.02


def test_this_process_busy_counts_and_idle_does_not():
    before = process_tree_cpu_seconds()
    start = time.process_time()
    while time.process_time() - start < 0.3:
        pass
    busy = process_tree_cpu_seconds() - before
    time.sleep(0.3)
    idle = process_tree_cpu_seconds() - before - busy
    assert 0.25 <= busy < 1.0 and idle < 0.1


def test_another_process_without_proc_is_refused_by_name(monkeypatch):
    import unipolicy_rl.training.cpu_time as cpu_time

    monkeypatch.setattr(cpu_time, "_PROC", Path("/nonexistent-proc"))
    assert process_tree_cpu_seconds() >= 0  # this process: the portable count
    with pytest.raises(ValueError, match="process 1 needs"):
        process_tree_cpu_seconds(1)
