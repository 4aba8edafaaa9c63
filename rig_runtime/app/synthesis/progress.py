"""The progress bar of ``rig synthesize run`` (rich, on a terminal): runs done of the planned
ones, and the best feasible candidate so far (its tunables and objectives)."""

from __future__ import annotations

import sys

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn


class SynthesisProgress:
    def __init__(self, total: int, done: int):
        self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                            TextColumn("{task.fields[best]}"), console=Console(stderr=True),
                            disable=not sys.stderr.isatty(), transient=False)
        self.task = self.bar.add_task("synthesis", total=total, completed=done, best="best feasible: -")

    def __enter__(self) -> "SynthesisProgress":
        self.bar.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.bar.__exit__(*exc)

    def advance(self) -> None:
        self.bar.update(self.task, advance=1)

    def best(self, text: str) -> None:
        self.bar.update(self.task, best=f"best feasible: {text}")
