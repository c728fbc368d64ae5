"""The trial report: one self-contained ``DIR/report.html`` per trial run (``posegrasp report DIR``).

It holds the summary (success with its Wilson 95 % interval), the per-block and failure tables, success
against pose error, and sample frames like the paper's Fig. 9-10: a few episodes are re-simulated from their
recorded seeds up to the look capture (``grasping.episode``'s own functions, so the frame is the one the
provider saw) and drawn with the segmentation (the model's labels, or the ground-truth mask for the
oracles) and the block models rendered by pyrender at the estimated and at the true pose. The strip shows
the overview camera at the look pose of several episodes (episodes do not expose mid-episode frames).
Everything is embedded (PNG/JPEG data URIs, inline CSS); the page needs no network.
"""

from __future__ import annotations

import argparse
import base64
import html
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from posegrasp.errors import DatasetError, SimulationError, UserError
from posegrasp.executor import Executor
from posegrasp.grasping.record import FAILURES
from posegrasp.grasping.runfolder import CAMPAIGN, EPISODES, SUMMARY, read_campaign, read_json_object, read_records
from posegrasp.sim.camera import Frame
from posegrasp.gl import pyrender_renderer

REPORT = "report.html"
#: Outline colours (RGB) of the model at the true and at the estimated pose.
TRUE_RGB, EST_RGB = (40, 230, 60), (255, 40, 200)


@dataclass
class Look:
    """An episode's re-simulated look capture: the frame, the provider's estimates, labels and overview image."""

    frame: Frame
    estimates: list
    labels: np.ndarray
    overview: np.ndarray
    objects: str = ""  # the object set's folder (``""``: the shipped blocks)


def _resimulate_look_task(item: tuple[Path, dict]) -> Look | None:
    """``resimulate_look(*item)``: a plain function of one argument, as executors (Ray too) take."""
    return resimulate_look(*item)


def resimulate_look(run_dir: Path, rec: dict) -> Look | None:
    """Episode ``rec`` re-simulated from its seeds up to the look capture; None if it never got there."""
    from posegrasp.grasping.episode import EpisodeTask, capture_look, drive_to_look, episode_draws, episode_workcell
    from posegrasp.grasping.model_provider import ModelProvider
    from posegrasp.catalog import catalog_by_id
    from posegrasp.grasping.perception import PICK_LOOK, PerceptionError, observation, perceive
    from posegrasp.grasping.provider_registry import make_provider
    from posegrasp.sim.camera import CameraRenderer
    from posegrasp.sim.workcell import OVERVIEW_CAMERA

    campaign = read_campaign(run_dir)
    task = EpisodeTask(int(rec["seed"]), int(rec["episode"]), rec["perception"], campaign.config,
                       campaign.T_gripper_cam)
    n_blocks, scene_seed, percept_seed, _ = episode_draws(task)
    if scene_seed != rec["scene_seed"]:
        raise DatasetError(f"episode {rec['episode']} of {run_dir} does not re-simulate (scene seed {scene_seed} "
                           f"!= recorded {rec['scene_seed']}): the code changed since the run; rerun the trials")
    try:
        wc = episode_workcell(task.cfg, scene_seed, n_blocks)
    except SimulationError:  # a scene that never settles (recorded as a simulation error)
        return None
    if not drive_to_look(wc, task.cfg.control):
        return None
    frame = capture_look(wc)
    provider = make_provider(task.perception, wc.cfg.objects)
    if isinstance(provider, ModelProvider):  # its class map too, from the same single run of the network
        result = provider.perceive(observation(frame, task.index, PICK_LOOK))
        ests, labels = provider.select(result), result.labels
    else:
        try:
            ests = perceive(provider, frame, percept_seed, task.index, PICK_LOOK,
                            known_ids=catalog_by_id(wc.cfg.objects), timeout_s=task.cfg.perception_timeout_s)
        except PerceptionError:  # the episode's "perception error": no estimates to draw
            ests = []
        labels = frame.mask
    cam = CameraRenderer.from_config(wc, OVERVIEW_CAMERA, wc.cfg.overview_camera, wc.cfg.render)
    overview = cam.rgb()
    cam.close()
    return Look(frame, ests, np.asarray(labels), overview, wc.cfg.objects)


def silhouette(block, T_cam_obj: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixels covered by ``block``'s mesh at ``T_cam_obj`` (OpenCV camera, m), rendered by pyrender."""
    import pyrender
    import trimesh

    r = pyrender_renderer(width, height)
    # pyrender's principal point is in pixel-edge coordinates; OpenCV's K uses pixel centres.
    cam = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, znear=0.02, zfar=5.0)
    sc = pyrender.Scene()
    sc.add(pyrender.Mesh.from_trimesh(trimesh.Trimesh(block.vertices, block.faces, process=False), smooth=False),
           pose=T_cam_obj)
    sc.add(cam, pose=np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenCV camera -> OpenGL camera
    return r.render(sc, flags=pyrender.RenderFlags.DEPTH_ONLY) > 0


def _outline(mask: np.ndarray, width: int = 2) -> np.ndarray:
    """Boundary pixels (``width`` px thick) of a bool mask."""
    inner = mask.copy()
    for _ in range(width):
        p = np.pad(inner, 1)
        inner = inner & p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
    return mask & ~inner


def segmentation_overlay(rgb: np.ndarray, labels: np.ndarray, alpha: float = 0.6) -> np.ndarray:
    """RGB (dimmed) with each nonzero label tinted in its own colour and outlined (uint8)."""
    rng = np.random.default_rng(7)
    colours = rng.integers(60, 256, size=(int(labels.max()) + 1, 3))
    out = 0.7 * rgb.astype(np.float32)
    fg = labels > 0
    out[fg] = (1 - alpha) * out[fg] + alpha * colours[labels[fg]]
    for v in np.unique(labels[fg]):
        out[_outline(labels == v, 1)] = colours[v]
    return out.astype(np.uint8)


def pose_overlay(look: Look) -> np.ndarray:
    """RGB (dimmed) with the block outlines at the true pose (green) and at the estimated pose (magenta)."""
    from posegrasp.catalog import catalog_by_id

    f = look.frame
    h, w = f.mask.shape
    cat = catalog_by_id(look.objects)
    out = (0.75 * f.rgb).astype(np.uint8)
    visible = np.unique(f.mask[f.mask > 0])
    for k in visible:  # thick, so that an estimate drawn on top of it leaves it visible
        out[_outline(silhouette(cat[int(f.obj_ids[k - 1])], f.T_cam_obj[k - 1], f.K, w, h), 4)] = TRUE_RGB
    for e in look.estimates:
        out[_outline(silhouette(cat[e.obj_id], e.T_cam_obj, f.K, w, h), 2)] = EST_RGB
    return out


def _data_uri(rgb: np.ndarray, fmt: str = "jpeg") -> str:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format=fmt.upper(), **({"quality": 88} if fmt == "jpeg" else {}))
    return f"data:image/{fmt};base64,{base64.b64encode(buf.getvalue()).decode()}"


def _adds_mm(rec: dict) -> float | None:
    return 1000 * rec["pose_error"]["err"] if rec.get("pose_error") else None


def _rotation_deg(rec: dict) -> float | None:
    return rec["estimate_error"]["re_deg"] if rec.get("estimate_error") else None


def error_plot(records: list[dict], value=_adds_mm,
               xlabel: str = "pose error of the grasped estimate, ADD(-S) (mm)") -> str | None:
    """PNG data URI: each episode's outcome against its perception error ``value(record)`` (None: no
    estimate), with binned success rates."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from posegrasp.grasping.stats import wilson

    pts = [(value(r), r["outcome"] == "success") for r in records if value(r) is not None]
    if not pts:
        return None
    x = np.array([p[0] for p in pts])
    y = np.array([p[1] for p in pts], dtype=float)
    jitter = np.random.default_rng(0).uniform(-0.04, 0.04, len(x))
    fig, ax = plt.subplots(figsize=(7.5, 3.6))
    ax.scatter(x, 100 * (y + jitter), s=14, c=np.where(y > 0, "tab:green", "tab:red"), alpha=0.7,
               label="episodes (100 = success, 0 = failure)")
    edges = np.unique(np.quantile(x, np.linspace(0, 1, min(5, len(x)) + 1)))
    if len(edges) > 1:
        idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
        mids, rates, lo, hi = [], [], [], []
        for b in range(len(edges) - 1):
            sel = idx == b
            if sel.any():
                k, n = int(y[sel].sum()), int(sel.sum())
                a, c = wilson(k, n)
                mids.append(float(np.median(x[sel])))
                rates.append(100 * k / n)
                lo.append(100 * (k / n - a))
                hi.append(100 * (c - k / n))
        ax.errorbar(mids, rates, yerr=[lo, hi], fmt="o-", color="tab:blue", capsize=4,
                    label="binned success rate (Wilson 95 %)")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("success (%)")
    ax.set_ylim(-8, 108)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return f"data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}"


def _pick_samples(records: list[dict], n: int) -> list[dict]:
    """The first successes and the first failures, up to ``n`` episodes in all (failures get half)."""
    fail = [r for r in records if r["outcome"] != "success"]
    ok = [r for r in records if r["outcome"] == "success"]
    nf = min(len(fail), n // 2)
    chosen = fail[:nf] + ok[: n - nf]
    chosen += fail[nf: nf + n - len(chosen)]
    return sorted(chosen, key=lambda r: r["episode"])


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def _interval(w: list[float]) -> str:
    return f"{100 * w[0]:.1f}-{100 * w[1]:.1f} %"


def _table(head: list[str], rows: list[list[str]]) -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def _caption(rec: dict) -> str:
    t = rec.get("target") or {}
    pe = rec.get("pose_error")
    err = f", {pe['metric']} {1000 * pe['err']:.1f} mm, rot {pe['re_deg']:.1f} deg" if pe else ""
    what = "success" if rec["outcome"] == "success" else f"failure: {rec['failure']}"
    target = t.get("type", "a false detection (no block)" if t else "-")
    why = f" ({rec['perception_error']})" if rec.get("perception_error") else ""
    return (f"episode {rec['episode']} ({what}{why}); target {target}{err}; "
            f"{rec['n_blocks']} blocks, {rec['detected']} detected")


_CSS = """body{font-family:sans-serif;margin:24px;color:#222;max-width:1400px}
table{border-collapse:collapse;margin:8px 0 20px}td,th{border:1px solid #ccc;padding:4px 10px;text-align:right}
th{background:#eee}td:first-child{text-align:left}.big{font-size:1.4em}
figure{display:inline-block;margin:6px;vertical-align:top}figcaption{font-size:.85em;max-width:420px}
img{border:1px solid #999}.key{display:inline-block;width:14px;height:14px;vertical-align:middle}"""
#: Sets the page title to the number of images the browser decoded (checked by the headless-browser test).
_SCRIPT = """<script>window.addEventListener('load',function(){var im=document.images,n=0;
for(var i=0;i<im.length;i++){if(im[i].complete&&im[i].naturalWidth>0)n++;}
document.title='images decoded: '+n+'/'+im.length;});</script>"""


def write_report(run_dir: Path, samples: int = 4, strip: int = 6, executor: Executor | None = None) -> Path:
    """Write ``run_dir/report.html`` from its ``episodes.jsonl``, ``summary.json`` and ``campaign.json``;
    ``samples`` episodes get Fig. 9-10 style frames, ``strip`` episodes an overview snapshot, re-simulated by
    ``executor`` (a campaign's warm workers) or in this process. Returns the path."""
    from posegrasp.grasping.stats import summarise
    from posegrasp.io import atomic_write

    run_dir = Path(run_dir)
    for name in (EPISODES, CAMPAIGN):
        if not (run_dir / name).is_file():
            raise DatasetError(f"{run_dir} has no {name}: give a folder written by 'posegrasp trials --out'")
    if samples < 0 or strip < 0:
        raise UserError(f"--samples and --strip must be >= 0, got {samples} and {strip}")
    records = [r for _, r in sorted(read_records(run_dir / EPISODES).items())]
    if not records:
        raise DatasetError(f"{run_dir / EPISODES} holds no finished episode: run (or resume) the trials first")
    campaign = read_campaign(run_dir)
    s = read_json_object(run_dir / SUMMARY) if (run_dir / SUMMARY).is_file() else summarise(records)
    perception = campaign.perception

    looks: dict[int, Look | None] = {}
    if executor is not None:
        shown = {r["episode"]: r for r in _pick_samples(records, samples) + records[:strip]}
        recs = [shown[e] for e in sorted(shown)]
        for i, lk in executor.imap(_resimulate_look_task, [(run_dir, r) for r in recs]):
            looks[recs[i]["episode"]] = lk

    def look(rec: dict) -> Look | None:
        if rec["episode"] not in looks:
            looks[rec["episode"]] = resimulate_look(run_dir, rec)
        return looks[rec["episode"]]

    task = campaign.config.task
    parts = [f"<h1>Grasp trials, task {html.escape(task)}: {html.escape(perception)}</h1>",
             f"<p class=big><b>{s['success']}/{s['n']}</b> episodes succeeded = <b>{_pct(s['rate'])}</b> "
             f"(Wilson 95 % interval {_interval(s['wilson95'])}); grasp success "
             f"{s['grasp_success']['success']}/{s['n']} = {_pct(s['grasp_success']['rate'])} "
             f"({_interval(s['grasp_success']['wilson95'])})</p>",
             _table(["setting", "value"], [["task", task], ["perception", perception], ["episodes", str(len(records))],
                                           ["campaign seed", str(campaign.seed)],
                                           ["object set", f"{campaign.set_record()['name']} "
                                                          f"({campaign.set_record()['path']})"],
                                           ["mean pose error (ADD(-S))", "-" if s.get("mean_pose_error_m") is None
                                            else f"{1000 * s['mean_pose_error_m']:.2f} mm"],
                                           ["mean simulated time per episode", f"{s['mean_sim_time_s']:.1f} s"],
                                           ["run folder", str(run_dir.resolve())]]),
             "<h2>Per target block</h2>",
             _table(["block", "success", "n", "rate", "95 % interval"],
                    [[b, str(r["success"]), str(r["n"]), _pct(r["rate"]), _interval(r["wilson95"])]
                     for b, r in s["per_block"].items()]),
             "<h2>Failures</h2>"]
    fails = [[f, str(s["failures"][f]), _pct(s["failures"][f] / s["n"]),
              ", ".join(str(r["episode"]) for r in records if r["failure"] == f)]
             for f in FAILURES if s["failures"].get(f)]
    parts.append(_table(["reason", "count", "share of episodes", "episodes"], fails) if fails else "<p>none</p>")
    parts.append("<h2>Success against pose error</h2>")
    plot = error_plot(records)
    parts.append(f'<img alt="success against pose error" src="{plot}">' if plot
                 else "<p>no episode has a pose error (nothing was detected)</p>")
    rot = error_plot(records, _rotation_deg, "rotation error of the grasped estimate, modulo symmetries (deg)")
    if rot:  # kitting and stack: the whole pose matters, and ADD(-S) forgives a block turned or upside down
        parts.append(f"<h2>Success against rotation error ({html.escape(task)})</h2>"
                     f'<img alt="success against rotation error" src="{rot}">')
    key = (f'<span class=key style="background:rgb{TRUE_RGB}"></span> model at the true pose &nbsp; '
           f'<span class=key style="background:rgb{EST_RGB}"></span> model at the estimated pose')
    seg = "the model's segmentation" if perception.startswith("model") else "the ground-truth instance mask"
    parts.append(f"<h2>Sample frames</h2><p>Hand camera at the look pose, re-simulated from the recorded seeds. "
                 f"Left: {seg}. Right: {key}.</p>")
    for rec in _pick_samples(records, samples):
        lk = look(rec)
        if lk is None:
            parts.append(f"<p>{html.escape(_caption(rec))}: the arm never reached the look pose</p>")
            continue
        cap = html.escape(_caption(rec))
        parts.append(f'<div><figure><img alt="segmentation" width="480" src="{_data_uri(segmentation_overlay(lk.frame.rgb, lk.labels))}">'
                     f'<figcaption>{cap}: segmentation</figcaption></figure>'
                     f'<figure><img alt="poses" width="480" src="{_data_uri(pose_overlay(lk))}">'
                     f'<figcaption>{cap}: true (green) and estimated (magenta) pose</figcaption></figure></div>')
    parts.append("<h2>Episode strip</h2><p>The overview camera at the look pose (the moment the hand camera is "
                 "captured) of the first episodes: a strip of look captures across episodes, not phases of one.</p>")
    for rec in records[:strip]:
        lk = look(rec)
        if lk is not None:
            what = "success" if rec["outcome"] == "success" else rec["failure"]
            parts.append(f'<figure><img alt="overview" width="320" src="{_data_uri(lk.overview)}">'
                         f'<figcaption>episode {rec["episode"]}: {html.escape(what)}</figcaption></figure>')
    page = (f"<!DOCTYPE html><html><head><meta charset=utf-8><title>trial report</title><style>{_CSS}</style>"
            f"{_SCRIPT}</head><body>{''.join(parts)}</body></html>")
    path = run_dir / REPORT
    atomic_write(path, lambda p: p.write_text(page))
    return path


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
