"""Trial campaigns: many episodes in parallel, resumable, with a summary, a report and a noise sweep.

``DIR/episodes.jsonl`` holds one JSON line per finished episode, appended as they finish; a rerun skips
the episodes already there (a torn last line from a kill is dropped) and the file is finally rewritten
sorted by episode, so it is identical for any worker count and after a kill and resume. Wall-clock
timings, which differ run to run, go to ``DIR/timings.jsonl``; ``DIR/summary.json`` has the success rate
with its Wilson 95 % interval and the per-block and per-failure tables (file layout: ``grasping.runfolder``).
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn

from posegrasp.errors import ConfigError, DatasetError, UserError
from posegrasp.executor import make_executor
from posegrasp.grasping.calibration import load_hand_eye
from posegrasp.grasping.bop_csv import check_rows
from posegrasp.grasping.captures import open_export, run_capturing
from posegrasp.catalog import set_record
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.episode import EpisodeJob, check_draws, run_episode
from posegrasp.grasping.latency import campaign_latency
from posegrasp.grasping.provider_registry import canonical_spec, make_provider
from posegrasp.grasping.report import write_report
from posegrasp.grasping.runfolder import (CAMPAIGN, EPISODES, RECORDS, SUMMARY, TIMINGS, Campaign, append_record,
                                          check_campaign, read_episodes, read_records, write_records)
from posegrasp.grasping.stats import rate_row, summarise
from posegrasp.grasping.tasks import check_task, get_task, with_set
from posegrasp.io import write_bytes, write_json
from posegrasp.lock import folder_lock
from posegrasp.outputs import Record
from posegrasp.progress import progress as progress_bar

#: Noise levels (translation m, rotation deg) of ``--sweep-noise``, by ``--noise``.
SWEEP_LEVELS = ((0.0, 0.0), (0.0025, 2.5), (0.005, 5.0), (0.01, 10.0), (0.02, 20.0), (0.04, 40.0))
SWEEPS = {"both": SWEEP_LEVELS,
          "rotation": tuple((0.0, r) for r in (0.0, 5.0, 10.0, 20.0, 45.0)),
          "translation": tuple((t, 0.0) for t in (0.0, 0.0025, 0.005, 0.01, 0.02))}


def campaign_settings(episodes: int, cfg: TrialConfig) -> tuple[TrialConfig, tuple[tuple[float, ...], ...]]:
    """``cfg`` checked for a campaign of ``episodes`` episodes (its object set's folder made absolute, for the
    workers) and the calibrated camera mount (row-major 4x4); a UserError for settings no campaign can run."""
    if episodes < 1:
        raise UserError(f"--episodes must be at least 1, got {episodes}")
    if not 1 <= cfg.min_blocks <= cfg.max_blocks:
        raise ConfigError(f"need 1 <= min_blocks <= max_blocks, got {cfg.min_blocks} and {cfg.max_blocks}")
    cfg = with_set(cfg)
    check_task(cfg)
    return cfg, tuple(tuple(float(v) for v in row) for row in load_hand_eye(cfg.hand_eye))


@dataclass(frozen=True)
class Display:
    """Where a campaign shows itself: its ``console`` (None: stderr's) and whether a progress bar runs there."""

    console: Console | None = None
    progress: bool = True


def run_trials(out: Path, episodes: int, seed: int, perception: str, workers: int | str | None,
               cfg: TrialConfig, display: Display = Display(), export: Path | None = None) -> dict:
    """Run (or resume) a campaign of ``episodes`` episodes into ``out``; returns the summary; ``progress``
    shows a progress bar on ``display.console`` while episodes run (``display.progress``); ``export``: also write the frames the episodes
    perceive there, as a BOP test split (``grasping.captures``)."""
    cfg, mount = campaign_settings(episodes, cfg)
    perception = canonical_spec(perception)  # a plug-in file's path absolute, for the workers and the record
    task = get_task(cfg.task)
    provider = make_provider(perception, cfg.scene.workcell.objects, cfg.perception_timeout_s)
    check_rows(provider, episodes, cfg.task, task.looks)  # before any work starts
    console, progress = display.console or Console(stderr=True), display.progress
    # Ray connects in make_executor, before anything is written; the pool's workers stay for the report's frames
    out = Path(out).absolute()  # a provider changing the working directory cannot move the run's files
    with folder_lock(out, owns=RECORDS), open_export(export, seed, cfg) as captures, \
            make_executor(workers) as executor:
        done = read_records(out / EPISODES)
        check_kept(out, done, episodes)
        if not done:  # a campaign binds once it has an episode: settings of a failed start are replaced
            (out / CAMPAIGN).unlink(missing_ok=True)
        check_campaign(out, Campaign(seed, perception, cfg, mount))
        for i, (_, rec) in read_episodes(out / EPISODES).items():  # well-formed, or one line naming its line
            check_draws(EpisodeJob(task, seed, i, perception, cfg, mount), rec, out)  # and drawn by this campaign
        write_records(out / EPISODES, [done[i] for i in sorted(done)])  # drops a torn line before appending
        timings = read_records(out / TIMINGS)
        write_records(out / TIMINGS, [timings[i] for i in sorted(timings) if i in done])
        todo = [EpisodeJob(task, seed, i, perception, cfg, mount) for i in range(episodes) if i not in done]
        if captures is not None:  # episodes run before without their captures: only capture them
            todo += [EpisodeJob(task, seed, i, perception, cfg, mount, captures_only=True) for i in done
                     if not captures.has(i)]
        t0 = time.perf_counter()
        if todo:
            with open(out / EPISODES, "a") as f, open(out / TIMINGS, "a") as ft, progress_bar(
                    TextColumn("[bold]trials[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("ETA"), TimeRemainingColumn(), enabled=progress, console=console,
                    transient=True) as bar:
                bar_id = bar.add_task(f"{cfg.task} {perception}", total=episodes, completed=len(done))
                ok = sum(r["outcome"] == "success" for r in done.values())
                for _, result in executor.imap(run_episode if captures is None else run_capturing, todo):
                    rec, timing = result[:2]
                    if captures is not None:  # the captures first: an episode on record has them
                        captures.write(result[2])
                        if rec.episode in done:  # on record already: it was only captured
                            continue
                    line = rec.to_json()
                    append_record(f, line, sync=True)
                    append_record(ft, timing.to_json())
                    done[rec.episode] = line
                    ok += rec.outcome == "success"
                    bar.update(bar_id, advance=1, description=f"{cfg.task} {perception}  success {ok}/{len(done)}")
        elapsed = time.perf_counter() - t0
        ran = sum(not t.captures_only for t in todo)  # (the others were only captured)
        records = [done[i] for i in sorted(done)]
        write_records(out / EPISODES, records)
        latency = campaign_latency(cfg.perception_latency, provider, records, read_records(out / TIMINGS))
        summary = {**summarise(records), **task.metrics(records, latency["seconds"])}
        summary.update(task=cfg.task, perception_latency=latency, seed=seed, perception=perception, workers=workers,
                       objects=set_record(cfg.scene.workcell.objects),
                       wall={"seconds": elapsed, "episodes_run": ran,
                             "episodes_per_min": 60 * ran / elapsed if ran and elapsed > 0 else None})
        write_json(out / SUMMARY, summary)
        task.print_summary(summary, console)
        if summary["wall"]["episodes_per_min"]:
            console.print(f"{ran} episodes in {elapsed:.1f} s wall = {summary['wall']['episodes_per_min']:.0f} "
                          "episodes/min")
        console.print(f"report -> {write_report(out, executor=executor)}")
    return summary


def check_kept(out: Path, done: dict[int, dict], episodes: int) -> None:
    """A one-line DatasetError unless a resume of ``episodes`` episodes keeps every finished one in ``done``,
    and the records come with their ``campaign.json`` (records of an unknown campaign are never adopted)."""
    if done and not (out / CAMPAIGN).is_file():
        raise DatasetError(f"{out} holds {len(done)} episode record(s) but no {CAMPAIGN}, so their settings are "
                           "unknown; use another --out")
    if done and max(done) >= episodes:
        raise DatasetError(f"{out} holds finished episodes up to {max(done)}; --episodes {episodes} would drop "
                           f"them: give --episodes {max(done) + 1} or more, or another --out")


def sweep_noise(out: Path, episodes: int, seed: int, workers: int | str | None, cfg: TrialConfig,
                levels=SWEEP_LEVELS, console: Console | None = None, progress: bool = True) -> list[dict]:
    """Noisy-oracle campaigns at increasing noise (same seeds) for ``cfg.task``; writes ``sweep.json`` and
    ``sweep.png``."""
    console = console or Console(stderr=True)
    # the sweep's files (each campaign locks its subfolder)
    with folder_lock(out, owns=(Record("sweep.json", ("trans_m", "rot_deg")), Record(f"noise_*/{CAMPAIGN}",
                                                                                      RECORDS[0].keys))):
        rows = []
        for t, r in levels:
            spec, run_dir = f"noisy-oracle:{t:g},{r:g}", out / f"noise_{t:g}m_{r:g}deg"
            s = run_trials(run_dir, episodes, seed, spec, workers, cfg, Display(console, progress))
            errs = [rec["pose_error"]["err"] for rec in read_records(run_dir / EPISODES).values()
                    if rec.get("pose_error")]
            rows.append({"task": cfg.task, "trans_m": t, "rot_deg": r, **rate_row(s["success"], s["n"]),
                         "median_pose_error_m": float(np.median(errs)) if errs else None})
        write_json(out / "sweep.json", rows)
        plot_sweep(rows, out / "sweep.png")
    return rows


def plot_sweep(rows: list[dict], path: Path) -> None:
    """Success rate (with Wilson intervals) against median pose error (ADD(-S), mm), the table beside it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [1000 * (r["median_pose_error_m"] or 0.0) for r in rows]
    xlabel = "median pose error of the estimate used, ADD(-S) (mm)"
    if all(r["trans_m"] == 0 for r in rows):  # a rotation sweep: ADD(-S) forgives rotations, plot the noise
        x, xlabel = [r["rot_deg"] for r in rows], "rotation noise sigma (deg, random axis)"
    elif all(r["rot_deg"] == 0 for r in rows):
        x, xlabel = [1000 * r["trans_m"] for r in rows], "translation noise sigma (mm per axis)"
    y = [100 * r["rate"] for r in rows]
    err = [[100 * (r["rate"] - r["wilson95"][0]) for r in rows], [100 * (r["wilson95"][1] - r["rate"]) for r in rows]]
    fig, (ax, tab) = plt.subplots(1, 2, figsize=(11, 4.2), gridspec_kw={"width_ratios": [1.2, 1]})
    ax.errorbar(x, y, yerr=err, fmt="o-", capsize=4)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(f"{rows[0].get('task', 'pick-place')} success (%)")
    ax.set_ylim(-3, 103)
    ax.grid(alpha=0.3)
    tab.axis("off")
    cells = [[f"{r['trans_m'] * 1000:g}", f"{r['rot_deg']:g}", f"{1000 * (r['median_pose_error_m'] or 0.0):.1f}",
              f"{r['success']}/{r['n']}", f"{100 * r['wilson95'][0]:.0f}-{100 * r['wilson95'][1]:.0f}"] for r in rows]
    t = tab.table(cellText=cells, colLabels=["sigma t (mm)", "sigma r (deg)", "ADD(-S) mm", "success", "95 % CI (%)"],
                  loc="center")
    t.auto_set_font_size(False)
    t.set_fontsize(9)
    t.scale(1, 1.5)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    write_bytes(path, buf.getvalue())
