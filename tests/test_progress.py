"""Progress output when it goes to a file: plain lines from the same columns as the terminal's bar."""

import io

from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)

from posegrasp.progress import LineProgress, progress, track

COLUMNS = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
           TextColumn("loss {task.fields[loss]}"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn())


def test_lines_at_start_and_completion():
    out = io.StringIO()
    with LineProgress(*COLUMNS, file=out, every_s=3600) as bar:
        task = bar.add_task("cls", total=4, loss="-")
        for k in range(4):
            bar.update(task, advance=1, loss=f"{0.5 / (k + 1):.3f}")
    lines = out.getvalue().splitlines()
    assert len(lines) == 2, lines  # the first update, then completion; none in between (every hour)
    assert lines[0].startswith("cls (25%) 1/4 loss 0.500 0:00:00 ETA 0:00:0")
    assert lines[1].startswith("cls (100%) 4/4 loss 0.125 0:00:00 ETA 0:00:00")


def test_resumed_task_and_unfinished_block():
    out = io.StringIO()
    with LineProgress(*COLUMNS, file=out, every_s=0) as bar:
        task = bar.add_task("seg", total=10, completed=6, loss="-")
        bar.update(task, completed=7)
        bar.update(task, completed=8, loss="0.2")
    lines = out.getvalue().splitlines()
    assert [ln.split(" ")[2] for ln in lines] == ["7/10", "8/10"]  # every update at every_s = 0, none at exit
    assert "loss 0.2" in lines[1]


def test_progress_picks_by_console():
    quiet = progress(*COLUMNS, enabled=False)
    assert isinstance(quiet, Progress) and quiet.disable
    to_file = progress(*COLUMNS, console=Console(file=io.StringIO()))
    assert isinstance(to_file, LineProgress)
    assert isinstance(progress(*COLUMNS, console=Console(file=io.StringIO(), force_terminal=True)), Progress)


def test_track_yields_everything_and_reports(capsys):
    assert list(track(range(3), "crops train")) == [0, 1, 2]
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("crops train (33%) 1/3") and lines[-1].startswith("crops train (100%) 3/3")
    assert list(track([1, 2], "quiet", enabled=False)) == [1, 2]
    assert capsys.readouterr().out == ""
