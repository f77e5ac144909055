"""One rich progress bar per stage, for the commands whose engine calls report progress events
(``preprocess_video``, ``load_driving``, ``animate``)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from rich.console import Console

from eva_engine.progress import Progress, ProgressEvent


@contextmanager
def stage_bars(console: Console) -> Iterator[Progress]:
    """Yields a ``Progress`` callback: a bar per stage, added when the stage first reports
    (``total`` 0: unknown)."""
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn
    from rich.progress import Progress as Bars

    columns = (TextColumn("{task.description:>8}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Bars(*columns, console=console) as bars:
        tasks: dict[str, int] = {}

        def report(event: ProgressEvent) -> None:
            total = event.total or None
            if event.stage not in tasks:
                tasks[event.stage] = bars.add_task(event.stage, total=total)
            bars.update(tasks[event.stage], completed=event.done, total=total)

        yield report
