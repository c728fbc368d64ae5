"""The report page, one function per section: each takes the run's typed records and returns its HTML; ``page``
wraps the sections in the document (inline CSS, the image-count script)."""

from __future__ import annotations

import html
from typing import Iterable, Mapping

from posegrasp.grasping.record import FAILURES, EpisodeRecord, Target
from posegrasp.grasping.report.figures import (EST_RGB, TRUE_RGB, Look, data_uri, error_plot, pose_overlay, rotation_deg,
                                               segmentation_overlay)
from posegrasp.grasping.report.run import Rate, TrialRun

_CSS = """body{font-family:sans-serif;margin:24px;color:#222;max-width:1400px}
table{border-collapse:collapse;margin:8px 0 20px}td,th{border:1px solid #ccc;padding:4px 10px;text-align:right}
th{background:#eee}td:first-child{text-align:left}.big{font-size:1.4em}
figure{display:inline-block;margin:6px;vertical-align:top}figcaption{font-size:.85em;max-width:420px}
img{border:1px solid #999}.key{display:inline-block;width:14px;height:14px;vertical-align:middle}"""
#: Sets the page title to the number of images the browser decoded (checked by the headless-browser test).
_SCRIPT = """<script>window.addEventListener('load',function(){var im=document.images,n=0;
for(var i=0;i<im.length;i++){if(im[i].complete&&im[i].naturalWidth>0)n++;}
document.title='images decoded: '+n+'/'+im.length;});</script>"""


def pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def interval(r: Rate) -> str:
    return f"{100 * r.wilson95[0]:.1f}-{100 * r.wilson95[1]:.1f} %"


def table(head: list[str], rows: list[list[str]]) -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def _outcome(rec: EpisodeRecord) -> str:
    return "success" if rec.outcome == "success" else f"failure: {rec.failure}"


def caption(rec: EpisodeRecord) -> str:
    """One line on an episode (plain text): outcome, target, pose error, blocks in the scene and detected."""
    t, pe = rec.target, rec.pose_error
    err = f", {pe.metric} {1000 * pe.err:.1f} mm, rot {pe.re_deg:.1f} deg" if pe else ""
    target = t.type if isinstance(t, Target) else "a false detection (no block)" if t else "-"
    why = f" ({rec.perception_error})" if rec.perception_error else ""
    return (f"episode {rec.episode} ({_outcome(rec)}{why}); target {target}{err}; "
            f"{rec.n_blocks} blocks, {rec.detected} detected")


def headline(run: TrialRun) -> str:
    """Title (task, perception) and the success and grasp-success rates with their intervals."""
    task, s = run.campaign.config.task, run.summary
    return (f"<h1>Grasp trials, task {html.escape(task)}: {html.escape(run.campaign.perception)}</h1>"
            f"<p class=big><b>{s.overall.success}/{s.overall.n}</b> episodes succeeded = "
            f"<b>{pct(s.overall.rate)}</b> (Wilson 95 % interval {interval(s.overall)}); grasp success "
            f"{s.grasp_success.success}/{s.overall.n} = {pct(s.grasp_success.rate)} "
            f"({interval(s.grasp_success)})</p>")


def settings(run: TrialRun) -> str:
    """What the run was made with, its mean pose error and simulated time, and where it lies."""
    c, s = run.campaign, run.summary
    objects = c.set_record()
    return table(["setting", "value"], [
        ["task", c.config.task], ["perception", c.perception], ["episodes", str(len(run.episodes))],
        ["campaign seed", str(c.seed)], ["object set", f"{objects['name']} ({objects['path']})"],
        ["mean pose error (ADD(-S))", "-" if s.mean_pose_error_m is None else f"{1000 * s.mean_pose_error_m:.2f} mm"],
        ["mean simulated time per episode", f"{s.mean_sim_time_s:.1f} s"],
        ["run folder", str(run.path.resolve())]])


def per_block(run: TrialRun) -> str:
    """Success by target block, with intervals."""
    return "<h2>Per target block</h2>" + table(
        ["block", "success", "n", "rate", "95 % interval"],
        [[b, str(r.success), str(r.n), pct(r.rate), interval(r)] for b, r in run.summary.per_block.items()])


def failures(run: TrialRun) -> str:
    """Failure reasons in ``FAILURES`` order: count, share and the episodes."""
    s = run.summary
    rows = [[f, str(s.failures[f]), pct(s.failures[f] / s.overall.n),
             ", ".join(str(r.episode) for r in run.episodes if r.failure == f)]
            for f in FAILURES if s.failures.get(f)]
    return "<h2>Failures</h2>" + (table(["reason", "count", "share of episodes", "episodes"], rows) if rows
                                  else "<p>none</p>")


def error_plots(run: TrialRun) -> str:
    """Success against the grasped estimate's ADD(-S); against its rotation error too where the task records it
    (kitting and stack: the whole pose matters, and ADD(-S) forgives a block turned or upside down)."""
    plot = error_plot(run.episodes)
    out = "<h2>Success against pose error</h2>" + (f'<img alt="success against pose error" src="{plot}">' if plot
                                                   else "<p>no episode has a pose error (nothing was detected)</p>")
    rot = error_plot(run.episodes, rotation_deg, "rotation error of the grasped estimate, modulo symmetries (deg)")
    if rot:
        out += (f"<h2>Success against rotation error ({html.escape(run.campaign.config.task)})</h2>"
                f'<img alt="success against rotation error" src="{rot}">')
    return out


def sample_frames(run: TrialRun, episodes: Iterable[EpisodeRecord], looks: Mapping[int, Look | None]) -> str:
    """Fig. 9-10 style frames of ``episodes``: the hand camera at the look pose with the segmentation, and with
    the models at the true and at the estimated pose."""
    key = (f'<span class=key style="background:rgb{TRUE_RGB}"></span> model at the true pose &nbsp; '
           f'<span class=key style="background:rgb{EST_RGB}"></span> model at the estimated pose')
    model = run.campaign.perception.startswith("model")
    seg = "the model's segmentation" if model else "the ground-truth instance mask"
    out = [f"<h2>Sample frames</h2><p>Hand camera at the look pose, re-simulated from the recorded seeds. "
           f"Left: {seg}. Right: {key}.</p>"]
    for rec in episodes:
        lk, cap = looks[rec.episode], html.escape(caption(rec))
        if lk is None:
            out.append(f"<p>{cap}: the arm never reached the look pose</p>")
            continue
        out.append(f'<div><figure><img alt="segmentation" width="480" '
                   f'src="{data_uri(segmentation_overlay(lk.frame.rgb, lk.labels))}">'
                   f'<figcaption>{cap}: segmentation</figcaption></figure>'
                   f'<figure><img alt="poses" width="480" src="{data_uri(pose_overlay(lk))}">'
                   f'<figcaption>{cap}: true (green) and estimated (magenta) pose</figcaption></figure></div>')
    return "".join(out)


def episode_strip(episodes: Iterable[EpisodeRecord], looks: Mapping[int, Look | None]) -> str:
    """The overview camera at the look pose of ``episodes`` (those that reached it)."""
    out = ["<h2>Episode strip</h2><p>The overview camera at the look pose (the moment the hand camera is "
           "captured) of the first episodes: a strip of look captures across episodes, not phases of one.</p>"]
    for rec in episodes:
        lk = looks[rec.episode]
        if lk is not None:
            what = "success" if rec.outcome == "success" else rec.failure
            out.append(f'<figure><img alt="overview" width="320" src="{data_uri(lk.overview)}">'
                       f'<figcaption>episode {rec.episode}: {html.escape(what)}</figcaption></figure>')
    return "".join(out)


def pick_samples(records: list[EpisodeRecord], n: int) -> list[EpisodeRecord]:
    """The first successes and the first failures, up to ``n`` episodes in all (failures get half), by index."""
    fail = [r for r in records if r.outcome != "success"]
    ok = [r for r in records if r.outcome == "success"]
    nf = min(len(fail), n // 2)
    chosen = fail[:nf] + ok[: n - nf]
    chosen += fail[nf: nf + n - len(chosen)]
    return sorted(chosen, key=lambda r: r.episode)


def page(sections: Iterable[str]) -> str:
    """The self-contained HTML document holding ``sections`` in order."""
    return (f"<!DOCTYPE html><html><head><meta charset=utf-8><title>trial report</title><style>{_CSS}</style>"
            f"{_SCRIPT}</head><body>{''.join(sections)}</body></html>")
