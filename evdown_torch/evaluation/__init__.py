"""The trade study behind ``evdown evaluate``: what each downscaler costs and what it keeps.

See docs/evaluation.md for the design and every measure. Modules: :mod:`.data` (where the
recordings come from), :mod:`.cache` (the disk cache), :mod:`.cells` (a cell and the jobs that
fill it), :mod:`.study` (the stages, through worker processes), :mod:`.ranks` (the stages over
the ranks of a ``torchrun`` launch), :mod:`.statistics` (intervals and tests) and
:mod:`.report` (CSV, Markdown, plot).
"""

from evdown_torch.evaluation.cells import BASELINE, CONTROL, Cell
from evdown_torch.evaluation.report import markdown_table, write_report
from evdown_torch.evaluation.study import (
    CellResult,
    Comparison,
    EvaluationResult,
    RankRun,
    run_evaluation,
)

__all__ = [
    "BASELINE",
    "CONTROL",
    "Cell",
    "CellResult",
    "Comparison",
    "EvaluationResult",
    "RankRun",
    "markdown_table",
    "run_evaluation",
    "write_report",
]
