"""What the kitting and stack tasks share: a block set down standing upright at a target pose, judged modulo its
symmetries, and scenes with a block standing upright to pick.

A block "stands upright" in the frame ``standing_R(block)``: its object set's ``upright.quat``, which turns its
upright face down at the kit's yaw (the identity for the shipped blocks). Frames below are ``T_world_obj`` (m).
"""

from __future__ import annotations

import functools
from abc import abstractmethod
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from posegrasp.catalog import PartType
from posegrasp.geometry import axis_angle_R, make_T, quat_to_R
from posegrasp.grasping.record import Failure
from posegrasp.grasping.tasks.base import EpisodeFailed, Goal, Graspable, Pickable, PickTask
from posegrasp.grasping.upright import UprightDeviation, match, standing_copies, tilt_deg, upright_error, yaw_between
from posegrasp.sim.scene import randomise_lights
from posegrasp.sim.workcell import BlockInstance, Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.episode import Episode
    from posegrasp.grasping.targets import Plan

#: Drops tried before a scene counts as one that never settles.
MAX_DROPS = 20


def standing_R(block: PartType) -> np.ndarray:
    """Rotation (world_obj) that stands the block on its upright face at the kit's yaw (``R d = -z``): the
    object set's ``upright.quat``."""
    return quat_to_R(block.upright_quat)


@functools.lru_cache(maxsize=32)
def standing_extent(block: PartType) -> tuple[float, float]:
    """Lowest and highest z (m) of the block's vertices in its standing frame (origin at its centre)."""
    z = (block.vertices @ standing_R(block).T)[:, 2]
    return float(z.min()), float(z.max())


@functools.lru_cache(maxsize=32)
def footprint(block: PartType) -> tuple[float, float]:
    """The standing block's extents (m) along its horizontal axes, longest first."""
    ext = np.ptp(block.vertices @ standing_R(block).T, axis=0)[:2]
    return float(ext.max()), float(ext.min())


def believed_upright(block: PartType, T_world_obj: np.ndarray, tol_deg: float) -> bool:
    """Does the (estimated) pose stand the block upright, within ``tol_deg``?"""
    return tilt_deg(block, T_world_obj[:3, :3]) <= tol_deg


def verdict(err: UprightDeviation, pos_tol: float, yaw_tol_deg: float, upright_tol_deg: float) -> Failure | None:
    """Failure reason of a placed block's error against its target, or None on success."""
    if err.tilt_deg > upright_tol_deg:
        return Failure.WRONG_FACE
    if err.te > pos_tol:
        return Failure.MISPLACED
    if abs(err.yaw_deg) > yaw_tol_deg:
        return Failure.MISALIGNED
    return None


class StandingSettings(Protocol):
    """The settings every standing task has (``KittingConfig``, ``StackConfig``)."""

    pos_tol: float
    yaw_tol_deg: float
    upright_tol_deg: float
    belief_tol_deg: float


class StandingTask(PickTask):
    """A pick task that sets the block down standing upright at a target pose: it picks only estimates believed
    upright, turns the block about the vertical while carrying it onto the nearest of its ``targets`` (the
    smallest turn over the block's symmetries), records the estimate's and the final pose's errors modulo
    symmetries and judges the final pose (``final_error``); it holds the block firmly (``config.FIRM_HOLD_TASKS``)."""

    unpickable = Failure.NO_UPRIGHT

    @abstractmethod
    def settings(self, cfg: TrialConfig) -> StandingSettings:
        """The task's settings block of ``cfg``."""

    @abstractmethod
    def targets(self, ep: Episode, plan: Plan, context: Any) -> tuple[np.ndarray, float]:
        """(M, 4, 4) poses the planned block (of its estimated type) may end in, and the height (m) of the
        surface it is set down on."""

    def final_error(self, ep: Episode, plan: Plan, context: Any) -> tuple[UprightDeviation, Failure | None]:
        """The block's final pose against its target and the task's verdict on it (None: success)."""

    def rest(self, ep: Episode, k: int) -> bool:
        """Wait for block ``k`` to come to rest after the hand let go; did it?"""
        return ep.wait_for_rest(k)

    def pickable(self, ep: Episode, context: Any) -> Pickable | None:
        tol = self.settings(ep.cfg).belief_tol_deg
        return lambda b, T: believed_upright(b, T, tol)

    def goal(self, ep: Episode, plan: Plan, context: Any) -> Goal:
        """Records the target estimate's error modulo symmetries, then the goal: the turn and the point that bring
        the block's estimated pose onto the nearest target pose."""
        ep.rec.estimate_error = upright_error(plan.block, plan.T_world_obj, ep.wc.block_poses()[plan.k - 1][None],
                                              standing=False)
        targets, surface = self.targets(ep, plan, context)
        cands = standing_copies(plan.est_block, plan.T_world_obj)
        i, j, _ = match(cands, targets)
        yaw = yaw_between(cands[i][:3, :3], targets[j][:3, :3])
        Rz = axis_angle_R(np.array([0.0, 0.0, 1.0]), yaw)
        xy = targets[j][:2, 3] - (Rz @ (cands[i][:3, 3] - plan.T_world_obj[:3, 3]))[:2]
        return Goal(xy, yaw, surface)

    def judge(self, ep: Episode, plan: Plan, context: Any) -> None:
        """Released and at rest, and the final pose within the task's tolerances; else its verdict, or
        "misplaced"."""
        at_rest = self.rest(ep, plan.k)
        ep.log.stop("settle", ep.ctl)
        err, reason = self.final_error(ep, plan, context)
        released = ep.released(plan.k)
        ep.rec.final_error, ep.rec.place_error = err, err.te
        ep.rec.placed = bool(reason is None and at_rest and released)
        if not ep.rec.placed:
            raise EpisodeFailed(reason or Failure.MISPLACED)


def scene_workcell(cfg: TrialConfig, types: list[PartType], rng: np.random.Generator) -> Workcell:
    """A workcell with ``types`` in random palette colours and random lights (as ``sim.scene.make_scene``)."""
    scfg = cfg.scene
    colours = [scfg.palette[i] for i in rng.integers(0, len(scfg.palette), size=len(types))]
    wc = Workcell(scfg.workcell, [BlockInstance(b, (*c, 1.0)) for b, c in zip(types, colours)])
    randomise_lights(wc, scfg, rng)
    return wc


def standing_pose(block: PartType, xy: np.ndarray, surface_z: float, rng: np.random.Generator) -> np.ndarray:
    """The block standing upright at a random yaw over ``xy`` (m), 1 mm above a surface at ``surface_z`` (a
    block dropped from higher up may topple: a standing cylinder did, scene after scene)."""
    yaw = axis_angle_R(np.array([0.0, 0.0, 1.0]), rng.uniform(0.0, 2.0 * np.pi))
    return make_T(yaw @ standing_R(block), (xy[0], xy[1], surface_z + 0.001 - standing_extent(block)[0]))


def any_upright(wc: Workcell, ks: list[int], tol_deg: float, graspable: Graspable) -> bool:
    """Does any of the blocks ``ks`` (1-based) stand upright with a grasp clear of its neighbours
    (``graspable``)? An upright block hemmed in by others would leave the task nothing it can reach."""
    poses = wc.block_poses()
    return any(believed_upright(wc.blocks[k - 1].block, poses[k - 1], tol_deg) and graspable(wc, k) for k in ks)
