"""CPU seconds a run spends, its worker processes included: a cost that load inflates far less than wall time.

Wall seconds measure what a user waits for, but on a shared machine they grow with everything
else that runs: a process that waits for a core adds wall seconds and no CPU seconds. CPU
seconds (user + system, summed over every core) count the work itself, so they move far less
with the load: 8 small SE-TRPO epochs took 4.0 wall s and 7.3 CPU s alone, 10.1 and 9.1 beside
two busy loops on the same 2 cores (docs/results.md, "The league"). Not an exact yardstick: what
sharing a core costs in caches, and any waiting a process spends spinning, is left in.
The count covers this process (all its threads: a model fit on a second thread too) and every
live descendant, such as the collector's worker processes, read from Linux's ``/proc``;
processes that already ended count through their parent's ``cutime``/``cstime``. Ray actors
are not descendants and are not counted. Elsewhere than Linux, only this process and the
children it has already waited for are counted (:func:`os.times`).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

__all__ = ["process_tree_cpu_seconds"]

_PROC = Path("/proc")


def _ticks_per_second() -> int:
    try:
        return os.sysconf("SC_CLK_TCK")
    except (AttributeError, ValueError, OSError):
        return 100


def _stat_cpu_ticks(pid: int) -> int | None:
    """utime + stime + cutime + cstime of ``pid`` in clock ticks (None if it is gone)."""
    try:
        stat = (_PROC / str(pid) / "stat").read_text()
    except OSError:
        return None
    # The second field, the command name, is in parentheses and may hold spaces.
    fields = stat[stat.rindex(")") + 2:].split()
    return sum(int(value) for value in fields[11:15])  # fields 14-17 of proc(5), counted from 1


def _children(pid: int) -> list[int]:
    children: list[int] = []
    try:
        tasks = list((_PROC / str(pid) / "task").iterdir())
    except OSError:
        return children
    for task in tasks:
        try:
            children += [int(child) for child in (task / "children").read_text().split()]
        except OSError:
            continue
    return children


def process_tree_cpu_seconds(pid: int | None = None) -> float:
    """CPU seconds (user + system) of process ``pid`` (this one by default) and its live
    descendants, including the processes they have already waited for."""
    root = os.getpid() if pid is None else pid
    if not (_PROC / str(root) / "stat").exists() or not (_PROC / str(root) / "task").exists():
        if pid is not None and pid != os.getpid():
            raise ValueError(f"the CPU time of process {pid} needs Linux's /proc")
        times = os.times()
        return time.process_time() + times.children_user + times.children_system
    ticks, pending, seen = 0, [root], set()
    while pending:
        current = pending.pop()
        if current in seen:
            continue
        seen.add(current)
        own = _stat_cpu_ticks(current)
        if own is None:
            continue
        ticks += own
        pending += _children(current)
    return ticks / _ticks_per_second()
