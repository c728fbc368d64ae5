"""Generating a BOP dataset: one simulated scene per BOP scene folder, scenes fanned out to worker processes.

A scene's content depends only on (seed, scene id, settings): its random streams come from
``SeedSequence([seed, scene_id])``, so the dataset is the same for any worker count, and a killed run resumes
by skipping complete scenes (``scene_gt_info.json`` present) and regenerating the others from scratch.
Workers return a scene's encoded files and this process writes them, holding the folder's lock
(``posegrasp.lock``); a split's settings bind once one of its scenes is complete.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from posegrasp.datagen.config import DatagenConfig, validate
from posegrasp.datagen.noise import noisy_depth, noisy_rgb
from posegrasp.datagen.render import LabelRenderer
from posegrasp.datagen.scene import build_scene, check_capacity
from posegrasp.datagen.views import ViewStats, visit_views
from posegrasp.datagen.writer import COMPLETE_FILE, SceneWriter, has_scenes, prepare_root, write_models_eval
from posegrasp import bop, inputs
from posegrasp import io as pio
from posegrasp.errors import ConfigError, DatasetError, SceneUnsettled
from posegrasp.executor import make_executor
from posegrasp.lock import folder_lock
from posegrasp.outputs import Record
from posegrasp.sim.camera import intrinsics
from posegrasp.sim.config import workcell_record
from posegrasp.sim.workcell import HAND_CAMERA

SPLITS = ("train_pbr", "test")
SETTINGS_FILE = "datagen_config.json"
STATS_FILE = "datagen_stats.json"


@dataclass(frozen=True)
class SceneJob:
    """Everything a worker needs to generate one scene (no path: workers never touch the dataset)."""

    split: str
    scene_id: int
    seed: int
    views: int
    cfg: DatagenConfig


def rgb_extension(cfg: DatagenConfig, split: str) -> str:
    """``jpg`` or ``png``; ``auto`` follows the BOP datasets (jpg for train_pbr, png otherwise)."""
    if cfg.rgb_format == "auto":
        return "jpg" if split == "train_pbr" else "png"
    return cfg.rgb_format


def is_complete(root: str | Path, split: str, scene_id: int) -> bool:
    """Whether a scene was fully written (its ``scene_gt_info.json``, written last, exists)."""
    return (bop.scene_dir(root, split, scene_id) / COMPLETE_FILE).is_file()


def generate_scene(job: SceneJob) -> SceneWriter:
    """Simulate and render one scene; returns its encoded files (``extra``: what ``scene_datagen.json`` records)."""
    cfg = job.cfg
    s_scene, s_views, s_noise = np.random.SeedSequence([job.seed, job.scene_id]).spawn(3)
    try:
        gs = build_scene(cfg, np.random.default_rng(s_scene))
    except SceneUnsettled as e:
        hint = "lower --blocks or raise min_spacing / area_margin" if cfg.scene == "table" else "lower --blocks"
        raise SceneUnsettled(f"scene {job.scene_id}: {e}; {hint}") from None
    wc = gs.workcell
    c = cfg.workcell.hand_camera
    renderer = LabelRenderer(wc, HAND_CAMERA, c, cfg.workcell.render, cfg.msaa)
    writer = SceneWriter(cfg.depth_scale, rgb_extension(cfg, job.split), cfg.jpg_quality)
    stats, noise_rng = ViewStats(), np.random.default_rng(s_noise)
    try:
        views = cfg.views if cfg.scene == "table" else cfg.clutter_views
        for im_id, _ in enumerate(visit_views(wc, views, job.views, np.random.default_rng(s_views), stats)):
            frame = renderer.capture()
            dn, rn = cfg.depth_noise, cfg.rgb_noise
            depth = noisy_depth(frame.depth, frame.K, dn, noise_rng, c.near, c.far) if dn.enabled else frame.depth
            rgb = noisy_rgb(frame.rgb, rn, noise_rng) if rn.enabled else frame.rgb
            writer.add(im_id, frame, rgb, depth, dn.keep_clean)
    finally:
        renderer.close()
    info = {
        "scene_id": job.scene_id,
        **({} if cfg.scene == "table" else {"scene": cfg.scene}),
        "images": stats.reached,
        "blocks": [{"obj_id": b.block.obj_id, "name": b.block.name, "rgba": list(b.rgba)} for b in wc.blocks],
        "distractors": len(gs.appearance.distractors),
        "lights": int(wc.model.nlight),
        "drops": gs.drops,
        "views": stats.as_dict(),
    }
    writer.finish(info)
    return writer


def check_settings(path: Path, settings: dict[str, Any], binding: bool) -> None:
    """Record the settings of a split, or refuse to mix a resumed split with other settings (``binding``: the
    split holds a complete scene; settings left by a failed start are replaced)."""
    want = json.loads(pio.dumps_json(settings))
    if binding and os.path.lexists(path):
        inputs.check_file(path, "json", DatasetError)
        try:
            have = inputs.read_json(path, DatasetError)
        except DatasetError:
            have = None
        if have != want:
            diff = sorted(k for k in want if not isinstance(have, dict) or have.get(k) != want[k])
            raise DatasetError(f"{path.parent} was generated with other settings (differing: {', '.join(diff)}); "
                               "use a new --out or the original options")
        return
    pio.write_json(path, want)


def recorded_config(cfg: DatagenConfig) -> dict[str, Any]:
    """``cfg`` as ``datagen_config.json`` records it: ``workcell.objects`` only for a set other than the shipped
    blocks (a dataset's ``models/`` are its set's; datasets made before sets existed stay resumable), the pile and
    bin settings only for those scenes (a table dataset's record is the one it had before they existed)."""
    d = dataclasses.asdict(cfg)
    d["workcell"] = workcell_record(d["workcell"])
    if not cfg.workcell.objects:
        del d["workcell"]["objects"]
    if cfg.scene == "table":
        for k in ("scene", "clutter", "clutter_views"):
            del d[k]
    return d


def aggregate_stats(root: Path, split: str, scenes: int) -> dict[str, Any]:
    """Dataset-level counts over scenes 0..scenes-1, and the complete scenes after them (a run asking for
    fewer scenes than the split holds keeps the whole split's counts), from their ``scene_datagen.json`` (no
    timings: the file is part of the byte-identical output)."""
    while is_complete(root, split, scenes):
        scenes += 1
    per_scene = [inputs.read_json(bop.scene_dir(root, split, s) / "scene_datagen.json", DatasetError)
                 for s in range(scenes)]
    totals = {k: sum(p["views"][k] for p in per_scene) for k in ViewStats().as_dict()}
    inst = sum(len(p["blocks"]) * p["images"] for p in per_scene)
    return {"scenes": scenes, "images": sum(p["images"] for p in per_scene), "instances": inst, "views": totals,
            "per_scene": [{"scene_id": p["scene_id"], "images": p["images"], "blocks": len(p["blocks"]),
                           "distractors": p["distractors"], "lights": p["lights"], **p["views"]} for p in per_scene]}


def generate_dataset(out: str | Path, scenes: int, views: int, seed: int = 0, cfg: DatagenConfig | None = None,
                     split: str = "train_pbr", workers: int | str | None = None, progress: bool = False) -> dict[str, Any]:
    """Write (or complete) a BOP dataset of ``scenes`` x up to ``views`` images under ``out``.

    Returns the dataset statistics (also in ``<out>/<split>/datagen_stats.json``) plus ``generated_scenes``
    and ``seconds`` for this run.
    """
    cfg = validate(cfg or DatagenConfig())
    if split not in SPLITS:
        raise ConfigError(f"split {split!r} must be one of {', '.join(SPLITS)}")
    if scenes < 1 or views < 1:
        raise ConfigError(f"--scenes and --views must be >= 1, got {scenes} and {views}")
    check_capacity(cfg)
    root = Path(out)
    c = cfg.workcell.hand_camera
    # a split's settings, written first (or their temporary file, of a run killed meanwhile), mark our datasets
    with folder_lock(root, owns=(Record(f"*/{SETTINGS_FILE}", ("seed", "views", "config")),
                                 Record(f"*/.{SETTINGS_FILE}.*.tmp"))):
        todo = [s for s in range(scenes) if not is_complete(root, split, s)]
        if isinstance(workers, int) or workers is None:  # no idle worker processes
            workers = max(1, min(workers or os.cpu_count() or 1, len(todo)))
        executor = make_executor(workers)  # Ray connects here, before anything is written
        ext = rgb_extension(cfg, split)
        steps = [lambda: check_settings(bop.split_dir(root, split) / SETTINGS_FILE,
                                        {"seed": seed, "views": views, "rgb_format": ext, "config": recorded_config(cfg)},
                                        binding=has_scenes(root, split)),
                 lambda: prepare_root(root, bop.Camera(c.width, c.height, intrinsics(c.width, c.height, c.fovy_deg),
                                                       cfg.depth_scale), cfg.workcell.objects)]
        # a new dataset's settings go first (they mark the folder as ours); a dataset with scenes checks its object
        # set and camera first (the more telling refusal)
        for step in steps[::-1] if has_scenes(root) else steps:
            step()
        for tmp in bop.split_dir(root, split).glob(".*.tmp"):  # leftovers of a killed write
            tmp.unlink()
        jobs = [SceneJob(split, s, seed, views, cfg) for s in todo]
        t0 = time.perf_counter()
        frames = 0
        with executor, _progress(progress) as bar:  # Ctrl-C ends the workers at once
            write_models_eval(root)
            task = bar.add_task("datagen", total=len(todo) * views, fps=0.0)
            for _, scene in executor.imap(generate_scene, jobs):
                scene.write(bop.scene_dir(root, split, scene.extra["scene_id"]))
                frames += scene.extra["images"]
                bar.update(task, advance=views, fps=frames / max(time.perf_counter() - t0, 1e-9))
        seconds = time.perf_counter() - t0
        stats = aggregate_stats(root, split, scenes)
        pio.write_json(bop.split_dir(root, split) / STATS_FILE, stats)
        if split == "test":  # what BOP 2019 scores: instances at least 10 % visible
            bop.write_test_targets(root, bop.targets_from_gt(bop.iter_scene_images(root, split, range(stats["scenes"]))))
    return {**stats, "generated_scenes": len(todo), "generated_images": frames, "seconds": seconds}


def _progress(enabled: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from posegrasp.progress import progress

    return progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("{task.fields[fps]:.1f} frames/s"), TimeElapsedColumn(), TextColumn("ETA"),
                    TimeRemainingColumn(), enabled=enabled)
