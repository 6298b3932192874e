"""``metrics.csv``'s writer, that training appends rows with.

The column names are :mod:`unipolicy_rl.metric_columns`' (re-exported here, so
``metrics_file.EPOCH`` and the like keep working); only the standard library is imported
besides: readers must not pay for training's imports.
"""

from __future__ import annotations

import csv
import os
import shutil
from pathlib import Path

from unipolicy_rl.metric_columns import *  # noqa: F403  (the column names, one source)


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
