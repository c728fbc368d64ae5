"""Resting-pose prior: a block on the table lies on one of its flat faces, or a cylinder on its side.

A pose estimate a few degrees off level makes the planner approach at a tilt and misjudge the block's
top and bottom. The planner therefore levels an estimate whose nearest resting direction is within
``max_tilt_deg`` of straight down: with ``R`` the estimated rotation and ``n`` the object-frame outward
normal of a flat face of the convex hull (or ``a``, a continuous symmetry axis, which lies horizontal),

    R' = R_c R,   R_c = rot(R n x -z, angle(R n, -z))   (face down)
    R' = R_c R,   R_c = rot(R a x z, -asin((R a) . z))     (axis level)

taking the smallest correction, about the block's centre. When the levelled block's lowest point is then
within ``max_gap`` of the table top (z = 0), it is set onto it. Blocks leaning more steeply (on another
block) keep their estimate. The oracle's poses pass through unchanged (they are level already).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.spatial import ConvexHull

from posegrasp.config import settings
from posegrasp.catalog import PartType
from posegrasp.geometry import axis_angle_R, make_T, transform_points


@settings
class RestConfig:
    """When to level a pose estimate (see the module docstring)."""

    #: Level pose estimates that nearly rest on the table.
    enabled: bool = True
    #: Level estimates at most this far (deg) from a resting pose.
    max_tilt_deg: float = 8.0
    #: Set levelled estimates onto the table when their bottom is this close (m) to it.
    max_gap: float = 0.01
    #: Hull faces smaller than this share of the hull's area are no resting faces.
    min_face_share: float = 0.04


@functools.lru_cache(maxsize=32)
def rest_normals(block: PartType, min_face_share: float = 0.04) -> np.ndarray:
    """(F, 3) outward unit normals (object frame) of the block's convex-hull faces it can lie on: coplanar
    hull triangles merged, faces of at least ``min_face_share`` of the hull's area."""
    hull = ConvexHull(block.vertices)
    tri = block.vertices[hull.simplices]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    keys, inverse = np.unique(np.round(hull.equations[:, :3], 3), axis=0, return_inverse=True)
    face_area = np.bincount(inverse.ravel(), weights=area, minlength=len(keys))
    n = keys[face_area >= min_face_share * area.sum()]
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _leveling(block: PartType, R: np.ndarray, min_face_share: float) -> tuple[float, np.ndarray]:
    """Smallest correction (angle rad, rotation) that brings ``R`` (world_obj) into a resting pose."""
    down = np.array([0.0, 0.0, -1.0])
    best = (np.inf, np.eye(3))
    for n in rest_normals(block, min_face_share) @ R.T:  # face normals in the world
        angle = float(np.arccos(np.clip(n @ down, -1.0, 1.0)))
        if angle < best[0]:
            axis = np.cross(n, down)
            best = (angle, axis_angle_R(axis, angle) if np.linalg.norm(axis) > 1e-9 else np.eye(3))
    for axis, _ in block.symmetries_continuous:
        a = R @ np.asarray(axis, dtype=float)
        elev = float(np.arcsin(np.clip(a[2], -1.0, 1.0)))  # the axis' angle above the horizontal
        h = np.cross(a, -down)
        if abs(elev) < best[0] and np.linalg.norm(h) > 1e-9:
            best = (abs(elev), axis_angle_R(h, -elev))
    return best


def rest_on_table(block: PartType, T_world_obj: np.ndarray, cfg: RestConfig = RestConfig(),
                  surface_z: float = 0.0) -> np.ndarray:
    """``T_world_obj`` (m) levelled into the nearest resting pose and set onto the table (or a horizontal
    surface at height ``surface_z``, m) if close to both; otherwise a copy of it unchanged."""
    T = np.array(T_world_obj, dtype=float)
    if not cfg.enabled:
        return T
    angle, R_c = _leveling(block, T[:3, :3], cfg.min_face_share)
    if angle > np.radians(cfg.max_tilt_deg):
        return T
    T = make_T(R_c @ T[:3, :3], T[:3, 3])
    bottom = float(transform_points(T, block.vertices)[:, 2].min())
    if abs(bottom - surface_z) <= cfg.max_gap:
        T[2, 3] -= bottom - surface_z
    return T
