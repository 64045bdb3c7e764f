"""Progress bar and summary table of a batch (rich, on stderr): part of the CLI layer.

Only the modules of ``rangeseg_cli.cli`` import click or rich; the library never does.
"""

from __future__ import annotations

import sys
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from ..batch.jobs import Record
from ..batch.runner import BatchSummary


class BatchReporter:
    """Shows a progress bar while a batch runs and a summary table at the end.

    Each failed image is reported once, as one line ``file: reason`` on
    stderr, whatever the verbosity; ``-vv`` adds the traceback of internal
    errors. The bar is shown only when stderr is a terminal and not ``-q``.
    """

    def __init__(self, *, quiet: bool = False, verbose: int = 0) -> None:
        self.console = Console(stderr=True, highlight=False)
        self.quiet, self.verbose = quiet, verbose
        self.progress: Progress | None = None
        self.task: Any = None

    def start(self, total: int) -> None:
        """Open the progress bar for ``total`` images."""
        if self.quiet or not sys.stderr.isatty() or total < 2:
            return
        self.progress = Progress(TextColumn("[bold]rangeseg"), BarColumn(),
                                 MofNCompleteColumn(), TimeElapsedColumn(),
                                 console=self.console, transient=True)
        self.progress.start()
        self.task = self.progress.add_task("images", total=total)

    def result(self, record: Record) -> None:
        """Advance the bar; report a failure on its own line."""
        if record.status == "failed":
            self.console.print(record.error, markup=False, soft_wrap=True)
            if self.verbose >= 2 and record.detail:
                self.console.print(record.detail, markup=False)
        if self.progress is not None:
            self.progress.advance(self.task)

    def stop(self) -> None:
        """Close the progress bar."""
        if self.progress is not None:
            self.progress.stop()
            self.progress = None

    def summary(self, summary: BatchSummary) -> None:
        """Print the summary table: done / resumed / failed / not images, time per stage."""
        if self.quiet:
            return
        table = Table(title="rangeseg summary", show_header=True)
        for col in ("done", "resumed", "failed", "not images", "seconds"):
            table.add_column(col, justify="right")
        table.add_row(str(summary.count("done")), str(summary.count("skipped")),
                      str(summary.count("failed")), str(len(summary.skipped_files)),
                      f"{summary.seconds:.2f}")
        self.console.print(table)
        stages = summary.stage_seconds
        if stages:
            self.console.print("time per stage (s): " + ", ".join(
                f"{k} {v:.3f}" for k, v in stages.items()), markup=False)


def _check_cell(check: dict[str, Any] | None) -> str:
    """A holdsite check as a table cell: ok, fail or - (not checked)."""
    return "-" if check is None else ("ok" if check["ok"] else "[red]fail[/red]")


def print_eval_table(result: dict[str, Any]) -> None:
    """Print the Hoover et al. (1996) classes per image and in total, and the tolerance curve."""
    keys = ("gt_regions", "correct", "over", "under", "missed", "noise")
    table = Table(title=f"Hoover et al. (1996) at tolerance {result['tolerance']:g}, "
                  f"GT regions >= {result['min_region']} px")
    for col in ("image", "GT", "correct", "over", "under", "missed", "noise", "holdsite",
                "usable"):
        table.add_column(col, justify="left" if col == "image" else "right")
    for stem, row in result["images"].items():
        if "error" in row:
            table.add_row(stem, "[red]error[/red]", *[""] * 7)
            continue
        table.add_row(stem, *(str(row[k]) for k in keys), _check_cell(row.get("holdsite")),
                      _check_cell(row.get("holdsite_object")))
    total = result["total"]
    cells = [f"[bold]{c['ok']}/{c['checked']}" if c else "" for c in
             (total.get("holdsite"), total.get("holdsite_object"))]
    table.add_row("[bold]total", *(f"[bold]{total[k]}" for k in keys), *cells,
                  end_section=True)
    console = Console(highlight=False)
    console.print(table)
    curve = total["curve"]
    console.print("correct detections vs tolerance: " + ", ".join(
        f"{t:g}: {c}" for t, c in zip(curve["tolerance"], curve["correct"], strict=True)))
