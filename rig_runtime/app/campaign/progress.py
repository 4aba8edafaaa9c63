"""The progress bar (rich, on a terminal): runs done, the pass rate so far, the ETA."""

from __future__ import annotations

import sys

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn


class CampaignProgress:
    def __init__(self, total: int, done: int, passed: int, judged: int):
        self.passed, self.judged = passed, judged
        self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TextColumn("ETA"),
                            TimeRemainingColumn(), console=Console(stderr=True), disable=not sys.stderr.isatty(),
                            transient=False)
        self.task = self.bar.add_task("campaign", total=total, completed=done, rate=self._rate())

    def _rate(self) -> str:
        return f"pass {100 * self.passed / self.judged:.1f} %" if self.judged else "pass -"

    def __enter__(self) -> "CampaignProgress":
        self.bar.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.bar.__exit__(*exc)

    def advance(self, status: str) -> None:
        if status != "error":
            self.judged += 1
            self.passed += status == "pass"
        self.bar.update(self.task, advance=1, rate=self._rate())
