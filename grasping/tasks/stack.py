"""The stack task: the block must end standing upright on a base block that stands on the pad, centred on the
base's top face within ``StackConfig.pos_tol``, its yaw within ``yaw_tol_deg`` of the base's modulo both blocks'
symmetries; the base moved at most ``base_move_tol``. Pairs can stack when the base's top is flat and the block's
bottom is (catalogue ``flat_top``, ``flat_bottom``).

The arm first looks down at the pad (capture ``BASE_LOOK``) and perceives the base through the same provider as
the pick look (its own seed, ``Episode.seed_for(1)``); then it picks a block believed upright that fits the base
and sets it down on the base's estimated top, steadying the arm (``SteadyConfig``).

Its scene: the pick-area blocks, one of which fits the base and is dropped upright, plus a base block (the last
instance) standing upright on the place pad, its centre within ``StackConfig.base_jitter`` of the pad's and its
yaw uniform; everything is settled by simulation. The same seed and settings give the same scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from posegrasp.config import settings
from posegrasp.catalog import PartType, catalog_by_id
from posegrasp.errors import SceneUnsettled, UserError
from posegrasp.geometry import make_T, transform_points
from posegrasp.grasping.perception import BASE_LOOK, PICK_LOOK
from posegrasp.grasping.record import BaseRecord, Failure
from posegrasp.grasping.support import rest_on_table
from posegrasp.grasping.tasks.base import PAD_TOP, EpisodeFailed, Graspable, Pickable, SteadyConfig, task_types
from posegrasp.grasping.tasks.standing import (MAX_DROPS, StandingTask, any_upright, believed_upright, footprint,
                                               scene_workcell, standing_extent, standing_pose, standing_R, verdict)
from posegrasp.grasping.upright import UprightDeviation, symmetries, upright_error
from posegrasp.sim.scene import choose_types, drop_poses, settle
from posegrasp.sim.workcell import Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.episode import Episode
    from posegrasp.grasping.targets import Plan


@settings
class StackConfig:
    """The stack task: a block set centred on a base block standing on the pad."""

    #: Success: the block's centre within this xy distance (m) of the base's top centre ...
    pos_tol: float = 0.01
    #: ... its yaw within this (deg) of the base's, modulo both blocks' symmetries ...
    yaw_tol_deg: float = 10.0
    #: ... upright within this (deg) ...
    upright_tol_deg: float = 15.0
    #: ... resting there this long (s) after the hand has left ...
    rest_time: float = 1.0
    #: ... and the base moved at most this far (m).
    base_move_tol: float = 0.005
    #: The planner targets only estimates this close (deg) to upright.
    belief_tol_deg: float = 20.0
    #: The base's centre is drawn this far (m, per axis) around the pad centre.
    base_jitter: float = 0.02
    #: The hand camera looks down at the pad from this height (m).
    look_height: float = 0.3
    #: How the arm is steadied around the grasp and the set-down (kitting does not steady: an L-block turns in
    #: the hand while held, 7-10 deg, and the longer hold took it past 10 deg).
    steady: SteadyConfig = field(default_factory=SteadyConfig)


def can_stack(base: PartType, block: PartType, overhang: float = 1.0) -> bool:
    """Can ``block`` stand upright on ``base`` standing upright: a flat top under a flat bottom, the block's
    footprint at most ``overhang`` times the base's, side for side? A block wider than its base tips over as the
    fingers let go: a fingertip that opens from its top edge drags it off."""
    if base.upright_down is None or block.upright_down is None or not (base.flat_top and block.flat_bottom):
        return False
    return all(a <= overhang * b for a, b in zip(footprint(block), footprint(base)))


def stack_targets(base: PartType, T_base: np.ndarray, block: PartType) -> np.ndarray:
    """(M, 4, 4) poses of ``block`` standing centred on the top of ``base`` at ``T_base``, one per symmetric
    copy of the base's frame that keeps it standing (so the block's yaw is compared modulo the base's
    symmetries too)."""
    frames = np.einsum("ij,njk->nik", T_base, symmetries(base)) @ make_T(standing_R(base).T, np.zeros(3))
    up = frames[:, 2, 2] > 0.9  # those with z up (all, if the base has fallen over)
    frames = frames[up] if up.any() else frames
    lift = make_T(standing_R(block), (0.0, 0.0, standing_extent(base)[1] - standing_extent(block)[0]))
    return frames @ lift


def stack_verdict(base: PartType, T_base_start: np.ndarray, T_base_final: np.ndarray, block: PartType,
                  T_final: np.ndarray, cfg: StackConfig) -> tuple[UprightDeviation, float, Failure | None]:
    """The stacked block's final pose against the base's top (as the base ends), how far the base moved (m)
    and the failure reason (None: stacked)."""
    err = upright_error(block, T_final, stack_targets(base, T_base_final, block))
    shift = float(np.linalg.norm(T_base_final[:3, 3] - T_base_start[:3, 3]))
    reason = Failure.BASE_MOVED if shift > cfg.base_move_tol else verdict(err, cfg.pos_tol, cfg.yaw_tol_deg,
                                                                            cfg.upright_tol_deg)
    return err, shift, reason


def stack_scene(cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
    """A settled scene: ``n_blocks`` blocks in the pick area, one of which fits the base and stands upright
    (``graspable``), and the base (instance ``n_blocks + 1``) standing on the place pad."""
    scfg, rng = cfg.scene, np.random.default_rng(seed)
    types = choose_types(scfg, n_blocks, rng)
    pool = task_types(cfg)
    bases = [b for b in pool if any(can_stack(b, t) for t in pool)]
    base = bases[int(rng.integers(len(bases)))]
    u = int(rng.integers(n_blocks))
    if not can_stack(base, types[u]):
        fits = [t for t in pool if can_stack(base, t)]
        types[u] = fits[int(rng.integers(len(fits)))]
    wc = scene_workcell(cfg, [*types, base], rng)
    pad, area = scfg.workcell.place_area, scfg.workcell.pick_area
    candidates = [k for k, b in enumerate(types, start=1) if can_stack(base, b)]
    for _ in range(MAX_DROPS):
        wc.reset()
        poses = drop_poses(scfg, types, rng)
        poses[u] = standing_pose(types[u], poses[u][:2, 3], 0.0, rng)
        xy = np.asarray(pad.center) + rng.uniform(-cfg.stack.base_jitter, cfg.stack.base_jitter, size=2)
        T_base = standing_pose(base, xy, PAD_TOP, rng)
        for k, T in enumerate([*poses, T_base], start=1):
            wc.set_block_pose(k, T)
        mujoco.mj_forward(wc.model, wc.data)
        settled = settle(wc, scfg)
        xy_now = wc.block_poses()[:, :2, 3]
        inside = np.all(np.abs(xy_now[:-1] - area.center) <= area.half_size)
        if (settled and inside and np.linalg.norm(xy_now[-1] - xy) < cfg.stack.base_move_tol
                and any_upright(wc, candidates, cfg.stack.upright_tol_deg, graspable)):
            wc.data.qvel[:] = 0.0
            wc.data.time = 0.0
            return wc
    raise SceneUnsettled(f"blocks did not come to rest with one upright after {MAX_DROPS} drops")


@dataclass(frozen=True)
class Base:
    """The base: its scene instance ``k`` (1-based), true start pose and the perceived type and levelled pose."""

    k: int
    T_start: np.ndarray
    block: PartType | None = None
    T_est: np.ndarray | None = None


class Stack(StandingTask):
    """Stack the block on the base standing on the pad, perceived from a look down at the pad."""

    name = "stack"
    looks = (PICK_LOOK, BASE_LOOK)

    def check(self, cfg: TrialConfig) -> None:
        types = task_types(cfg)
        if not any(can_stack(a, b) for a in types for b in types):
            raise UserError(f"task stack needs an object type with a flat top and one with a flat bottom that fits "
                            f"on it; the scene's types ({', '.join(b.name for b in types)}) have no such pair: "
                            "choose other scene.block_types or another --objects set")

    def scene(self, cfg: TrialConfig, seed: int, n_blocks: int, graspable: Graspable) -> Workcell:
        return stack_scene(cfg, seed, n_blocks, graspable)

    def settings(self, cfg: TrialConfig) -> StackConfig:
        return cfg.stack

    def steady(self, cfg: TrialConfig) -> SteadyConfig:
        return cfg.stack.steady

    def prepare(self, ep: Episode) -> Base:
        """Look down at the pad, perceive the base through the provider and level its estimate onto the pad;
        records the base and its estimate's error."""
        wc, k = ep.wc, len(ep.wc.blocks)
        base = Base(k, wc.block_poses()[k - 1].copy())
        ep.rec.base = BaseRecord(k, wc.blocks[k - 1].block.name)
        pad = wc.cfg.place_area
        if not ep.look_down(pad.center, ep.cfg.stack.look_height, "stack.look_height"):
            raise EpisodeFailed(Failure.TIMEOUT)
        ep.log.stop("look_base", ep.ctl)
        seed = ep.seed_for(1)
        frame = ep.capture(BASE_LOOK)
        if ep.captures_only:
            return base
        ests = ep.perceive(frame, seed, BASE_LOOK)
        T_world_cam = ep.T_world_cam()
        cat = catalog_by_id(wc.cfg.objects)
        on_pad = [(float(np.linalg.norm(T[:2, 3] - pad.center)), e.obj_id, T)
                  for e in ests for T in [T_world_cam @ e.T_cam_obj]
                  if np.all(np.abs(T[:2, 3] - pad.center) <= np.add(pad.half_size, 0.02))]
        ep.log.stop("perceive_base", ep.ctl)
        if not on_pad:
            raise EpisodeFailed(Failure.NO_BASE)
        _, obj_id, T = min(on_pad, key=lambda o: o[0])
        block = cat[obj_id]
        T = rest_on_table(block, T, ep.cfg.rest, surface_z=PAD_TOP)
        ep.rec.base = BaseRecord(k, ep.rec.base.type, upright_error(block, T, base.T_start[None], standing=False))
        return Base(k, base.T_start, block, T)

    def pickable(self, ep: Episode, base: Base) -> Pickable:
        tol = ep.cfg.stack.belief_tol_deg
        return lambda b, T: can_stack(base.block, b) and believed_upright(b, T, tol)

    def targets(self, ep: Episode, plan: Plan, base: Base) -> tuple[np.ndarray, float]:
        """Centred on the base's estimated top face, aligned with it."""
        surface = float(transform_points(base.T_est, base.block.vertices)[:, 2].max())
        return stack_targets(base.block, base.T_est, plan.est_block), surface

    def rest(self, ep: Episode, k: int) -> bool:
        """At rest, and still at rest ``StackConfig.rest_time`` later."""
        if not ep.wait_for_rest(k):
            return False
        ep.ctl.hold(ep.cfg.stack.rest_time)
        v = ep.wc.block_speeds()[k - 1]
        return bool(v[0] < ep.cfg.scoring.rest_speed[0] and v[1] < ep.cfg.scoring.rest_speed[1])

    def final_error(self, ep: Episode, plan: Plan, base: Base) -> tuple[UprightDeviation, Failure | None]:
        T = ep.wc.block_poses()
        base_block = ep.wc.blocks[base.k - 1].block
        err, shift, reason = stack_verdict(base_block, base.T_start, T[base.k - 1], plan.block, T[plan.k - 1],
                                           ep.cfg.stack)
        ep.rec.base = BaseRecord(base.k, base_block.name, ep.rec.base.estimate_error, shift)
        return err, reason
