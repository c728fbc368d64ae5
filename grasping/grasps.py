"""Grasp candidates for the 3-finger Jaco hand: top-down pinches planned in the object frame.

A grasp is a gripper (pinch-site) pose ``T_world_gripper``: z is the approach direction (straight down),
x the squeeze axis (finger 1 on +x opposes fingers 2 and 3 on -x), and the block's material centre sits at
``HAND_Y`` along the gripper y axis, between finger 1 and finger 3. Candidates are made per block type in
the object frame (every face as the top, both in-plane axes as the squeeze axis, a few offsets along the
face), expanded by the block's symmetries, moved into the world by the ESTIMATED pose, then checked on the
estimated geometry: the material span across the fingers at the pinch height, the table, the clearance
of the open hand from the neighbours' estimated surfaces, and (by the caller) IK reachability.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from posegrasp.grasping.config import GraspConfig
from posegrasp.catalog import BlockType, sample_surface, symmetry_transforms
from posegrasp.geometry import make_T, transform_points

#: Where the grasped block's centre sits along the gripper y axis (m): between finger 1 and finger 3.
HAND_Y = -0.005
#: Half width (m) of a finger pad along the gripper y axis, and the contact band around the pinch height.
_PAD_HALF = 0.012
_BAND = (-0.008, 0.012)  # heights relative to the pinch point that the closing fingertips touch
_PAD_OVERLAP = 0.004  # a yaw-stable pinch's contact face reaches this far past fingers 2 and 3's inner edges (m)
#: The open hand in the gripper frame (m), from the jaco_hand meshes: each finger is a box from its pad
#: (at half the opening along x) outward by _FINGER_OUTER, over its y span, from _TIP_BELOW past the pinch
#: point (the tips curl past it when closing) upward; the palm is a box starting 7 cm above the pinch point.
_TIP_BELOW = 0.012
_FINGER_OUTER = 0.03
_FINGER1_Y = ((-0.032, 0.002),)
_FINGER23_Y = ((-0.062, -0.022), (-0.002, 0.032))
_PALM = ((-0.06, -0.065, -1.0), (0.06, 0.035, -0.07))


@dataclass(frozen=True)
class Grasp:
    """One executable grasp: pinch-site pose (world), material span (m), hand clearance (m), tilt, the share
    of the contact window lying on the two contact planes (flatness, 0-0.5) and the score (higher is better)."""

    T_world_gripper: np.ndarray
    width: float
    clearance: float
    tilt_deg: float
    support: float
    score: float


def squeeze_axes(block: BlockType) -> list[int]:
    """Object axes (0, 1, 2) the fingers may squeeze along.

    Excluded: the axis of a continuous symmetry (a lying cylinder squeezed on its end discs slips out in
    simulation) and an axis whose two faces are one flat face and one broken one (< 50 % flat, e.g. the
    studs of a brick: the fingertips catch single studs).
    """
    V, tri = block.vertices, block.vertices[block.faces]
    lo, hi = V.min(0), V.max(0)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    axes = []
    for s in range(3):
        if any(abs(axis[s]) > 0.99 for axis, _ in block.symmetries_continuous):
            continue
        u, v = (i for i in range(3) if i != s)
        face = (hi[u] - lo[u]) * (hi[v] - lo[v])
        flat = [area[np.all(np.abs(tri[:, :, s] - plane) < 5e-4, axis=1)].sum() / face for plane in (lo[s], hi[s])]
        if min(flat) < 0.5 <= max(flat):
            continue
        axes.append(s)
    return axes


@functools.lru_cache(maxsize=32)
def object_candidates(block: BlockType, n_continuous: int = 36) -> np.ndarray:
    """(N, 4, 4) grasp frames ``T_obj_grasp`` (object frame, m): z = approach into a face, x = squeeze axis.

    Origins lie on the face at its centre and at +-1/4 of its length along the third axis; the set is
    closed under the block's symmetries (``symmetry_transforms``), duplicates removed.
    """
    lo, hi = block.vertices.min(0), block.vertices.max(0)
    centre, ext = (lo + hi) / 2, hi - lo
    frames = []
    eye = np.eye(3)
    allowed = squeeze_axes(block)
    for a in range(3):
        for sign in (1.0, -1.0):
            z = -sign * eye[a]  # approach from the +a (sign=1) or -a face, into the block
            for s in set(allowed) - {a}:
                x = eye[s]
                y = np.cross(z, x)
                l_axis = int(np.argmax(np.abs(y)))
                length = ext[l_axis]
                offsets = (0.0, -0.25 * length, 0.25 * length) if length >= 0.045 else (0.0,)
                for o in offsets:
                    p = centre.copy()
                    p[a] = hi[a] if sign > 0 else lo[a]
                    p[l_axis] += o
                    frames.append(make_T(np.stack([x, y, z], 1), p))
    syms = symmetry_transforms(block, n_continuous)
    out = np.einsum("sij,njk->snik", syms, np.stack(frames)).reshape(-1, 4, 4)
    key = np.round(np.concatenate([out[:, :3, 3] / 1e-3, out[:, :3, :3].reshape(-1, 9) / 0.05], 1)).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return out[np.sort(first)]


@functools.lru_cache(maxsize=32)
def surface_points(block: BlockType, n: int = 1500) -> np.ndarray:
    """(n, 3) surface samples of a block (object frame, m) used for width and clearance checks."""
    return np.concatenate([sample_surface(block, n, seed=0), block.vertices])


def _box_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Signed distance (m) of points (N, 3) to an axis-aligned box: negative inside."""
    d = np.maximum(lo - p, p - hi)
    outside = np.linalg.norm(np.maximum(d, 0.0), axis=1)
    inside = np.minimum(d.max(1), 0.0)
    return outside + inside


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def plan_grasps(block: BlockType, T_world_obj: np.ndarray, neighbours: np.ndarray, cfg: GraspConfig,
                yaw_now: float, opening_margin: float = 0.03, yaw_stable: bool = False) -> list[Grasp]:
    """Feasible top-down grasps on a block at its estimated pose, best first.

    ``neighbours``: (M, 3) world points (m) on the other blocks' estimated surfaces; ``yaw_now``: the
    gripper's current yaw (rad, angle of its x axis in the world xy plane), to prefer small wrist turns.
    The block's centre sits at ``HAND_Y`` along the gripper y axis; with ``yaw_stable`` it sits as near
    ``cfg.pose_hand_y`` as lets the contact faces reach the inner edges of both finger 2's and finger 3's pads
    (finger 1 against finger 3 alone is a couple that turns the block in the hand), or at ``HAND_Y`` if
    the faces are too narrow for that.
    """
    C = np.einsum("ij,njk->nik", T_world_obj, object_candidates(block))
    cos_tilt = -C[:, 2, 2]  # z axis against straight down
    keep = cos_tilt > np.cos(np.deg2rad(cfg.max_tilt_deg))
    C, tilt = C[keep], np.degrees(np.arccos(np.clip(cos_tilt[keep], -1, 1)))
    pts = transform_points(T_world_obj, surface_points(block))
    centre = T_world_obj[:3, 3]
    grasps: list[Grasp] = []
    seen: set[tuple[int, int, int]] = set()
    for Tc, tl in zip(C, tilt):
        xh = np.array([Tc[0, 0], Tc[1, 0], 0.0])
        if np.linalg.norm(xh) < 0.5:
            continue
        xh /= np.linalg.norm(xh)
        for x in (xh, -xh):
            key = (round(np.degrees(np.arctan2(x[1], x[0])) / 5), round(Tc[0, 3] / 0.003), round(Tc[1, 3] / 0.003))
            if key in seen:
                continue
            seen.add(key)
            g = _evaluate(x, Tc[:2, 3], float(tl), pts, centre, neighbours, cfg, yaw_now, opening_margin, yaw_stable)
            if g is not None:
                grasps.append(g)
    return sorted(grasps, key=lambda g: -g.score)


def _evaluate(x: np.ndarray, entry_xy: np.ndarray, tilt: float, pts: np.ndarray, centre: np.ndarray,
              neighbours: np.ndarray, cfg: GraspConfig, yaw_now: float, opening_margin: float,
              yaw_stable: bool = False) -> Grasp | None:
    """A straight-down grasp with squeeze axis ``x`` through ``entry_xy``, checked on the estimated geometry."""
    z = np.array([0.0, 0.0, -1.0])
    y = np.cross(z, x)
    R = np.stack([x, y, z], 1)
    rel = pts - np.array([entry_xy[0], entry_xy[1], 0.0])
    px, py, h = rel @ x, rel @ y, pts[:, 2]
    column = (np.abs(px) < cfg.max_width / 2) & (np.abs(py) < _PAD_HALF)
    if not column.any():
        return None
    best = None
    for depth in cfg.contact_depths:  # the pinch height with the flattest contact faces ...
        z_pinch = max(h[column].max() - depth, cfg.min_pinch_height)
        band = column & (h > z_pinch + _BAND[0]) & (h < z_pinch + _BAND[1])
        if not band.any():
            continue
        lo, hi = px[band].min(), px[band].max()
        # Flat contact faces: the share of the window's points on each extreme plane (studs, curves: few).
        support = min((px[band] < lo + 0.0015).sum(), (px[band] > hi - 0.0015).sum()) / band.sum()
        merit = support - 5.0 * abs(z_pinch - centre[2])  # and close to the centre's height (less torque)
        if best is None or merit > best[0]:
            best = (merit, support, z_pinch, lo, hi)
    if best is None:
        return None
    _, support, z_pinch, lo, hi = best
    hand_y = HAND_Y
    if yaw_stable:  # the contact face's span along y at the pinch height, shifted by hand_y, must cover both
        face = (np.abs(px - lo) < 0.0015) & (np.abs(h - z_pinch) < 0.004)  # inner pad edges of fingers 2, 3
        inner2, inner3 = _FINGER23_Y[0][1] - _PAD_OVERLAP, _FINGER23_Y[1][0] + _PAD_OVERLAP
        if face.any() and inner3 - py[face].max() <= inner2 - py[face].min():
            hand_y = float(np.clip(cfg.pose_hand_y, inner3 - py[face].max(), inner2 - py[face].min()))
    width = float(hi - lo)
    if not cfg.min_width <= width <= cfg.max_width:
        return None
    grasp_point = np.array([entry_xy[0], entry_xy[1], z_pinch]) + 0.5 * (lo + hi) * x
    T = make_T(R, grasp_point - hand_y * y)
    clearance = 0.05
    if len(neighbours):
        local = (neighbours - T[:3, 3]) @ R  # gripper frame
        o = width / 2 + opening_margin / 2
        boxes = [((o, y0, -1.0), (o + _FINGER_OUTER, y1, _TIP_BELOW)) for y0, y1 in _FINGER1_Y] + \
                [((-o - _FINGER_OUTER, y0, -1.0), (-o, y1, _TIP_BELOW)) for y0, y1 in _FINGER23_Y] + [_PALM]
        clearance = min(clearance, min(float(_box_distance(local, np.array(lo), np.array(hi)).min())
                                       for lo, hi in boxes))
        if clearance < cfg.clearance_min:
            return None
    off_centre = float(np.linalg.norm(grasp_point[:2] - centre[:2]))
    turn = abs(float(_wrap(np.arctan2(x[1], x[0]) - yaw_now)))
    score = (-0.01 * tilt - 30.0 * off_centre + 20.0 * min(clearance, 0.02) - 0.3 * turn - 2.0 * width
             + 2.0 * support)
    return Grasp(T, width, clearance, tilt, float(support), float(score))
