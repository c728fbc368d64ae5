"""The kitting task: the block must end standing upright on the pad (its catalogue ``upright_down`` face down)
at the kit's yaw ``KittingConfig.kit_yaw_deg``, its centre within ``pos_tol`` of the kit point and its yaw within
``yaw_tol_deg``, both modulo its symmetries (``grasping.upright``).

Its scene is the pick-area scene of ``sim.scene.make_scene``, but one block, of a type with an upright face, is set
standing upright (random yaw, 1 mm above the table) and the scene is dropped again until at least one block lies
upright with a grasp clear of its neighbours, so there is always a block the robot can kit. The same seed and
settings give the same scene.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from posegrasp.config import settings
from posegrasp.catalog import PartType
from posegrasp.errors import SceneUnsettled, UserError
from posegrasp.geometry import axis_angle_R, make_T
from posegrasp.grasping.record import Failure
from posegrasp.grasping.tasks.base import PAD_TOP, Graspable, task_types
from posegrasp.grasping.tasks.standing import (MAX_DROPS, StandingTask, any_upright, scene_workcell, standing_extent,
                                               standing_pose, standing_R, verdict)
from posegrasp.grasping.upright import UprightDeviation, upright_error
from posegrasp.sim.scene import choose_types, drop_and_settle
from posegrasp.sim.workcell import Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.episode import Episode
    from posegrasp.grasping.targets import Plan


@settings
class KittingConfig:
    """The kitting task: the block must end upright on the pad at the kit's yaw."""

    #: Success: the block's centre within this xy distance (m) of the kit's ...
    pos_tol: float = 0.015
    #: ... its yaw within this (deg) of the kit's, both modulo its symmetries ...
    yaw_tol_deg: float = 10.0
    #: ... and its upright face within this (deg) of straight down (else "wrong face up").
    upright_tol_deg: float = 15.0
    #: The planner targets only estimates this close (deg) to upright.
    belief_tol_deg: float = 20.0
    #: The kit's yaw on the pad (world, deg).
    kit_yaw_deg: float = 0.0


def kit_targets(block: PartType, xy: np.ndarray, surface_z: float, cfg: KittingConfig) -> np.ndarray:
    """(1, 4, 4) the kit pose: standing on the surface at height ``surface_z`` over ``xy`` at the kit's yaw."""
    R = axis_angle_R(np.array([0.0, 0.0, 1.0]), np.radians(cfg.kit_yaw_deg)) @ standing_R(block)
    return make_T(R, (xy[0], xy[1], surface_z - standing_extent(block)[0]))[None]


def kitting_verdict(block: PartType, T_final: np.ndarray, xy: np.ndarray, surface_z: float,
                    cfg: KittingConfig) -> tuple[UprightDeviation, Failure | None]:
    """The kitted block's final pose against the kit pose over ``xy``, and the failure reason (None: kitted)."""
    err = upright_error(block, T_final, kit_targets(block, xy, surface_z, cfg))
    return err, verdict(err, cfg.pos_tol, cfg.yaw_tol_deg, cfg.upright_tol_deg)


def kitting_scene(cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
    """A settled pick-area scene of ``n_blocks`` blocks, at least one standing upright and ``graspable``."""
    rng = np.random.default_rng(seed)
    types = choose_types(cfg.scene, n_blocks, rng)
    u = int(rng.integers(n_blocks))
    if types[u].upright_down is None:
        able = [b for b in task_types(cfg) if b.upright_down is not None]
        types[u] = able[int(rng.integers(len(able)))]
    wc = scene_workcell(cfg, types, rng)
    candidates = [k for k, b in enumerate(types, start=1) if b.upright_down is not None]

    def arrange(poses: list[np.ndarray], blocks: list[PartType]) -> list[np.ndarray]:
        poses[u] = standing_pose(blocks[u], poses[u][:2, 3], 0.0, rng)
        return poses

    for _ in range(MAX_DROPS):
        drop_and_settle(wc, cfg.scene, types, rng, arrange=arrange)
        if any_upright(wc, candidates, cfg.kitting.upright_tol_deg, graspable):
            return wc
    raise SceneUnsettled(f"blocks did not come to rest with one upright after {MAX_DROPS} drops")


class Kitting(StandingTask):
    """Kit the block: upright on the pad at the kit's yaw, over the episode's place point."""

    name = "kitting"

    def check(self, cfg: TrialConfig) -> None:
        types = task_types(cfg)
        if not any(b.upright_down is not None for b in types):
            raise UserError(f"task kitting needs an object type with an upright face; the scene's types "
                            f"({', '.join(b.name for b in types)}) have none: add one to scene.block_types")

    def scene(self, cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
        return kitting_scene(cfg, seed, n_blocks, graspable)

    def settings(self, cfg: TrialConfig) -> KittingConfig:
        return cfg.kitting

    def targets(self, ep: Episode, plan: Plan, context: Any) -> tuple[np.ndarray, float]:
        return kit_targets(plan.est_block, ep.place_xy, PAD_TOP, ep.cfg.kitting), PAD_TOP

    def final_error(self, ep: Episode, plan: Plan, context: Any) -> tuple[UprightDeviation, Failure | None]:
        return kitting_verdict(plan.block, ep.wc.block_poses()[plan.k - 1], ep.place_xy, PAD_TOP, ep.cfg.kitting)
