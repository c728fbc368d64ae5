"""The upright resting face: the face an object stands on when kitted, its orientation on the table, and whether
it can stack.

A face of the convex hull with outward normal ``n`` is a stable resting face when the centre of mass, projected
along ``n``, falls inside the polygon of hull vertices lying in that face's plane (the footprint). The mesh's own
bottom (``n = -z`` of its frame) is kept when stable (a CAD part is usually drawn standing); otherwise the stable
face with the centre of mass lowest above it (the most stable). ``R_table_obj`` turns ``n`` onto the table's ``-z``
by the smallest rotation, which also fixes the kit's yaw.

Standing so, its bottom is flat when the mesh's own faces in the resting plane cover at least a quarter of its
upright bounding rectangle on the table (an arch's two feet do, a 32-gon cylinder's side facet does not), and its
top is flat when the faces in the highest plane parallel to it cover at least 65 % of that rectangle, so that a
part of the same size can stand on it (a round top does, 78 %; a brick's studs and an L's upright leg do not).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from posegrasp.geometry import axis_angle_R


FLAT_BOTTOM = 0.25  # fraction of the upright bounding rectangle the faces in the resting plane must cover
FLAT_TOP = 0.65  # ... and the faces in the top plane


@dataclass(frozen=True)
class Upright:
    """The upright pose: ``R_table_obj`` (3, 3), the resting face's outward normal ``down`` (object frame, unit),
    and whether the bottom and the top are flat (can stack)."""

    R_table_obj: np.ndarray
    down: np.ndarray
    flat_bottom: bool
    flat_top: bool


def _footprint(hull: np.ndarray, n: np.ndarray, tol: float) -> tuple[ConvexHull, np.ndarray] | None:
    """2D convex hull of the hull vertices in the extreme plane along ``n``, and the (2, 3) in-plane basis."""
    h = hull @ n
    on = hull[h >= h.max() - tol]
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    basis = np.stack([u, np.cross(n, u)])
    try:
        return ConvexHull(on @ basis.T), basis
    except (QhullError, ValueError):  # a vertex or an edge: no area to stand on
        return None


def _plane_area(mesh: trimesh.Trimesh, n: np.ndarray, tol: float) -> float:
    """Area (m^2) of the mesh faces facing ``n`` (within 1 deg) in the mesh's extreme plane along ``n``."""
    h = np.asarray(mesh.vertices) @ n
    in_plane = (np.asarray(mesh.face_normals) @ n > np.cos(np.deg2rad(1.0))) & \
        (h[np.asarray(mesh.faces)].min(axis=1) >= h.max() - tol)
    return float(np.asarray(mesh.area_faces)[in_plane].sum())


def _supports(hull: np.ndarray, com: np.ndarray, n: np.ndarray, tol: float) -> float | None:
    """Height (m) of ``com`` above the plane of hull face direction ``n`` if the object rests stably on it."""
    foot = _footprint(hull, n, tol)
    if foot is None:
        return None
    poly, basis = foot
    inside = (poly.equations[:, :2] @ (basis @ com) + poly.equations[:, 2] < -tol).all()
    return float((hull @ n).max() - com @ n) if inside else None


def turn_onto(n: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking unit vector ``n`` onto unit vector ``target``."""
    axis = np.cross(n, target)
    s, c = np.linalg.norm(axis), float(n @ target)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        return axis_angle_R(perp / np.linalg.norm(perp), np.pi)
    return axis_angle_R(axis / s, float(np.arctan2(s, c)))


def upright(mesh: trimesh.Trimesh, com: np.ndarray, tol: float) -> Upright:
    """The upright pose of ``mesh`` (m) with centre of mass ``com``.

    ``tol`` (m) is how far a vertex may lie off a face's plane and still count as in it.
    """
    hull = mesh.convex_hull
    pts = np.asarray(hull.vertices)
    down = np.array([0.0, 0.0, -1.0])
    if _supports(pts, com, down, tol) is None:
        normals = np.vstack([np.asarray(hull.facets_normal).reshape(-1, 3), np.asarray(hull.face_normals)])
        best = None
        for n in normals:
            h = _supports(pts, com, n / np.linalg.norm(n), tol)
            if h is not None and (best is None or h < best[0] - tol):
                best = (h, n / np.linalg.norm(n))
        down = best[1] if best else down  # a closed solid has a stable face; fall back to -z all the same
    R = turn_onto(down, np.array([0.0, 0.0, -1.0]))
    xy = (pts @ R.T)[:, :2]
    area = float(np.prod(xy.max(0) - xy.min(0)))
    return Upright(R_table_obj=R, down=np.round(down, 12) + 0.0,
                   flat_bottom=bool(area > 0 and _plane_area(mesh, down, tol) >= FLAT_BOTTOM * area),
                   flat_top=bool(area > 0 and _plane_area(mesh, -down, tol) >= FLAT_TOP * area))
