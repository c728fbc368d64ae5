"""Bin picking's report page: its verdict in the headline (percent cleared, attempt and grasp success), its
statistics, and the attempts of a few episodes; for the oracle providers those episodes replayed whole
(``report.replay``): each failed attempt's capture with the estimates, the tote before and after, a film."""

from __future__ import annotations

import html
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable, Mapping

from posegrasp.errors import DatasetError
from posegrasp.grasping.record import Target
from posegrasp.grasping.report import sections
from posegrasp.grasping.report.figures import EST_RGB, TRUE_RGB, animation_uri, data_uri, figure_uri, pose_overlay
from posegrasp.grasping.report.replay import REPLAYED, Replay, replay_episodes, replayable
from posegrasp.grasping.report.run import Rate, TrialRun, rate_of
from posegrasp.grasping.report.sections import interval, pct, table
from posegrasp.grasping.runfolder import SUMMARY
from posegrasp.grasping.tasks.bin_pick.record import Attempt, BinPickRecord

if TYPE_CHECKING:
    from posegrasp.executor import Executor
    from posegrasp.grasping.episode import EpisodeJob
    from posegrasp.grasping.tasks.base import Task

#: Episodes shown at most (each replayed whole: its film and failed captures).
SHOWN = 2


@dataclass(frozen=True)
class BinPickSummary:
    """Bin picking's summary (``summary.json``'s ``bin_pick``, ``tasks.bin_pick.bin_metrics``)."""

    percent_cleared: float | None  # mean over the episodes (%)
    percent_cleared_ci95: tuple[float, float] | None  # its Student-t 95 % interval (None: under 2 episodes)
    episodes_cleared: int
    parts_present: int
    parts_removed: int
    attempts: Rate  # attempts that put their part alone into the out-box
    grasps: Rate | None  # those of the attempts that went for a part (None: a summary written before it was kept)
    sim_hours: float
    picks_per_sim_hour: float | None
    attempt_failures: dict[str, int]  # attempts by failure reason
    episode_ends: dict[str, int]  # episodes by how they ended ("cleared" or a failure reason)
    per_type: dict[str, Rate]  # attempts by the target's part type
    per_visibility: dict[str, Rate]  # attempts by the target's visible fraction (``VISIBILITY_BINS``)
    picks_per_hour: float | None = None  # of the cycle time: the arm's and perception's (``grasping.latency``)

    @classmethod
    def from_json(cls, data: dict, where: str) -> BinPickSummary:
        """The ``bin_pick`` block ``data``; a DatasetError naming ``where``."""
        try:
            pc = data["percent_cleared"]
            return cls(None if pc["mean"] is None else float(pc["mean"]),
                       None if pc["ci95"] is None else (float(pc["ci95"][0]), float(pc["ci95"][1])),
                       int(data["episodes_cleared"]), int(data["parts_present"]), int(data["parts_removed"]),
                       rate_of(data["attempts"], f"{where}.attempts"),
                       rate_of(data["grasps"], f"{where}.grasps") if "grasps" in data else None, float(data["sim_hours"]),
                       None if data["picks_per_sim_hour"] is None else float(data["picks_per_sim_hour"]),
                       {str(f): int(k) for f, k in data["attempt_failures"].items()},
                       {str(f): int(k) for f, k in data["episode_ends"].items()},
                       {str(t): rate_of(r, f"{where}.per_type.{t}") for t, r in data["per_type"].items()},
                       {str(b): rate_of(r, f"{where}.per_visibility.{b}") for b, r in data["per_visibility"].items()},
                       None if data.get("picks_per_hour") is None else float(data["picks_per_hour"]))
        except (KeyError, TypeError, ValueError, AttributeError, IndexError):
            raise DatasetError(f"{where} is corrupt (needs the keys of bin picking's summary); rerun the trials "
                               "into a new --out") from None


def rates(title: str, head: str, rates: Mapping[str, Rate]) -> str:
    return f"<h3>{html.escape(title)}</h3>" + table(
        [head, "success", "n", "rate", "95 % interval"],
        [[k, str(r.success), str(r.n), pct(r.rate), interval(r)] for k, r in rates.items()])


def counts(title: str, head: str, counts: Mapping[str, int]) -> str:
    return f"<h3>{html.escape(title)}</h3>" + (table([head, "count"], [[k, str(v)] for k, v in counts.items()])
                                               if counts else "<p>none</p>")


def statistics(run: TrialRun, b: BinPickSummary) -> str:
    """Bin picking's statistics: percent cleared, attempt and grasp success, picks per simulated hour, attempt
    failures and episode ends by reason, attempt success by part type and by the target's visible fraction."""
    cleared = "-" if b.percent_cleared is None else f"{b.percent_cleared:.1f} %"
    if b.percent_cleared_ci95 is not None:
        cleared += f" (t 95 % interval {b.percent_cleared_ci95[0]:.1f}-{b.percent_cleared_ci95[1]:.1f} %)"
    per_hour = "-" if b.picks_per_sim_hour is None else f"{b.picks_per_sim_hour:.0f}"
    a, g = b.attempts, b.grasps
    return ("<h2>Bin picking</h2>" + table(["measure", "value"], [
        ["parts cleared per episode (mean)", cleared],
        ["totes emptied", f"{b.episodes_cleared}/{run.summary.overall.n}"],
        ["parts removed", f"{b.parts_removed}/{b.parts_present}"],
        ["attempt success", f"{a.success}/{a.n} = {pct(a.rate)} (Wilson 95 % interval {interval(a)})"],
        ["grasp success (attempts that went for a part)",
         "-" if g is None else f"{g.success}/{g.n} = {pct(g.rate)} (Wilson 95 % interval {interval(g)})"],
        ["picks per hour (the arm's motion and perception's latency)",
         "-" if b.picks_per_hour is None else f"{b.picks_per_hour:.0f}"],
        ["picks per simulated hour (the arm's motion)", per_hour], ["simulated hours", f"{b.sim_hours:.3f}"]])
        + counts("Failed attempts", "reason", b.attempt_failures)
        + counts("Episode ends", "end", b.episode_ends)
        + rates("Attempt success by part type", "part type", b.per_type)
        + rates("Attempt success by the target's visible fraction", "visible fraction", b.per_visibility))


def _attempt_row(a: Attempt) -> list[str]:
    t = a.target
    target = t.type if isinstance(t, Target) else "a false detection (no part)" if t else "-"
    vis = "-" if a.visib_fract is None else f"{a.visib_fract:.2f}"
    err = "-" if a.pose_error is None else f"{a.pose_error.metric} {1000 * a.pose_error.err:.1f} mm"
    return [str(a.attempt), target, vis, err, a.outcome, a.failure or "-", f"{a.sim_time:.1f} s"]


def attempts(run: TrialRun, episodes: Iterable[BinPickRecord], replays: Mapping[int, Replay | None]) -> str:
    """Per shown episode: its attempts, and the hand camera's capture of each failed attempt with the models at
    the true and at the provider's estimated poses (replayed episodes only)."""
    key = (f'<span class=key style="background:rgb{TRUE_RGB}"></span> model at the true pose &nbsp; '
           f'<span class=key style="background:rgb{EST_RGB}"></span> model at the estimated pose')
    out = [f"<h2>Attempts</h2><p>Each attempt of the shown episodes; below a table, the hand camera's capture of "
           f"each failed attempt, replayed from the recorded seeds: {key}.</p>"]
    if not replayable(run.campaign.perception):
        out.append(f"<p>Episodes are replayed for the providers {', '.join(REPLAYED)} only (a model's network would "
                   "run at every attempt again): no captures, tote images or film for this run.</p>")
    for rec in episodes:
        end = "tote emptied" if rec.outcome == "success" else f"ended: {rec.failure}"
        out.append(f"<h3>Episode {rec.episode} ({html.escape(end)}): {rec.removed}/{rec.n_blocks} parts removed in "
                   f"{len(rec.attempts)} attempts, {rec.sim_time:.1f} s simulated</h3>")
        out.append(table(["attempt", "target", "visible fraction", "estimate error", "outcome", "failure",
                           "simulated time"], [_attempt_row(a) for a in rec.attempts]) if rec.attempts
                   else "<p>no attempt</p>")
        rp = replays.get(rec.episode)
        for a in rec.attempts:
            lk = rp.looks.get(a.attempt) if rp is not None else None
            if lk is not None:
                cap = html.escape(f"episode {rec.episode}, attempt {a.attempt}: {a.failure}")
                out.append(f'<figure><img alt="failed attempt" width="480" src="{data_uri(pose_overlay(lk))}">'
                           f"<figcaption>{cap}</figcaption></figure>")
    return "".join(out)


def films(episodes: Iterable[BinPickRecord], replays: Mapping[int, Replay | None]) -> str:
    """Per replayed episode: the overview camera's tote before the first and after the last attempt, and a film
    of the episode (an animated GIF)."""
    out = ["<h2>The tote, before and after</h2><p>The overview camera, replayed from the recorded seeds: the tote "
           "before the first attempt, after the last (parts in the out-box are taken out of the scene), and the "
           "episode as a film.</p>"]
    for rec in episodes:
        rp = replays.get(rec.episode)
        if rp is None:
            continue
        speed = f"a frame every {rp.period_s:.2f} s of simulated time, shown in real time"
        out.append(f'<div><figure><img alt="tote before" width="320" src="{data_uri(rp.before)}">'
                   f"<figcaption>episode {rec.episode}: before</figcaption></figure>"
                   f'<figure><img alt="tote after" width="320" src="{data_uri(rp.after)}">'
                   f"<figcaption>episode {rec.episode}: after ({rec.removed}/{rec.n_blocks} removed)</figcaption>"
                   f'</figure><figure><img class=film alt="episode film" width="320" '
                   f'src="{animation_uri(rp.film, rp.period_s)}"><figcaption>episode {rec.episode}: '
                   f"{len(rp.film)} frames, {speed}</figcaption></figure></div>")
    return "".join(out)


def headline(run: TrialRun, b: BinPickSummary) -> str:
    """Title (task, perception) and bin picking's verdict: percent cleared, attempt and grasp success."""
    cleared = "-" if b.percent_cleared is None else f"{b.percent_cleared:.1f} %"
    g = b.grasps
    grasps = "" if g is None else f"; grasp success {g.success}/{g.n} = {pct(g.rate)} ({interval(g)})"
    return (f"<h1>Grasp trials, task {html.escape(run.campaign.config.task)}: "
            f"{html.escape(run.campaign.perception)}</h1><p class=big>cleared <b>{cleared}</b> of the parts per "
            f"episode; attempt success <b>{b.attempts.success}/{b.attempts.n} = {pct(b.attempts.rate)}</b> "
            f"(Wilson 95 % interval {interval(b.attempts)}){grasps}</p>")


def tray_section(run: TrialRun, tray: dict | None) -> str:
    """The tray's statistics (``metrics.tray_metrics``) and a plot of the set-down parts' errors against their
    slots with the tolerances; empty for an out-box run."""
    if not tray:
        return ""
    b = run.campaign.config.bin_pick
    errs = [a.place_error for r in run.episodes for a in getattr(r, "attempts", ()) if a.place_error]
    p, pos, yaw = tray["placed"], tray["position_error_mm"], tray["yaw_error_deg"]
    rows = [["placement success per attempt", f"{p['success']}/{p['n']} = {pct(p['rate'])}"],
            ["parts placed per episode (mean)", f"{tray['placed_per_episode']['mean']:.2f}"],
            ["parts set down in a slot", str(tray["set_down"])]]
    if tray["set_down"]:
        rows += [["position error (mm): median, 90 %, largest", f"{pos['median']:.2f}, {pos['p90']:.2f}, {pos['max']:.2f}"],
                 ["yaw error (deg): median, 90 %, largest", f"{yaw['median']:.2f}, {yaw['p90']:.2f}, {yaw['max']:.2f}"]]
    out = f"<h2>Tray</h2>{table(['measure', 'value'], rows)}"
    if errs:
        out += (f'<figure><img alt="placement errors" src="{_error_scatter(errs, b.pos_tol, b.yaw_tol_deg)}">'
                "<figcaption>each part set down: its position error against its yaw error, modulo its "
                "symmetries; the box is the tolerance</figcaption></figure>")
    return out


def _error_scatter(errs: list[dict], pos_tol: float, yaw_tol_deg: float) -> str:
    """PNG data URI: position error (mm) against yaw error (deg) per placed part, the tolerance drawn as a box."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    ax.scatter([e["yaw_deg"] for e in errs], [1000 * e["te"] for e in errs], s=14, alpha=0.7)
    ax.add_patch(plt.Rectangle((-yaw_tol_deg, 0), 2 * yaw_tol_deg, 1000 * pos_tol, fill=False, color="tab:green"))
    ax.set_xlabel("yaw error (deg)")
    ax.set_ylabel("position error (mm)")
    ax.grid(alpha=0.3)
    return figure_uri(fig)


def perception_seed(job: EpisodeJob, attempt: int) -> int:
    """The perception seed of ``attempt`` (its capture's ``im_id``), as ``attempt.empty_tote`` draws it."""
    from posegrasp.grasping.episode import episode_draws, further_seed

    return episode_draws(job)[2] if attempt == 0 else further_seed(job, attempt)


def page(task: Task, run: TrialRun, samples: int, executor: Executor | None) -> str:
    """The page of a bin-picking run: its verdict and statistics, the attempts of up to ``SHOWN`` of the
    ``samples`` episodes shown and, for the oracle providers, those episodes replayed (failed captures, tote,
    film)."""
    from posegrasp.grasping.episode import EpisodeJob
    shown = sections.pick_samples(run.episodes, min(samples, SHOWN))
    replays = {}
    if replayable(run.campaign.perception):
        c = run.campaign
        jobs = [(EpisodeJob(task, r.seed, r.episode, r.perception, c.config, c.T_gripper_cam), r,
                 frozenset(a.attempt for a in r.attempts if a.outcome != "success")) for r in shown]
        replays = replay_episodes(jobs, perception_seed, executor)
    b = BinPickSummary.from_json(run.summary.data["bin_pick"], f"{run.path / SUMMARY}.bin_pick")
    tray = run.summary.data["bin_pick"].get("tray")
    return sections.page([headline(run, b), sections.settings(run), statistics(run, b), tray_section(run, tray),
                          attempts(run, shown, replays), films(shown, replays)])
