"""The HTML report of a run: headline scores, per-class and per-stage tables, plots, config.

``report.html`` is self-contained (every plot is embedded as a base64 PNG), so it opens
offline on any machine; the same plots are also written as PNG files in ``plots/``.
:mod:`~workflows.report.figures` draws the plots, :mod:`~workflows.report.html` lays out the
page and :mod:`~workflows.report.build` writes both.
"""

from workflows.report.build import write_report
from workflows.report.figures import (
    CLASS_COLOURS,
    class_colour,
    confusion_figure,
    f1_per_stage_figure,
    format_score,
    importance_figure,
    precision_recall_figure,
    topdown_figure,
)
from workflows.report.html import PLOT_NAMES

__all__ = [
    "CLASS_COLOURS",
    "PLOT_NAMES",
    "class_colour",
    "confusion_figure",
    "f1_per_stage_figure",
    "format_score",
    "importance_figure",
    "precision_recall_figure",
    "topdown_figure",
    "write_report",
]
