"""The pick-and-place task: any block the robot sees, set down with its centre within ``ScoringConfig.place_tol``
of the episode's place point on the pad (the pad's centre plus a random offset within ``grasp.place_jitter``),
at rest, the hand away from it and no finger touching it. Its scene is ``sim.scene.make_scene``'s."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from posegrasp.grasping.record import TASK_FIELDS, EpisodeRecord, Failure
from posegrasp.grasping.tasks.base import EpisodeFailed, Graspable, PickTask
from posegrasp.sim.scene import make_scene
from posegrasp.sim.workcell import Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.episode import Episode
    from posegrasp.grasping.targets import Plan


#: The task's name (``--task``).
PICK_PLACE = "pick-place"


@dataclass
class PickPlaceRecord(EpisodeRecord, task=PICK_PLACE):
    """A pick-and-place episode: the ``EpisodeRecord`` without the kitting and stack tasks' fields
    (``record.TASK_FIELDS`` but ``task``)."""

    def to_json(self) -> dict:
        d = super().to_json()
        for k in TASK_FIELDS[1:]:
            d.pop(k, None)
        return d


class PickPlace(PickTask):
    """Pick any block and set it down over the episode's place point."""

    name = PICK_PLACE
    record_type = PickPlaceRecord

    def scene(self, cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
        return make_scene(seed, n_blocks, cfg.scene).workcell

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
