"""``write_report``: the run folder read, the episodes to show re-simulated, the sections assembled into
``DIR/report.html``; and the ``posegrasp report`` command."""

from __future__ import annotations

import argparse
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from posegrasp.errors import UserError
from posegrasp.executor import Executor
from posegrasp.grasping.report import sections
from posegrasp.grasping.report.resim import resimulate_looks
from posegrasp.grasping.report.run import TrialRun, read_run
from posegrasp.grasping.report.sections import pick_samples
from posegrasp.grasping.tasks import get_task

REPORT = "report.html"


def write_report(run_dir: Path, samples: int = 4, strip: int = 6, executor: Executor | None = None) -> Path:
    """Write ``run_dir/report.html`` from its ``episodes.jsonl``, ``summary.json`` and ``campaign.json``;
    ``samples`` episodes get Fig. 9-10 style frames, ``strip`` episodes an overview snapshot, re-simulated by
    ``executor`` (a campaign's warm workers) or in this process; a task with a page of its own
    (``Task.report_page``: bin picking) shows that instead. Returns the path."""
    from posegrasp.io import atomic_write

    if samples < 0 or strip < 0:
        raise UserError(f"--samples and --strip must be >= 0, got {samples} and {strip}")
    run = read_run(run_dir)
    page = get_task(run.campaign.config.task).report_page(run, samples, executor) or \
        _table_page(run, samples, strip, executor)
    path = run.path / REPORT
    atomic_write(path, lambda p: p.write_text(page))
    return path


def _table_page(run: TrialRun, samples: int, strip: int, executor: Executor | None) -> str:
    """The page of a table task: sample frames and the overview strip at the look pose."""
    shown, strip_eps = pick_samples(run.episodes, samples), run.episodes[:strip]
    resim = {r.episode: r for r in shown + strip_eps}
    with ThreadPoolExecutor(1) as plotter:  # the plots drawn while the looks are re-simulated (and rendered here)
        plots = plotter.submit(sections.error_plots, run)
        looks = resimulate_looks(run.path, [resim[e] for e in sorted(resim)], executor)
        return sections.page([sections.headline(run), sections.settings(run), sections.per_block(run),
                              sections.failures(run), plots.result(),
                              sections.sample_frames(run, shown, looks), sections.episode_strip(strip_eps, looks)])


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="write DIR/report.html for a trial run (self-contained HTML)")
    p.add_argument("dir", help="a folder written by 'posegrasp trials --out'")
    p.add_argument("--samples", type=int, default=4, help="episodes shown with overlays (default 4)")
    p.add_argument("--strip", type=int, default=6, help="episodes in the overview strip (default 6)")
    p.set_defaults(run=run_report_cmd)


def run_report_cmd(args: argparse.Namespace) -> int:
    path = write_report(Path(args.dir), args.samples, args.strip)
    print(f"report -> {path}")
    return 0
