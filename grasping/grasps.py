"""Grasp candidates for the Jaco hand: top-down pinches planned in the object frame.

A grasp is a gripper (pinch-site) pose ``T_world_gripper``: z is the approach direction (straight down),
x the squeeze axis (finger 1 on +x opposes fingers 2 and 3, or 3, on -x), and the block's material centre sits at
the hand's ``hand_y`` along the gripper y axis (the hand's geometry: ``grasping.hand``;
the score's weights: ``config.GraspScoreConfig``). Candidates are made per block type in the object frame
(every face as the top, both in-plane axes as the squeeze axis, a few offsets along the face) where those suit
the shape (``faces_fit``: boxes, prisms, round parts, the shipped blocks), else from
the mesh's own antipodal pairs (``antipodal_pairs``: any imported shape), expanded by the block's symmetries,
moved into the world by the ESTIMATED pose, then checked on the estimated geometry: the material span across
the fingers at the pinch height, the table, the clearance of the open hand from the neighbours' estimated
surfaces, and (by the caller) IK reachability.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from posegrasp.grasping.config import GraspConfig
from posegrasp.grasping.hand import (CONTACT_BAND, FACE_REACH, FLAT_PINCH_DROP, KG3, ON_PLANE_TOL, PAD_FACE_HEIGHT,
                                     PAD_HALF_WIDTH, PAD_OVERLAP, Hand)
from posegrasp.catalog import PartType, sample_surface, symmetry_transforms
from posegrasp.geometry import make_T, transform_points

#: On shapes with mesh-made candidates (``faces_fit`` false) the span is measured this far past the widest
#: opening on each side, so that material reaching past it (a handle beside the pinched body) makes the span
#: too wide instead of going unseen (m).
_COLUMN_MARGIN = 0.005
_SPAN_TOL = 0.003  # ... and the span must be that of the antipodal pair the candidate was made for, within this (m)
#: The clearance a grasp records when no neighbour comes closer (m).
_CLEAR = 0.05


@dataclass(frozen=True)
class Grasp:
    """One executable grasp: pinch-site pose (world), material span (m), hand clearance (m), tilt, the share
    of the contact window lying on the two contact planes (flatness, 0-0.5) and the score (higher is better);
    ``stable``: the contact face reaches the pads of fingers 2 and 3 (``plan_grasps``' ``yaw_stable``)."""

    T_world_gripper: np.ndarray
    width: float
    clearance: float
    tilt_deg: float
    support: float
    score: float
    stable: bool = True


def squeeze_axes(block: PartType, all_axes: bool = False) -> list[int]:
    """Object axes (0, 1, 2) the fingers may squeeze along: all three with ``all_axes``, else not these two.

    The axis of a continuous symmetry (a lying cylinder squeezed on its end discs slips out of the 3-finger hand
    in simulation) and an axis whose two faces are one flat face and one broken one (< 50 % flat, e.g. the
    studs of a brick: the 3-finger hand's fingertips catch single studs). The 2-finger hand's pads, centred and
    facing each other, hold both (``Hand.all_axes``).
    """
    if all_axes:
        return [0, 1, 2]
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


#: Antipodal candidates: both contact normals within this half-angle (deg) of the squeeze axis (a friction
#: coefficient of tan(15 deg) = 0.27, well inside the simulated 0.9, so the pinch holds off-centre too), from
#: this many seeded surface samples, each pair approached from this many directions around its squeeze axis.
ANTIPODAL_CONE_DEG = 15.0
_ANTIPODAL_SAMPLES = 600
_APPROACHES = 12
_PATCH_RADIUS = 0.005  # the surface this close to a contact must face the finger (m)


def _face_normals(block: PartType) -> np.ndarray:
    """(M, 3) outward unit normals of the block's triangles (object frame)."""
    tri = block.vertices[block.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def _surface_samples(block: PartType, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``sample_surface``'s (n, 3) points (m, object frame) and the index of the triangle of each (its first
    draw, repeated)."""
    tri = block.vertices[block.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    idx = np.random.default_rng(seed).choice(len(tri), size=n, p=area / area.sum())
    return sample_surface(block, n, seed), idx


def _flat_patches(pts: np.ndarray, normals: np.ndarray, tree: cKDTree, contacts: np.ndarray, facing: np.ndarray,
                  cos_cone: float) -> np.ndarray:
    """(K,) bool: does the surface within ``_PATCH_RADIUS`` of ``contacts[k]`` and 2 mm of its tangent plane face
    ``facing[k]`` within the cone everywhere (a finger pad rests on it, not on a thin rim or a stud; a thin wall's
    inside is not in the way)? ``pts``/``normals``: surface samples (m), ``tree`` a k-d tree of ``pts``."""
    near = cKDTree(contacts).sparse_distance_matrix(tree, _PATCH_RADIUS, output_type="ndarray")
    owner, idx = near["i"], near["j"]
    rel = pts[idx] - contacts[owner]
    f = facing[owner]
    on = (np.linalg.norm(rel, axis=1) < _PATCH_RADIUS) & (np.abs(np.einsum("ij,ij->i", rel, f)) < 0.002)
    away = on & (np.einsum("ij,ij->i", normals[idx], f) < cos_cone)
    return np.bincount(owner[away], minlength=len(contacts)) == 0


@functools.lru_cache(maxsize=32)
def antipodal_pairs(block: PartType, n: int = _ANTIPODAL_SAMPLES, seed: int = 0,
                    cone_deg: float = ANTIPODAL_CONE_DEG, min_width: float = GraspConfig.min_width,
                    max_width: float = GraspConfig.max_width) -> np.ndarray:
    """(K, 2, 3) antipodal contact pairs ``[finger-side contact, far contact]`` (object frame, m).

    Dex-Net style: ``n`` points drawn uniformly over the surface (seeded), a ray from each straight into the
    part along its inward normal, and the point where it leaves the part for good is the opposite contact (the
    fingers close from outside: across a hollow or a slot they touch the outer walls).
    A pair is kept when the outward normal there lies within ``cone_deg`` of the ray (both normals oppose
    within the friction cone), the span is within ``min_width``-``max_width`` and the surface within 5 mm of
    each contact faces the finger within the cone (a pad rests on it, not on a thin rim, a handle or a stud's
    side). Dropped: pairs along a continuous symmetry axis (a round end slips out), and pairs within 3 mm and
    10 deg of a kept one. Same block and seed, same pairs.
    """
    import trimesh

    normals = _face_normals(block)
    pts, idx = _surface_samples(block, 10 * n, seed)  # the first n start rays, all check contact patches
    pt_n = normals[idx]
    tree = cKDTree(pts)
    p1, d = pts[:n], -pt_n[:n]
    mesh = trimesh.Trimesh(np.asarray(block.vertices), np.asarray(block.faces), process=False)
    hits, ray, face = trimesh.ray.ray_triangle.RayMeshIntersector(mesh).intersects_location(
        p1 + 1e-6 * d, d, multiple_hits=True)
    cos_cone = np.cos(np.deg2rad(cone_deg))
    dist = np.einsum("ij,ij->i", hits - p1[ray], d[ray])
    exits = np.flatnonzero((dist > 1e-5) & (np.einsum("ij,ij->i", normals[face], d[ray]) > 0.0))  # leaving
    last: dict[int, int] = {}
    for h in exits[np.lexsort((-dist[exits], ray[exits]))]:  # where each ray leaves the part for good
        last.setdefault(int(ray[h]), int(h))
    rays = np.array(sorted(last), dtype=np.int64)
    h = np.array([last[r] for r in rays], dtype=np.int64)
    axis, width, far = d[rays], dist[h], hits[h]
    round_axes = np.array([a for a, _ in block.symmetries_continuous]).reshape(-1, 3)
    ok = ((min_width <= width) & (width <= max_width) & (np.einsum("ij,ij->i", normals[face[h]], axis) >= cos_cone)
          & (np.abs(axis @ round_axes.T).max(1, initial=0.0) <= cos_cone))
    rays, axis, width, far = rays[ok], axis[ok], width[ok], far[ok]
    flat = _flat_patches(pts, pt_n, tree, np.concatenate([p1[rays], far]), np.concatenate([-axis, axis]), cos_cone)
    keep = flat[: len(rays)] & flat[len(rays):]
    # greedy: a pair within 3 mm and 10 deg of one kept before it is dropped
    cos10 = np.cos(np.deg2rad(10.0))
    mids, spans, pairs = np.empty((0, 3)), np.empty((0, 3)), []
    for r, a, w, q in zip(rays[keep], axis[keep], width[keep], far[keep]):
        mid = p1[r] + 0.5 * w * a
        if np.any((np.linalg.norm(mids - mid, axis=1) < 3e-3)
                  & (np.abs(spans @ a) > cos10 * np.linalg.norm(spans, axis=1))):
            continue
        pairs.append(np.stack([p1[r], q]))
        mids, spans = np.vstack([mids, 0.5 * (p1[r] + q)]), np.vstack([spans, q - p1[r]])
    return np.stack(pairs) if pairs else np.zeros((0, 2, 3))


def _pair_frames(pairs: np.ndarray) -> list[np.ndarray]:
    """Grasp frames ``T_obj_grasp`` for antipodal pairs: x along the pair, origin at its midpoint, z (approach)
    every ``360 / _APPROACHES`` degrees around x."""
    frames = []
    for q in pairs:
        x = (q[1] - q[0]) / np.linalg.norm(q[1] - q[0])
        ref = np.eye(3)[int(np.argmin(np.abs(x)))]
        a = np.cross(x, ref)
        a /= np.linalg.norm(a)
        b = np.cross(x, a)
        for k in range(_APPROACHES):
            t = 2.0 * np.pi * k / _APPROACHES
            z = np.cos(t) * a + np.sin(t) * b
            frames.append(make_T(np.stack([x, np.cross(z, x), z], 1), 0.5 * (q[0] + q[1])))
    return frames


@functools.lru_cache(maxsize=32)
def faces_fit(block: PartType) -> bool:
    """Do the face-based candidates suit this shape: does every one of its ``antipodal_pairs`` squeeze along a
    bounding-box axis (within the friction cone), moved by any of its symmetries?"""
    pairs = antipodal_pairs(block)
    axes = np.einsum("sij,aj->sai", symmetry_transforms(block)[:, :3, :3], np.eye(3)).reshape(-1, 3)
    spans = pairs[:, 1] - pairs[:, 0]
    along = np.abs(spans @ axes.T).max(1, initial=0.0) / np.linalg.norm(spans, axis=1)
    return bool(np.all(along >= np.cos(np.deg2rad(ANTIPODAL_CONE_DEG))))


@functools.lru_cache(maxsize=32)
def object_candidates(block: PartType, n_continuous: int = 36, all_axes: bool = False) -> np.ndarray:
    """(N, 4, 4) grasp frames ``T_obj_grasp`` (object frame, m): z = approach direction, x = squeeze axis, one of
    ``squeeze_axes(block, all_axes)`` (``candidate_spans`` gives the span each was made for)."""
    return candidate_spans(block, n_continuous, all_axes)[0]


@functools.lru_cache(maxsize=32)
def candidate_spans(block: PartType, n_continuous: int = 36, all_axes: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``object_candidates``' (N, 4, 4) frames and (N,) the span (m) of the antipodal pair each was made for
    (NaN for a face-based one).

    Origins lie on the face at its centre and at +-1/4 of its length along the third axis. These face-based
    frames suit shapes whose antipodal pairs all squeeze along a bounding-box axis (moved by the symmetries):
    boxes, prisms, round parts, brackets, the shipped blocks. A shape with a pair squeezing across anything
    else (a mug's body beside its handle, slanted or curved sides off the box axes) gets frames from its
    ``antipodal_pairs`` instead: x along the pair, origin at its midpoint, approach every 30 deg around x.
    The set is closed under the block's symmetries (``symmetry_transforms``), duplicates removed.
    """
    lo, hi = block.vertices.min(0), block.vertices.max(0)
    centre, ext = (lo + hi) / 2, hi - lo
    frames = []
    eye = np.eye(3)
    allowed = squeeze_axes(block, all_axes)
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
    spans = np.full(len(frames), np.nan)
    if not faces_fit(block):
        pairs = antipodal_pairs(block)
        frames = _pair_frames(pairs)
        spans = np.repeat(np.linalg.norm(pairs[:, 1] - pairs[:, 0], axis=1), _APPROACHES)
    out = np.einsum("sij,njk->snik", syms, np.stack(frames)).reshape(-1, 4, 4)
    key = np.round(np.concatenate([out[:, :3, 3] / 1e-3, out[:, :3, :3].reshape(-1, 9) / 0.05], 1)).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    keep = np.sort(first)
    return out[keep], np.tile(spans, len(syms))[keep]


@functools.lru_cache(maxsize=32)
def surface_points(block: PartType, n: int = 1500) -> np.ndarray:
    """(n, 3) surface samples of a block (object frame, m) used for width and clearance checks."""
    return np.concatenate([sample_surface(block, n, seed=0), block.vertices])


@functools.lru_cache(maxsize=32)
def surface_normals(block: PartType, n: int = 1500) -> np.ndarray:
    """Outward unit normals (object frame) of ``surface_points(block, n)``: each sample's triangle's, zero at
    the vertices appended after them (a vertex has no one normal)."""
    return np.concatenate([_face_normals(block)[_surface_samples(block, n, 0)[1]], np.zeros_like(block.vertices)])


def _box_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Signed distance (m) of points (N, 3) to an axis-aligned box: negative inside. Per coordinate column (a
    reduction along the rows' 3 values costs numpy 4x as much; the sums are the same, in the same order)."""
    d = np.maximum(lo - p, p - hi)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    ox, oy, oz = np.maximum(x, 0.0), np.maximum(y, 0.0), np.maximum(z, 0.0)
    return np.sqrt(ox * ox + oy * oy + oz * oz) + np.minimum(np.maximum(np.maximum(x, y), z), 0.0)


def near_boxes(p: np.ndarray, boxes: list, reach: float) -> np.ndarray:
    """Bool (...,): which points ``p`` (..., 3) lie within ``reach`` (m), plus 1 um for rounding, of the box that
    bounds all ``boxes`` (min corner, max corner) along each axis; the others are farther than ``reach`` from every
    box, so a clearance test up to ``reach`` need not measure them."""
    lo = np.min([b[0] for b in boxes], axis=0) - reach - 1e-6
    hi = np.max([b[1] for b in boxes], axis=0) + reach + 1e-6
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (z <= hi[2])


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def plan_grasps(block: PartType, T_world_obj: np.ndarray, neighbours: np.ndarray, cfg: GraspConfig,
                yaw_now: float, yaw_stable: bool = False, hand: Hand = KG3) -> list[Grasp]:
    """Feasible top-down grasps on a block at its estimated pose, best first.

    ``neighbours``: (M, 3) world points (m) on the other blocks' estimated surfaces; ``yaw_now``: the
    gripper's current yaw (rad, angle of its x axis in the world xy plane), to prefer small wrist turns.
    The block's centre sits at ``hand.hand_y`` along the gripper y axis; with ``yaw_stable`` (and a ``hand`` with
    fingers 2 and 3) it sits as near ``cfg.pose_hand_y`` as lets the contact faces reach the inner edges of both
    finger 2's and finger 3's pads (finger 1 against finger 3 alone is a couple that turns the block in the hand), or
    at ``hand.hand_y`` if
    the faces are too narrow for that; if some of the block's grasps are yaw-stable, the others score
    ``cfg.score.unstable`` less (an L-block pinched on its 25 mm end faces turned 10 deg in the hand, every time).
    The open hand of the clearance check is ``cfg.finger_margin`` wider than the grasp.
    """
    frames, spans = candidate_spans(block, all_axes=hand.all_axes)
    C = np.einsum("ij,njk->nik", T_world_obj, frames)
    cos_tilt = -C[:, 2, 2]  # z axis against straight down
    keep = cos_tilt > np.cos(np.deg2rad(cfg.max_tilt_deg))
    C, spans, tilt = C[keep], spans[keep], np.degrees(np.arccos(np.clip(cos_tilt[keep], -1, 1)))
    if not faces_fit(block):  # of a mesh pair's approaches that reach one grasp, the least tilted counts
        order = np.argsort(tilt, kind="stable")
        C, spans, tilt = C[order], spans[order], tilt[order]
    pts = transform_points(T_world_obj, surface_points(block))
    normals = surface_normals(block) @ T_world_obj[:3, :3].T
    centre = T_world_obj[:3, 3]
    reach = cfg.max_width / 2 + (0.0 if faces_fit(block) else _COLUMN_MARGIN)
    grasps: list[Grasp] = []
    seen: set[tuple[int, int, int]] = set()
    for Tc, tl, span in zip(C, tilt, spans):
        xh = np.array([Tc[0, 0], Tc[1, 0], 0.0])
        if np.linalg.norm(xh) < 0.5:
            continue
        xh /= np.linalg.norm(xh)
        for x in (xh, -xh):
            key = (round(np.degrees(np.arctan2(x[1], x[0])) / 5), round(Tc[0, 3] / 0.003), round(Tc[1, 3] / 0.003))
            if key in seen:
                continue
            seen.add(key)
            where = _Where(pts, normals, centre, neighbours, cfg, yaw_now, yaw_stable, reach, hand)
            g = _evaluate(x, Tc[:2, 3], float(tl), where)
            if g is not None and not abs(g.width - span) > _SPAN_TOL:  # a mesh candidate pinches its own pair
                grasps.append(g)
    if any(g.stable for g in grasps):
        grasps = [g if g.stable else dataclasses.replace(g, score=g.score - cfg.score.unstable) for g in grasps]
    return sorted(grasps, key=lambda g: -g.score)


@dataclass(frozen=True)
class _Where:
    """What a grasp is checked against: the part's estimated surface points ``pts``, their outward ``normals``
    (zero where none) and its centre, the neighbours' points (world, m), the planner's settings, the wrist's yaw now
    (rad), whether the hold must be yaw-stable, the reach (m) along the squeeze axis within which the span is
    measured (None: half the widest opening), the hand."""

    pts: np.ndarray
    normals: np.ndarray
    centre: np.ndarray
    neighbours: np.ndarray
    cfg: GraspConfig
    yaw_now: float
    yaw_stable: bool = False
    reach: float | None = None
    hand: Hand = KG3


def _evaluate(x: np.ndarray, entry_xy: np.ndarray, tilt: float, where: _Where) -> Grasp | None:
    """A straight-down grasp with squeeze axis ``x`` through ``entry_xy``, checked on the estimated geometry
    (``where``); the span is measured on the surface points within ``where.reach`` of the entry along ``x``."""
    pts, centre, neighbours, cfg = where.pts, where.centre, where.neighbours, where.cfg
    yaw_now, yaw_stable, reach, hand = where.yaw_now, where.yaw_stable, where.reach, where.hand
    z = np.array([0.0, 0.0, -1.0])
    y = np.cross(z, x)
    R = np.stack([x, y, z], 1)
    rel = pts - np.array([entry_xy[0], entry_xy[1], 0.0])
    px, py, h = rel @ x, rel @ y, pts[:, 2]
    column = (np.abs(px) < (cfg.max_width / 2 if reach is None else reach)) & (np.abs(py) < PAD_HALF_WIDTH)
    if not column.any():
        return None
    best = None
    top = h[column].max()
    lowest = cfg.min_pinch_height - (FLAT_PINCH_DROP if top < cfg.min_pinch_height else 0.0)
    for depth in cfg.contact_depths:  # the pinch height with the flattest contact faces ...
        z_pinch = max(top - depth, lowest)
        band = column & (h > z_pinch + CONTACT_BAND[0]) & (h < z_pinch + CONTACT_BAND[1])
        if not band.any():
            continue
        lo, hi = px[band].min(), px[band].max()
        # Flat contact faces: the share of the window's points on each extreme plane (studs, curves: few).
        support = min((px[band] < lo + ON_PLANE_TOL).sum(), (px[band] > hi - ON_PLANE_TOL).sum()) / band.sum()
        merit = support - cfg.score.pinch_height * abs(z_pinch - centre[2])  # near the centre's height: less torque
        if best is None or merit > best[0]:
            best = (merit, support, z_pinch, lo, hi, band)
    if best is None:
        return None
    _, support, z_pinch, lo, hi, band = best
    opposed = _opposed(where.normals[band & (px < lo + ON_PLANE_TOL)], where.normals[band & (px > hi - ON_PLANE_TOL)])
    hand_y, stable = hand.hand_y, True
    if yaw_stable and hand.paired:  # the contact face's y span at the pinch height, shifted by hand_y, covers both
        on_face = np.abs(px - lo) < ON_PLANE_TOL
        face = on_face & (np.abs(h - z_pinch) < PAD_FACE_HEIGHT)  # inner pad edges of fingers 2, 3
        inner2, inner3 = hand.facing_y[0][1] - PAD_OVERLAP, hand.facing_y[1][0] + PAD_OVERLAP
        narrowest = _face_span(on_face, py, h, z_pinch)
        stable = narrowest is not None and inner3 - narrowest[1] <= inner2 - narrowest[0]
        if face.any() and inner3 - py[face].max() <= inner2 - py[face].min():
            hand_y = float(np.clip(cfg.pose_hand_y, inner3 - py[face].max(), inner2 - py[face].min()))
    width = float(hi - lo)
    if not cfg.min_width <= width <= cfg.max_width:
        return None
    grasp_point = np.array([entry_xy[0], entry_xy[1], z_pinch]) + 0.5 * (lo + hi) * x
    T = make_T(R, grasp_point - hand_y * y)
    clearance = _CLEAR
    if len(neighbours):
        local = (neighbours - T[:3, 3]) @ R  # gripper frame
        boxes = hand.boxes(width / 2 + cfg.finger_margin / 2)
        clearance = min(clearance, min(float(_box_distance(local, np.array(lo), np.array(hi)).min())
                                       for lo, hi in boxes))
        if clearance < cfg.clearance_min:
            return None
    off_centre = float(np.linalg.norm(grasp_point[:2] - centre[:2]))
    turn = abs(float(_wrap(np.arctan2(x[1], x[0]) - yaw_now)))
    w = cfg.score
    score = (-w.tilt * tilt - w.off_centre * off_centre + w.clearance * min(clearance, w.clearance_cap)
             - w.turn * turn - w.width * width + w.support * support - (0.0 if opposed else w.unopposed))
    return Grasp(T, width, clearance, tilt, float(support), float(score), stable)


def _opposed(n_lo: np.ndarray, n_hi: np.ndarray) -> bool:
    """Do the two contact regions oppose each other: some outward normal of each (rows of ``n_lo``, ``n_hi``; zero
    rows, vertices, count for nothing) within twice ``ANTIPODAL_CONE_DEG`` of antiparallel, so that a line between
    the contacts lies within both friction cones? Parallel faces at any tilt and edges do; a prism's two 60 deg
    slopes do not (each pad's edge presses a face turned 30 deg from it: the squeeze drives the prism down and out
    of the fingers; its end caps hold), and such a grasp scores ``GraspScoreConfig.unopposed`` less."""
    a, b = n_lo[np.any(n_lo != 0.0, axis=1)], n_hi[np.any(n_hi != 0.0, axis=1)]
    return not len(a) or not len(b) or float((-a @ b.T).max()) >= np.cos(np.deg2rad(2.0 * ANTIPODAL_CONE_DEG))


def _face_span(on: np.ndarray, py: np.ndarray, h: np.ndarray, z_pinch: float) -> tuple[float, float] | None:
    """The y extent (m, gripper frame) that the contact face (the surface points ``on`` it) covers both
    ``FACE_REACH`` above and below the pinch height (points within ``ON_PLANE_TOL`` of each), or None where it is
    missing: an L-block pinched at its upright part's foot has a long face below and a short one above."""
    ends = []
    for dz in (-FACE_REACH, FACE_REACH):
        s = on & (np.abs(h - (z_pinch + dz)) < ON_PLANE_TOL)
        if not s.any():
            return None
        ends.append((py[s].min(), py[s].max()))
    return max(a for a, _ in ends), min(b for _, b in ends)
