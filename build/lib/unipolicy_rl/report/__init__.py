"""A sweep's results in one folder: ``python -m unipolicy_rl.report <sweep or run dir> [--out DIR]``.

Training curves with seed bands, design-grid heatmaps, relative performance, generalisation
beyond the training range, a summary table, and what is missing, in ``report.md``.
"""

from unipolicy_rl.report.build import Report, build_report
from unipolicy_rl.report.runs import ReportError

__all__ = ["Report", "ReportError", "build_report"]
