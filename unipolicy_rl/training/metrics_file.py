"""``metrics.csv``'s writer, that training appends rows with.

The column names are :mod:`unipolicy_rl.metric_columns`' (re-exported here, so
``metrics_file.EPOCH`` and the like keep working); only the standard library is imported
besides: readers must not pay for training's imports.
"""

from __future__ import annotations

import csv
import math
import os
import shutil
from pathlib import Path

from unipolicy_rl.metric_columns import *  # noqa: F403  (the column names, one source)
from unipolicy_rl.metric_columns import EPOCH, IMAGINED


def without_redone_epochs(rows: list[dict[str, float]]) -> list[dict[str, float]]:
    """``rows`` (numbers, in file order) with each epoch once: a run resumed from an older checkpoint
    into its own folder logs again the epochs after it, and the later rows are the ones its
    checkpoint continued from. An epoch has one real row (its imagined rows repeat its number):
    a row of an earlier epoch than the last row's, or a second real row of an epoch, marks a
    redo, and the earlier rows of the epochs redone go (those up to the last real one of them,
    so a redone epoch's own imagined rows before its real row stay)."""
    kept: list[dict[str, float]] = []
    last_real = -math.inf  # the latest epoch with a real row in ``kept``
    for row in rows:
        epoch = row[EPOCH]
        if kept and epoch < kept[-1][EPOCH]:
            kept = [old for old in kept if old[EPOCH] < epoch]
            last_real = max((old[EPOCH] for old in kept if _is_real(old)), default=-math.inf)
        elif _is_real(row) and epoch <= last_real:
            end = max(index for index, old in enumerate(kept) if old[EPOCH] >= epoch and _is_real(old))
            kept = [old for index, old in enumerate(kept) if old[EPOCH] < epoch or index > end]
        kept.append(row)
        if _is_real(row):
            last_real = max(last_real, epoch)
    return kept


def _is_real(row: dict[str, float]) -> bool:
    return row.get(IMAGINED) != 1.0  # (a file from before the column holds real rows only)


class MetricsCSV:
    """``metrics.csv``: one row per training batch, appended (a resumed run continues the file).

    Real and imagined batches log different figures, so a row may bring a column the file
    has not had yet: the file is then rewritten once with the wider header (cells a row
    lacks stay empty). The rewrite goes to a temporary file that replaces the old one, so a
    crash during it leaves the old file whole rather than a truncated one.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.columns: list[str] = []
        if path.is_file():
            with path.open(newline="") as file:
                self.columns = next(csv.reader(file), [])

    def drop_epochs_after(self, epoch: int) -> None:
        """Removes the rows of the epochs after ``epoch``: a run resumed from its checkpoint at
        ``epoch`` logs them again, so each epoch is in the file once (the redone one replacing
        the one a kill cut off)."""
        if not self.path.is_file():
            return
        with self.path.open(newline="") as file:
            rows = list(csv.DictReader(file))
        kept = [row for row in rows if _epoch(row) <= epoch]
        if len(kept) < len(rows):
            self._rewrite(self.columns, kept)

    def append(self, row: dict[str, float]) -> None:
        new = [key for key in row if key not in self.columns]
        if new:
            rows = []
            if self.path.is_file():
                with self.path.open(newline="") as file:
                    rows = list(csv.DictReader(file))
            self._rewrite(self.columns + new, rows)
            self.columns += new
        with self.path.open("a", newline="") as file:
            csv.DictWriter(file, fieldnames=self.columns).writerow(row)

    def _rewrite(self, columns: list[str], rows: list[dict[str, str]]) -> None:
        # Same folder, so os.replace is a rename within one file system (atomic).
        temporary = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            with temporary.open("w", newline="") as file:
                writer = csv.DictWriter(file, fieldnames=columns)
                writer.writeheader()
                writer.writerows(rows)
                file.flush()
                os.fsync(file.fileno())
            if self.path.is_file():
                shutil.copymode(self.path, temporary)
            os.replace(temporary, self.path)
        finally:
            temporary.unlink(missing_ok=True)


def _epoch(row: dict[str, str]) -> float:
    """A written row's epoch (a row cut short by a kill, without one, counts as after every epoch)."""
    try:
        return float(row.get(EPOCH) or "inf")
    except ValueError:
        return float("inf")
