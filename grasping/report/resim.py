"""An episode re-simulated from its recorded seeds up to the look capture, with ``grasping.episode``'s own
functions: the hand-camera frame the provider saw, its estimates and labels, and the overview camera's image."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from posegrasp.errors import SimulationError
from posegrasp.executor import Executor, SerialExecutor
from posegrasp.grasping.record import EpisodeRecord
from posegrasp.grasping.report.figures import Look
from posegrasp.grasping.runfolder import read_campaign


def resimulate_look(run_dir: Path, rec: EpisodeRecord) -> Look | None:
    """Episode ``rec`` of the run in ``run_dir`` re-simulated from its seeds up to the look capture; None if it
    never got there."""
    from posegrasp.catalog import catalog_by_id
    from posegrasp.grasping.episode import EpisodeJob, capture_look, check_draws, episode_workcell
    from posegrasp.grasping.targets import drive_to_look
    from posegrasp.grasping.model_provider import ModelProvider
    from posegrasp.grasping.perception import PICK_LOOK, PerceptionError, observation, perceive
    from posegrasp.grasping.provider_registry import make_provider
    from posegrasp.grasping.tasks import get_task
    from posegrasp.sim.camera import CameraRenderer
    from posegrasp.sim.workcell import OVERVIEW_CAMERA

    campaign = read_campaign(run_dir)
    job = EpisodeJob(get_task(campaign.config.task), rec.seed, rec.episode, rec.perception, campaign.config,
                     campaign.T_gripper_cam)
    n_blocks, scene_seed, percept_seed, _ = check_draws(job, rec, run_dir)
    try:
        wc = episode_workcell(job.task, job.cfg, scene_seed, n_blocks)
    except SimulationError:  # a scene that never settles (recorded as a simulation error)
        return None
    if not drive_to_look(wc, job.cfg.control):
        return None
    frame = capture_look(wc)
    provider = make_provider(job.perception, wc.cfg.objects)
    if isinstance(provider, ModelProvider):  # its class map too, from the same single run of the network
        result = provider.perceive(observation(frame, job.index, PICK_LOOK))
        ests, labels = provider.select(result), result.labels
    else:
        try:
            ests = perceive(provider, frame, percept_seed, job.index, PICK_LOOK,
                            known_ids=catalog_by_id(wc.cfg.objects), timeout_s=job.cfg.perception_timeout_s)
        except PerceptionError:  # the episode's "perception error": no estimates to draw
            ests = []
        labels = frame.mask
    cam = CameraRenderer(wc, OVERVIEW_CAMERA, wc.cfg.overview_camera, wc.cfg.render)
    overview = cam.rgb()
    cam.close()
    return Look(frame, ests, np.asarray(labels), overview, wc.cfg.objects)


def _resimulate_look_task(item: tuple[Path, EpisodeRecord]) -> Look | None:
    """``resimulate_look(*item)``: a plain function of one argument, as executors (Ray too) take."""
    return resimulate_look(*item)


def resimulate_looks(run_dir: Path, episodes: Sequence[EpisodeRecord],
                     executor: Executor | None = None) -> dict[int, Look | None]:
    """``resimulate_look`` of each episode, by episode index, run by ``executor`` (a campaign's warm workers) or
    in this process."""
    done = (executor or SerialExecutor()).imap(_resimulate_look_task, [(run_dir, r) for r in episodes])
    return {episodes[i].episode: look for i, look in done}
