"""The pick-and-place task: any block the robot sees, set down with its centre within ``ScoringConfig.place_tol``
of the episode's place point on the pad (the pad's centre plus a random offset within ``grasp.place_jitter``),
at rest, the hand away from it and no finger touching it. Its scene is ``sim.scene.make_scene``'s."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from posegrasp.grasping.record import EpisodeRecord, Failure
from posegrasp.grasping.tasks.base import EpisodeFailed, Graspable, PickTask
from posegrasp.sim.scene import make_scene
from posegrasp.sim.workcell import Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.episode import Episode
    from posegrasp.grasping.targets import Plan


class PickPlace(PickTask):
    """Pick any block and set it down over the episode's place point."""

    name = "pick-place"

    def scene(self, cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
        return make_scene(seed, n_blocks, cfg.scene).workcell

    def new_record(self, episode: int, seed: int, scene_seed: int, n_blocks: int, perception: str) -> EpisodeRecord:
        """A record without the task fields (pick-and-place records keep the layout they had before the tasks)."""
        return EpisodeRecord(episode, seed, scene_seed, n_blocks, perception)

    def judge(self, ep: Episode, plan: Plan, context: Any) -> None:
        """Wait for the block to come to rest, then score the place: within place_tol of the place point, at
        rest, the hand away from it and no finger touching it."""
        k = plan.k
        at_rest = ep.wait_for_rest(k)
        ep.log.stop("settle", ep.ctl)
        err = float(np.linalg.norm(ep.wc.block_poses()[k - 1][:2, 3] - ep.place_xy))
        ep.rec.place_error = err
        ep.rec.placed = bool(err <= ep.cfg.scoring.place_tol and at_rest and ep.released(k))
        if not ep.rec.placed:
            raise EpisodeFailed(Failure.MISPLACED)
