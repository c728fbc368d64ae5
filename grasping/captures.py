"""The frames a campaign's robot perceives, as a BOP test split: ``posegrasp trials --export-captures DIR``.

Scene ``i`` of split ``test`` is episode ``i``; its image ``PICK_LOOK`` (0) is the look at the pick area and, in the
stack task, image ``BASE_LOOK`` (1) the look at the base on the pad; in bin picking image ``a`` is attempt ``a``'s
look into the tote and ``HELD_LOOK + a`` (1000 + a) the tray's second look at the part it holds, from the tray's
upward camera (its own K and pose in ``scene_camera.json``). An image holds exactly what a provider sees
(``grasping.perception.observation``): the colour image (png), the depth in the hand camera's 0.1 mm steps
(``DEPTH_SCALE``; the png's depth_scale) and K, with the ground truth (``scene_gt.json``, amodal and visible masks,
``scene_gt_info.json``) and the camera's world pose (``cam_R_w2c``, ``cam_t_w2c`` in ``scene_camera.json``); the
root holds the object set's ``models/``, ``models_eval/``, ``camera.json`` and ``test_targets_bop19.json``. The
files are written by ``datagen.writer`` from ``posegrasp.bop``'s encoders, so ``posegrasp dataset check`` and
``posegrasp eval`` read the export as any BOP dataset.

The export does not depend on the provider: with ``--captures-only`` an episode only drives to its looks and
captures (no perception, no grasp), which gives the same frames as the full episode, and a full episode that
stops before a later look (stack: no base seen) has that look captured by a captures-only run. A scene is
complete once its ``scene_gt_info.json`` exists: a killed export resumes with the others; ``captures.json``
binds the folder to one campaign (seed and trial settings) once a scene is complete. The folder is locked
(``posegrasp.lock``) while it is written.
"""

from __future__ import annotations

import dataclasses
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn

from posegrasp import bop
from posegrasp.datagen.generate import check_settings
from posegrasp.datagen.render import LabelRenderer
from posegrasp.datagen.writer import COMPLETE_FILE, SceneWriter, has_scenes, prepare_root, write_models_eval
from posegrasp.executor import make_executor
from posegrasp.grasping.config import TrialConfig, config_record
from posegrasp.grasping.episode import EpisodeJob, run_episode
from posegrasp.grasping.perception import DEPTH_SCALE
from posegrasp.grasping.record import EpisodeRecord, EpisodeTimings, Failure
from posegrasp.grasping.tasks import get_task
from posegrasp.lock import folder_lock
from posegrasp.outputs import Record
from posegrasp.progress import progress as progress_bar
from posegrasp.sim.camera import Frame, intrinsics
from posegrasp.sim.config import CameraConfig
from posegrasp.sim.workcell import Workcell

SPLIT = "test"
SETTINGS_FILE = "captures.json"
EPISODE_FILE = "scene_episode.json"  #: per scene: the episode it comes from and the captures it holds
_PHYSICAL = (Failure.TIMEOUT, Failure.SIMULATION_ERROR)  # failures a captures-only run meets at the same point


class _Recorder:
    """An episode's captures with their labels, encoded in memory in a worker (``SceneWriter``)."""

    def __init__(self) -> None:
        self.scene = SceneWriter(DEPTH_SCALE, "png")

    def __call__(self, wc: Workcell, frame: Frame, im_id: int, camera: str, c: CameraConfig) -> None:
        labels = LabelRenderer(wc, camera, c, msaa=0)
        try:
            amodal, boxes, beyond = labels.amodal(frame.T_cam_obj)
        finally:
            labels.close()
        labelled = dataclasses.replace(frame, extra={"amodal": amodal, "boxes": boxes, "beyond": beyond})
        self.scene.add(im_id, labelled, frame.rgb, frame.depth, clean_depth=False)


def run_capturing(job: EpisodeJob) -> tuple[EpisodeRecord, EpisodeTimings, SceneWriter]:
    """Worker: run episode ``job`` (or only its captures, ``job.captures_only``) and encode its captures; an
    episode that stopped before a later look (stack: no base seen) gets them from a captures-only run."""
    record, timings, scene = _run(job)
    if not job.captures_only and not set(job.task.fixed_looks) <= set(scene.cams) \
            and record.failure not in _PHYSICAL:
        scene = _run(dataclasses.replace(job, captures_only=True))[2]
    scene.finish({"episode": job.index, "seed": job.seed, "scene_seed": record.scene_seed, "task": job.cfg.task,
                  "captures": sorted(scene.cams)})
    return record, timings, scene


def _run(job: EpisodeJob) -> tuple[EpisodeRecord, EpisodeTimings, SceneWriter]:
    recorder = _Recorder()
    record, timings = run_episode(job, recorder)
    return record, timings, recorder.scene


class CaptureExport:
    """An export folder open for writing (``open_export``): which episodes it holds, and writing one."""

    def __init__(self, root: Path):
        self.root = root

    def has(self, episode: int) -> bool:
        """Whether episode ``episode``'s captures are complete in the export."""
        return (bop.scene_dir(self.root, SPLIT, episode) / COMPLETE_FILE).is_file()

    def write(self, scene: SceneWriter) -> None:
        """Write one episode's captures (its scene folder)."""
        scene.write(bop.scene_dir(self.root, SPLIT, scene.extra["episode"]), EPISODE_FILE)


@contextmanager
def open_export(root: Path | None, seed: int, cfg: TrialConfig) -> Iterator[CaptureExport | None]:
    """The export folder ``root`` of a campaign (seed ``seed``, settings ``cfg``), locked and prepared (models,
    camera, settings checked); on a normal exit ``test_targets_bop19.json`` is written for its complete scenes.
    ``root`` None: no export (yields None)."""
    if root is None:
        yield None
        return
    c = cfg.scene.workcell.hand_camera
    with folder_lock(root, owns=(Record(SETTINGS_FILE, ("seed", "config")),)):  # its settings file first: a folder without it is not ours
        check_settings(root / SETTINGS_FILE, {"seed": seed, "task": cfg.task, "config": config_record(cfg)},
                       binding=has_scenes(root, SPLIT))
        prepare_root(root, bop.Camera(c.width, c.height, intrinsics(c.width, c.height, c.fovy_deg), DEPTH_SCALE),
                     cfg.scene.workcell.objects)
        write_models_eval(root)
        for tmp in bop.split_dir(root, SPLIT).glob(".*.tmp"):  # leftovers of a killed write
            tmp.unlink()
        yield CaptureExport(root)
        scenes = [s for s in bop.list_scenes(root, SPLIT) if CaptureExport(root).has(s)] \
            if bop.split_dir(root, SPLIT).is_dir() else []
        bop.write_test_targets(root, bop.targets_from_gt(bop.iter_scene_images(root, SPLIT, scenes)))


def export_captures(root: Path, episodes: int, seed: int, workers: int | str | None, cfg: TrialConfig,
                    mount: tuple[tuple[float, ...], ...], console: Console | None = None,
                    progress: bool = True) -> dict:
    """``--captures-only``: write (or complete) the captures of episodes 0..episodes-1 of the campaign (seed,
    settings ``cfg`` and camera ``mount`` checked by ``trials.campaign_settings``) into the export ``root``
    without running their grasps; returns counts and the wall time."""
    console = console or Console(stderr=True)
    t0 = time.perf_counter()
    with open_export(root, seed, cfg) as export:
        executor = make_executor(workers)
        # captures only: the provider named is never asked
        task = get_task(cfg.task)
        todo = [EpisodeJob(task, seed, i, "oracle", cfg, mount, captures_only=True) for i in range(episodes)
                if not export.has(i)]
        images = 0
        with executor, progress_bar(TextColumn("[bold]captures[/] {task.description}"), BarColumn(),
                                    MofNCompleteColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                                    enabled=progress, console=console, transient=True) as bar:
            task = bar.add_task(cfg.task, total=episodes, completed=episodes - len(todo))
            for _, (_, _, scene) in executor.imap(run_capturing, todo):
                export.write(scene)
                images += len(scene.cams)
                bar.update(task, advance=1)
    seconds = time.perf_counter() - t0
    result = {"export": str(root), "episodes": episodes, "captured_episodes": len(todo), "images": images,
              "seconds": round(seconds, 2)}
    console.print(f"captures of {len(todo)} episodes ({images} images) -> {root} in {seconds:.1f} s")
    return result
