"""A block's pose against an upright target pose, modulo the block's symmetries.

With ``S`` the block's symmetry transforms (``catalog.symmetry_transforms``, continuous ones every 1 deg) the
frames ``T S`` describe the same physical block as ``T``. Against target frames ``T_t`` (a set too: a stack
target inherits the base's symmetries), among the copies standing on the upright face (``R S d`` within
45 deg of down, if any does), the pair with the smallest rotation angle
``angle(R_t^T R S) = arccos((tr - 1) / 2)`` is the match; for it

- ``re_deg``: that angle, the rotation error modulo symmetries;
- ``yaw_deg``: its component about the vertical, ``atan2(M[1,0] - M[0,1], M[0,0] + M[1,1])`` of
  ``M = R S R_t^T`` (world frame);
- ``tilt_deg``: the angle between the block's upright face normal ``R S d`` (``d = upright_down``) and the
  target's ``R_t d``: 0 when the right face is down;
- ``te``: the xy distance (m) between the matched frames' origins and ``dz`` their height difference.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from posegrasp.catalog import PartType, symmetry_transforms

#: Continuous symmetries are sampled every 360 / this degrees.
N_CONTINUOUS = 360
DOWN = np.array([0.0, 0.0, -1.0])


@dataclass(frozen=True)
class UprightDeviation:
    """A pose against its target, modulo symmetries: xy distance and height difference (m), rotation angle,
    yaw about the vertical and tilt of the upright face (deg)."""

    te: float
    dz: float
    re_deg: float
    yaw_deg: float
    tilt_deg: float


@functools.lru_cache(maxsize=32)
def symmetries(block: PartType) -> np.ndarray:
    """(K, 4, 4) symmetry transforms of a block (identity first, continuous ones every 1 deg)."""
    return symmetry_transforms(block, N_CONTINUOUS)


def match(cands: np.ndarray, targets: np.ndarray) -> tuple[int, int, float]:
    """Indices of the candidate and target frames (N, 4, 4) and (M, 4, 4) with the smallest rotation angle
    between them, and that angle (rad)."""
    tr = np.einsum("mji,nji->mn", targets[:, :3, :3], cands[:, :3, :3])  # trace(R_t^T R_c)
    j, i = np.unravel_index(int(np.argmax(tr)), tr.shape)
    return int(i), int(j), float(np.arccos(np.clip((tr[j, i] - 1.0) / 2.0, -1.0, 1.0)))


def yaw_between(R_from: np.ndarray, R_to: np.ndarray) -> float:
    """Angle (rad) about the world vertical that best turns ``R_from`` into ``R_to``."""
    M = R_to @ R_from.T
    return float(np.arctan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1]))


def standing_copies(block: PartType, T_world_obj: np.ndarray) -> np.ndarray:
    """(K, 4, 4) the symmetric copies ``T S`` of a pose that stand on the upright face (within 45 deg of
    down), or all of them if none does: an L-block's copy flipped onto its leg is nearer a target in angle
    than the upright copy turned by 114 deg, but turning it about the vertical cannot get it there."""
    cands = np.einsum("ij,njk->nik", T_world_obj, symmetries(block))
    if block.upright_down is None:
        return cands
    up = (cands[:, :3, :3] @ block.upright_down) @ DOWN > np.cos(np.radians(45.0))
    return cands[up] if up.any() else cands


def upright_error(block: PartType, T_world_obj: np.ndarray, targets: np.ndarray,
                  standing: bool = True) -> UprightDeviation:
    """Error of ``T_world_obj`` against the nearest of the target frames ``targets`` (M, 4, 4), modulo the
    block's symmetries (module docstring); ``standing=False`` compares every copy (an estimate against the
    ground truth, which need not stand)."""
    cands = standing_copies(block, T_world_obj) if standing else np.einsum("ij,njk->nik", T_world_obj,
                                                                             symmetries(block))
    i, j, angle = match(cands, np.asarray(targets).reshape(-1, 4, 4))
    Tc, Tt = cands[i], np.asarray(targets).reshape(-1, 4, 4)[j]
    d = DOWN if block.upright_down is None else block.upright_down
    tilt = np.arccos(np.clip((Tc[:3, :3] @ d) @ (Tt[:3, :3] @ d), -1.0, 1.0))
    return UprightDeviation(float(np.linalg.norm(Tc[:2, 3] - Tt[:2, 3])), float(Tc[2, 3] - Tt[2, 3]),
                        float(np.degrees(angle)), float(np.degrees(yaw_between(Tt[:3, :3], Tc[:3, :3]))),
                        float(np.degrees(tilt)))


def tilt_deg(block: PartType, R_world_obj: np.ndarray) -> float:
    """Angle (deg) between straight down and the nearest symmetric copy of the block's upright face normal:
    0 for a block standing upright; 180 if the type has no upright pose."""
    if block.upright_down is None:
        return 180.0
    downs = (R_world_obj @ symmetries(block)[:, :3, :3] @ block.upright_down)
    return float(np.degrees(np.arccos(np.clip(downs @ DOWN, -1.0, 1.0).max())))
