"""Progress of long jobs: rich's live bar on a terminal, plain lines when the output goes to a file.

    with progress(TextColumn("{task.description}"), MofNCompleteColumn(), TimeRemainingColumn()) as bar:
        task = bar.add_task("datagen", total=n)
        bar.advance(task)

Rich draws nothing when its console is not a terminal (``nohup posegrasp train ... > log``), so there the same
columns are written as one line per task every ``every_s`` seconds and when the task completes, e.g.
``cls (27%) 2000/7500 loss 0.2135 0:11:04 ETA 0:30:27``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import IO, Any, Iterable, Iterator, TypeVar

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)
from rich.text import Text

T = TypeVar("T")


def progress(*columns: ProgressColumn, enabled: bool = True, console: Console | None = None,
             transient: bool = False, every_s: float = 30.0) -> "Progress | LineProgress":
    """A rich ``Progress`` with these columns when ``console`` (default: stdout's) is a terminal, else a
    ``LineProgress`` writing to the console's file; disabled (silent) when not ``enabled``."""
    console = console or Console()
    if not enabled or console.is_terminal:
        return Progress(*columns, console=console, transient=transient, disable=not enabled)
    return LineProgress(*columns, file=console.file, every_s=every_s)


def track(sequence: Iterable[T], description: str, total: int | None = None, enabled: bool = True) -> Iterator[T]:
    """Iterate ``sequence`` with a progress display (count, elapsed time, ETA)."""
    total = total if total is not None else len(sequence)  # type: ignore[arg-type]
    with progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TextColumn("ETA"), TimeRemainingColumn(), enabled=enabled) as bar:
        task = bar.add_task(description, total=total)
        for item in sequence:
            yield item
            bar.advance(task)


@dataclass
class _Task:
    description: str
    total: float | None
    completed: float
    fields: dict[str, Any]
    start: float = field(default_factory=time.monotonic)
    started_at: float = 0.0  # completed when the task was added (a resumed job's done part)
    printed: float = float("-inf")  # monotonic time of the last line written (the first update writes one)
    printed_at: float = -1.0  # completed at that line


class LineProgress:
    """The part of ``rich.progress.Progress`` the jobs use (``add_task``, ``update``, ``advance``, a context manager),
    writing plain lines: per task, every ``every_s`` s and when it completes (or the block ends). Each line renders the
    columns: text columns by their format, m/n for ``MofNCompleteColumn``, the percentage for ``BarColumn``, elapsed
    time and ETA (from the rate since the task was added) for the time columns; other columns are left out."""

    def __init__(self, *columns: ProgressColumn, file: IO[str], every_s: float = 30.0):
        if every_s < 0:
            raise ValueError(f"every_s must be >= 0, got {every_s}")
        self.columns, self.file, self.every_s = columns, file, every_s
        self.tasks: list[_Task] = []

    def __enter__(self) -> "LineProgress":
        return self

    def __exit__(self, *exc: Any) -> None:
        for t in self.tasks:
            if t.printed_at != t.completed:
                self._write(t)

    def add_task(self, description: str, total: float | None = 100.0, completed: float = 0, **fields: Any) -> int:
        """A new task; returns its id."""
        self.tasks.append(_Task(description, total, completed, fields, started_at=completed))
        return len(self.tasks) - 1

    def update(self, task_id: int, *, total: float | None = None, completed: float | None = None,
               advance: float | None = None, description: str | None = None, **fields: Any) -> None:
        """Set or advance a task's progress and fields; writes its line when one is due."""
        t = self.tasks[task_id]
        if total is not None:
            t.total = total
        if completed is not None:
            t.completed = completed
        if advance is not None:
            t.completed += advance
        if description is not None:
            t.description = description
        t.fields.update(fields)
        done = t.total is not None and t.completed >= t.total
        if (done and t.printed_at != t.completed) or time.monotonic() - t.printed >= self.every_s:
            self._write(t)

    def advance(self, task_id: int, advance: float = 1) -> None:
        self.update(task_id, advance=advance)

    def line(self, task_id: int) -> str:
        """The task's line as it would be written now."""
        t = self.tasks[task_id]
        elapsed = time.monotonic() - t.start
        parts = []
        for c in self.columns:
            if isinstance(c, TextColumn):
                fmt = c.text_format.format(task=t)
                parts.append(Text.from_markup(fmt).plain if c.markup else fmt)
            elif isinstance(c, MofNCompleteColumn):
                parts.append(f"{t.completed:g}/{'?' if t.total is None else f'{t.total:g}'}")
            elif isinstance(c, BarColumn) and t.total:
                parts.append(f"({100.0 * t.completed / t.total:.0f}%)")
            elif isinstance(c, TimeElapsedColumn):
                parts.append(_hms(elapsed))
            elif isinstance(c, TimeRemainingColumn):
                rate = (t.completed - t.started_at) / elapsed if elapsed > 0 else 0.0
                left = None if t.total is None or rate <= 0 else (t.total - t.completed) / rate
                parts.append("-:--:--" if left is None else _hms(left))
        return " ".join(p for p in parts if p)

    def _write(self, t: _Task) -> None:
        self.file.write(self.line(self.tasks.index(t)) + "\n")
        self.file.flush()
        t.printed, t.printed_at = time.monotonic(), t.completed


def _hms(seconds: float) -> str:
    s = int(max(seconds, 0.0))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"
