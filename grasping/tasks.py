"""The trial tasks' targets and verdicts: pick-and-place, kitting into a fixed orientation, stacking.

- ``pick-place``: the block within ``ScoringConfig.place_tol`` of a point on the pad (``grasping.episode``).
- ``kitting``: the block standing upright on the pad (its catalogue ``upright_down`` face down) at the kit's
  yaw ``KittingConfig.kit_yaw_deg``, its centre within ``pos_tol`` of the kit point and its yaw within
  ``yaw_tol_deg``, both modulo its symmetries (``grasping.upright``).
- ``stack``: the block standing upright on a base block that stands on the pad, centred on the base's top
  face within ``StackConfig.pos_tol``, its yaw within ``yaw_tol_deg`` of the base's modulo both blocks'
  symmetries; the base moved at most ``base_move_tol``. Pairs can stack when the base's top is flat and the
  block's bottom is (catalogue ``flat_top``, ``flat_bottom``).

A block "stands upright" in the frame ``standing_R(block)``: its object set's ``upright.quat``, which turns
its upright face down at the kit's yaw (the identity for the shipped blocks). Frames below are ``T_world_obj`` (m).
"""

from __future__ import annotations

import functools

import numpy as np

from posegrasp.catalog import PartType, load_catalog
from posegrasp.errors import UserError
from posegrasp.geometry import axis_angle_R, make_T, quat_to_R
from posegrasp.grasping.config import TASKS, KittingConfig, StackConfig, TrialConfig, firm_hold_tasks
from posegrasp.grasping.upright import UprightDeviation, symmetries, tilt_deg, upright_error

#: Height (m) of the place pad's surface.
PAD_TOP = 0.003
#: Failure reasons of the kitting and stack tasks (the verdicts below), beside ``record.FAILURES``'s.
NO_UPRIGHT, WRONG_FACE, MISALIGNED, BASE_MOVED, NO_BASE = (
    "no upright block", "wrong face up", "misaligned", "base moved", "no base seen")


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


def can_stack(base: PartType, block: PartType, overhang: float = 1.0) -> bool:
    """Can ``block`` stand upright on ``base`` standing upright: a flat top under a flat bottom, the block's
    footprint at most ``overhang`` times the base's, side for side? A block wider than its base tips over as the
    fingers let go: a long cuboid knocked a cylinder 4 cm off the pad; a 2x2 brick (31.8 mm) on a standing
    cylinder (30 mm) fell, 6 times in 6 (seed 0), dragged by a fingertip that opens from its top edge."""
    if base.upright_down is None or block.upright_down is None or not (base.flat_top and block.flat_bottom):
        return False
    return all(a <= overhang * b for a, b in zip(footprint(block), footprint(base)))


def kit_targets(block: PartType, xy: np.ndarray, surface_z: float, cfg: KittingConfig) -> np.ndarray:
    """(1, 4, 4) the kit pose: standing on the surface at height ``surface_z`` over ``xy`` at the kit's yaw."""
    R = axis_angle_R(np.array([0.0, 0.0, 1.0]), np.radians(cfg.kit_yaw_deg)) @ standing_R(block)
    return make_T(R, (xy[0], xy[1], surface_z - standing_extent(block)[0]))[None]


def stack_targets(base: PartType, T_base: np.ndarray, block: PartType) -> np.ndarray:
    """(M, 4, 4) poses of ``block`` standing centred on the top of ``base`` at ``T_base``, one per symmetric
    copy of the base's frame that keeps it standing (so the block's yaw is compared modulo the base's
    symmetries too)."""
    frames = np.einsum("ij,njk->nik", T_base, symmetries(base)) @ make_T(standing_R(base).T, np.zeros(3))
    up = frames[:, 2, 2] > 0.9  # those with z up (all, if the base has fallen over)
    frames = frames[up] if up.any() else frames
    lift = make_T(standing_R(block), (0.0, 0.0, standing_extent(base)[1] - standing_extent(block)[0]))
    return frames @ lift


def believed_upright(block: PartType, T_world_obj: np.ndarray, tol_deg: float) -> bool:
    """Does the (estimated) pose stand the block upright, within ``tol_deg``?"""
    return tilt_deg(block, T_world_obj[:3, :3]) <= tol_deg


def verdict(err: UprightDeviation, pos_tol: float, yaw_tol_deg: float, upright_tol_deg: float) -> str | None:
    """Failure reason of a placed block's error against its target, or None on success."""
    if err.tilt_deg > upright_tol_deg:
        return WRONG_FACE
    if err.te > pos_tol:
        return "misplaced"
    if abs(err.yaw_deg) > yaw_tol_deg:
        return MISALIGNED
    return None


def kitting_verdict(block: PartType, T_final: np.ndarray, xy: np.ndarray, surface_z: float,
                    cfg: KittingConfig) -> tuple[UprightDeviation, str | None]:
    """The kitted block's final pose against the kit pose over ``xy``, and the failure reason (None: kitted)."""
    err = upright_error(block, T_final, kit_targets(block, xy, surface_z, cfg))
    return err, verdict(err, cfg.pos_tol, cfg.yaw_tol_deg, cfg.upright_tol_deg)


def stack_verdict(base: PartType, T_base_start: np.ndarray, T_base_final: np.ndarray, block: PartType,
                  T_final: np.ndarray, cfg: StackConfig) -> tuple[UprightDeviation, float, str | None]:
    """The stacked block's final pose against the base's top (as the base ends), how far the base moved (m)
    and the failure reason (None: stacked)."""
    err = upright_error(block, T_final, stack_targets(base, T_base_final, block))
    shift = float(np.linalg.norm(T_base_final[:3, 3] - T_base_start[:3, 3]))
    reason = BASE_MOVED if shift > cfg.base_move_tol else verdict(err, cfg.pos_tol, cfg.yaw_tol_deg,
                                                                    cfg.upright_tol_deg)
    return err, shift, reason


def task_types(cfg: TrialConfig) -> list[PartType]:
    """The block types the task's scenes draw from (the scene's ``block_types``, or its whole object set)."""
    cat = load_catalog(cfg.scene.workcell.objects)
    return [cat[n] for n in cfg.scene.block_types if n in cat] if cfg.scene.block_types else list(cat.values())


def check_task(cfg: TrialConfig) -> None:
    """UserError unless ``cfg.task`` is a task the scene's block types can serve."""
    if cfg.task not in TASKS:
        raise UserError(f"unknown task {cfg.task!r}; choose one of: {', '.join(TASKS)}")
    unknown = [t for t in firm_hold_tasks(cfg) if t not in TASKS]
    if unknown:
        raise UserError(f"firm_hold_tasks names unknown task(s) {unknown}; choose among: {', '.join(TASKS)}")
    types = task_types(cfg)
    names = ", ".join(b.name for b in types)
    if cfg.task == "kitting" and not any(b.upright_down is not None for b in types):
        raise UserError(f"task kitting needs an object type with an upright face; the scene's types ({names}) "
                        "have none: add one to scene.block_types")
    if cfg.task == "stack" and not any(can_stack(a, b) for a in types for b in types):
        raise UserError(f"task stack needs an object type with a flat top and one with a flat bottom that fits "
                        f"on it; the scene's types ({names}) have no such pair: choose other scene.block_types "
                        "or another --objects set")
