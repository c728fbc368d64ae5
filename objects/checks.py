"""Whether an object suits the workcell: the Jaco hand's opening, the pick area and the hand camera.

The hand holds an object across a span ``w(d)``, its width along a direction ``d`` (the hull's extent along
``d``). ``w`` is continuous on the sphere of directions, so it takes every value between its minimum (the
narrowest width) and its maximum (the diameter): some span fits the fingers' opening ``[min_width, max_width]``
exactly when ``narrowest <= max_width`` and ``diameter >= min_width``. The narrowest width is taken over the hull's
face normals and 2000 spread directions (an upper bound within a fraction of a percent).
"""

from __future__ import annotations

import numpy as np
import trimesh

from posegrasp.objects.config import FitCheckConfig


def _spread_directions(n: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over a hemisphere (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = i / n
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z ** 2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def narrowest_width(mesh: trimesh.Trimesh) -> float:
    """Smallest extent (m) of the mesh along any direction (its convex hull's minimum width)."""
    hull = mesh.convex_hull
    pts = np.asarray(hull.vertices)
    dirs = np.vstack([np.asarray(hull.face_normals), _spread_directions(2000)])
    proj = pts @ dirs.T
    return float((proj.max(0) - proj.min(0)).min())


def fit_warnings(mesh: trimesh.Trimesh, diameter: float, R_table_obj: np.ndarray, fit: FitCheckConfig,
                 min_pixels: float) -> list[str]:
    """One sentence per way the object (m, object frame; ``R_table_obj`` standing it upright) does not suit the
    workcell ``fit`` (empty when it suits it): no span fits the hand, it does not fit the pick area, or it spans
    under ``min_pixels`` (px) in the hand camera at the look pose."""
    hand = fit.hand_span
    out = []
    narrow = narrowest_width(mesh)
    if narrow > hand[1]:
        out.append(f"the Jaco hand cannot grasp it: its narrowest span, {narrow * 1000:.1f} mm, exceeds the "
                   f"fingers' opening of {hand[1] * 1000:.1f} mm")
    if diameter < hand[0]:
        out.append(f"the Jaco hand cannot grasp it: it is {diameter * 1000:.1f} mm across at most, below the "
                   f"fingers' smallest span of {hand[0] * 1000:.1f} mm")
    foot = np.asarray(mesh.convex_hull.vertices) @ R_table_obj.T
    ex, ey = foot[:, :2].max(0) - foot[:, :2].min(0)
    ax, ay = 2 * fit.pick_area_half_size[0], 2 * fit.pick_area_half_size[1]
    if not ((ex <= ax and ey <= ay) or (ey <= ax and ex <= ay)):
        out.append(f"too large for the pick area: it stands {ex * 1000:.0f} x {ey * 1000:.0f} mm upright, the area "
                   f"is {ax * 1000:.0f} x {ay * 1000:.0f} mm")
    px = diameter * fit.focal_px / fit.look_height
    if px < min_pixels:
        out.append(f"too small for the pick area's camera: {px:.1f} px across from the look pose, below "
                   f"{min_pixels:g} px")
    return out
