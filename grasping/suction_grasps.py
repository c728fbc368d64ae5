"""Suction grasps: where a round cup seals on a part, planned on its ESTIMATED pose and model alone.

A suction grasp is a tool pose ``T_world_gripper``: origin at the centre of the cup's rim on the part's surface, z
the approach (the face's inward normal: into the part), x and y the wrist's turn about it (the cup is round, the
wrist is not). The tool is a ``CupGeometry``: the rim's radius r and seal tolerance, the cup, bellows and stem as a
cylinder from the rim up, the wrist and camera as boxes (gripper frame, ``grasping.hand.Box``'s layout), which come
the bellows' stroke nearer the part when the cup presses on it.

Where a cup seals is a property of the part type and the cup, so it is found once per pair in the object frame
(``cup_spots``): points drawn over the model's surface (area-weighted, seeded) and the centre of every flat face
that a rim fits in, each with its face's outward normal n. At each, a ray comes straight down -n onto the surface
from the points of the rim circle (``RIM_POINTS``, in the tangent plane), of the rings ``SLIDE_STEPS`` wider, and
of two inner rings and the centre; h, the surface's height above the tangent plane where it meets it, gives::

    seals        |h| <= seal_tol on the rim (across an edge the ray falls past the face, over a stud it meets
                 its top), h <= seal_tol inside it (nothing rises into the cup) and a surface under every inner
                 point (no hole through the part); the cup's body clears the part's own other faces
    seal_margin  = seal_tol - max |h| on the rim                    (how flat the patch is)
    edge_margin  = the widest SLIDE_STEPS ring that seals, all narrower ones sealing too (how far the cup may
                   slide off under a pose error and still seal)
    com_distance = |(c - p) - ((c - p) . n) n|   (m; c the model's centre of mass: the moment arm in the cup's plane)

On an estimate (``plan_suction``) the spots move into the world by the estimated pose; kept are those whose normal
lies within ``suction_max_tilt_deg`` of straight up, whose cup body keeps off the floor and ``suction_clearance``
from the other parts' points (their estimates' surfaces, the depth image's), ``suction_wall_clearance`` from the
walls', and whose wrist boxes do too (and clear the part's own surface), the wrist turned least from ``yaw_now``
(x the current heading projected onto the cup's plane, then turned 90, -90 or 180 deg about z where that clears)::

    score = margin_w * (seal_margin + edge_margin) - com_w * com_distance - tilt_w * tilt_deg - turn_w * turn
            + height_w * (top - floor)

(``BinPickConfig``'s ``suction_*`` weights, its ``turn_weight`` per radian of wrist turn and ``height_weight`` per
metre of the part's estimated top above the floor: the highest parts first). A part with no spot facing up gets no
grasp; ``unsealable`` names the part types a cup cannot seal on at all.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable

import numpy as np

from posegrasp.catalog import PartType
from posegrasp.errors import ConfigError
from posegrasp.geometry import transform_points
from posegrasp.grasping.grasps import (_box_distance, _face_normals, _surface_samples, _wrap, near_boxes,
                                       surface_points)
from posegrasp.grasping.hand import PALM, Box, camera_box
from posegrasp.sim.config import CameraConfig

if TYPE_CHECKING:
    from posegrasp.grasping.tasks.bin_pick.config import BinPickConfig

#: Points on the rim circle (and on each wider ring) where the surface must lie within the seal tolerance (as many
#: as the simulated cup's seal test takes).
RIM_POINTS = 32
#: The rings this much (m) wider than the rim checked for ``edge_margin``.
SLIDE_STEPS = (0.002, 0.004, 0.006)
_INNER = (0.0, 1.0 / 3.0, 2.0 / 3.0)  # inner rings (fractions of the rim's radius; 0: the centre alone)
_INNER_POINTS = 12
_TURNS_DEG = (0.0, 90.0, -90.0, 180.0)  # the wrist turns tried about the approach, least first
_CLEAR = 0.02  # the clearance (m) a grasp records when nothing comes closer
_SAME = (0.003, np.cos(np.radians(10.0)))  # a grasp this close (m) and this parallel to a better one is dropped
_CHUNK = 64  # candidates per block of the clearance checks (memory)
#: ``seen_seals``: the sectors of the rim's ring that must each show the face in the depth image.
SEEN_SECTORS = 8
#: ``seen_seals``: the rim's ring reaches in to this share of the rim's radius.
RING = 0.6
_EPS = 1e-9  # barycentric slack: a ray through a shared edge meets both triangles


@dataclass(frozen=True)
class CupGeometry:
    """The suction tool as the planner models it (m, gripper frame: origin at the rim's centre on the part, z into
    the part): the rim's ``radius``, ``seal_tol`` (the surface under the rim may lie this far off its plane), the
    cup, bellows and stem as a cylinder of ``body_radius`` from the rim up ``body_length`` (to the palm), the
    bellows' ``stroke`` (pressed on the part, the wrist comes down this much nearer it) and the wrist and camera as
    the boxes ``wrist`` (min corner, max corner each; above the rim, z <= 0, up out of reach as ``hand.PALM``).
    The defaults: a 20 mm cup on the Jaco's palm, its camera where ``CameraConfig`` mounts it."""

    radius: float = 0.01
    seal_tol: float = 0.0015
    body_radius: float = 0.01
    body_length: float = 0.072
    stroke: float = 0.01
    wrist: tuple[Box, ...] = (PALM, camera_box(CameraConfig().mount_pos))

    def __post_init__(self) -> None:
        if not 0.0 < self.radius < 1.0:
            raise ConfigError(f"cup radius must be in (0, 1) m, got {self.radius}")
        if not 0.0 <= self.seal_tol < self.radius:
            raise ConfigError(f"cup seal_tol must be in [0, radius) m, got {self.seal_tol}")
        if not self.radius <= self.body_radius < 1.0:
            raise ConfigError(f"cup body_radius must be in [radius, 1) m, got {self.body_radius}")
        if not 0.0 < self.body_length < 1.0:
            raise ConfigError(f"cup body_length must be in (0, 1) m, got {self.body_length}")
        if not 0.0 <= self.stroke < self.body_length:
            raise ConfigError(f"cup stroke must be in [0, body_length) m, got {self.stroke}")
        if not all(all(a < b for a, b in zip(*box)) and box[1][2] + self.stroke <= 0.0 for box in self.wrist):
            raise ConfigError(f"cup wrist boxes must be (min corner, max corner) above the rim by the stroke, got "
                              f"{self.wrist}")

    def boxes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The wrist boxes (min corner, max corner; m, gripper frame) with the bellows pressed: ``stroke`` nearer
        the part (+z)."""
        return [(np.asarray(lo) + [0, 0, self.stroke], np.asarray(hi) + [0, 0, self.stroke]) for lo, hi in self.wrist]


@dataclass(frozen=True)
class CupSpots:
    """Where a cup seals on a part type (object frame): (K, 3) ``points`` (m), their outward unit ``normals``, and
    per spot ``seal_margin``, ``edge_margin`` and ``com_distance`` (m; the module's docstring)."""

    points: np.ndarray
    normals: np.ndarray
    seal_margin: np.ndarray
    edge_margin: np.ndarray
    com_distance: np.ndarray


@dataclass(frozen=True)
class CupSurroundings:
    """What a suction grasp on one part must clear (world, m): ``others``, the other parts' points (their
    estimates' surfaces, the depth image's points off the target: ``bin_pick.planner.choose_part``'s ``around``),
    ``walls``, the walls' points (empty on a pile), the ``floor``'s height, the wrist's yaw now (rad,
    ``grasps.plan_grasps``' ``yaw_now``) and, for the check of the seal on what the camera sees (``seen_seals``),
    the depth image's points in the heap's area, the floor's and the target's own among them (None: no such check)."""

    others: np.ndarray
    walls: np.ndarray
    floor: float
    yaw_now: float
    seen: np.ndarray | None = None


@dataclass(frozen=True)
class SuctionGrasp:
    """One suction grasp: the tool pose (world), its seal and edge margins and the moment arm of the part's centre of
    mass (m; ``CupSpots``), the tool's clearance from the other parts and the walls (m, at most 2 cm), the
    approach's tilt from straight down (deg), the wrist's turn to it (rad), the score (higher is better) and, on the
    hybrid hand, the fingers' opening (m) in the pick (None: the suction tool has none)."""

    T_world_gripper: np.ndarray
    seal_margin: float
    edge_margin: float
    com_distance: float
    clearance: float
    tilt_deg: float
    turn: float
    score: float
    opening: float | None = None


@functools.lru_cache(maxsize=32)
def _mesh(part: PartType):
    import trimesh

    return trimesh.Trimesh(np.asarray(part.vertices), np.asarray(part.faces), process=False)


def centre_of_mass(part: PartType) -> np.ndarray:
    """(3,) the part's centre of mass (m, object frame): its closed mesh's volume centroid, uniform density."""
    return np.asarray(_mesh(part).center_mass, float)


def _face_centres(part: PartType, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The area centroids (m, object frame) and outward normals of the part's flat faces (coplanar triangles
    together) of at least a disc's area of ``radius`` (m)."""
    mesh = _mesh(part)
    groups = list(mesh.facets)
    grouped = np.zeros(len(mesh.faces), bool)
    for g in groups:
        grouped[g] = True
    groups += [np.array([i]) for i in np.flatnonzero(~grouped)]
    area, cen, normals = mesh.area_faces, mesh.triangles_center, _face_normals(part)
    big = [g for g in groups if area[g].sum() >= np.pi * radius ** 2]
    if not big:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return (np.stack([area[g] @ cen[g] / area[g].sum() for g in big]),
            np.stack([normals[g[np.argmax(area[g])]] for g in big]))


def _basis(n: np.ndarray) -> np.ndarray:
    """(3, 3) columns u, v, n: a right-handed frame with z along the unit vector ``n``."""
    u = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u), n], 1)


def _rays(radius: float) -> tuple[np.ndarray, list[slice]]:
    """(R, 2) tangent-plane offsets (m) of the rays and the slices of the rim, of each ``SLIDE_STEPS`` ring and of
    the inner points."""
    ring = lambda r, k: r * np.stack([np.cos(a := 2 * np.pi * np.arange(k) / k), np.sin(a)], 1)  # noqa: E731
    parts = [ring(radius, RIM_POINTS)] + [ring(radius + s, RIM_POINTS) for s in SLIDE_STEPS]
    parts.append(np.concatenate([ring(f * radius, 1 if f == 0.0 else _INNER_POINTS) for f in _INNER]))
    ends = np.cumsum([0] + [len(p) for p in parts])
    return np.concatenate(parts), [slice(a, b) for a, b in zip(ends[:-1], ends[1:])]


def _heights(local: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(R,) the highest surface height (m) above each tangent-plane point ``q`` (R, 2) among the triangles
    ``local`` (T, 3, 3; u, v, height) that face up; -inf where none lies above or below it."""
    A, e1, e2 = local[:, 0], local[:, 1] - local[:, 0], local[:, 2] - local[:, 0]
    den = e1[:, 0] * e2[:, 1] - e2[:, 0] * e1[:, 1]  # > 0: the triangle faces up (counter-clockwise seen from n)
    up = den > 1e-14
    A, e1, e2, den = A[up], e1[up], e2[up], den[up]
    d = q[:, None, :] - A[None, :, :2]
    s = (d[..., 0] * e2[:, 1] - e2[:, 0] * d[..., 1]) / den
    t = (e1[:, 0] * d[..., 1] - d[..., 0] * e1[:, 1]) / den
    inside = (s >= -_EPS) & (t >= -_EPS) & (s + t <= 1.0 + _EPS)
    h = A[:, 2] + s * e1[:, 2] + t * e2[:, 2]
    return np.where(inside, h, -np.inf).max(1, initial=-np.inf)


def seal_margins(part: PartType, points: np.ndarray, normals: np.ndarray,
                 cup: CupGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Per cup centre ``points`` (K, 3; m, object frame, on the surface) with outward unit ``normals``: the seal
    margin (m; NaN where the cup does not seal there) and the edge margin (m), as the module's docstring says.
    Only the surface is judged here, not the cup's body (``cup_spots``)."""
    tri = part.vertices[part.faces]
    centre = tri.mean(1)
    reach = np.linalg.norm(tri - centre[:, None], axis=2).max(1) + cup.radius + SLIDE_STEPS[-1] + 1e-4
    q, (rim, *rings, inner) = _rays(cup.radius)
    seal, edge = np.full(len(points), np.nan), np.zeros(len(points))
    for i, (p, n) in enumerate(zip(points, normals)):
        local = (tri[np.linalg.norm(centre - p, axis=1) <= reach] - p) @ _basis(n)
        if np.abs(_heights(local, q[rim])).max() > cup.seal_tol:  # the rim first: most spots fail there
            continue
        h = _heights(local, q)
        if h[inner].max() > cup.seal_tol or np.isinf(h[inner]).any():
            continue
        seal[i] = cup.seal_tol - np.abs(h[rim]).max()
        wider = [np.abs(h[r]).max() <= cup.seal_tol for r in rings] + [False]
        edge[i] = ((0.0,) + SLIDE_STEPS)[wider.index(False)]
    return seal, edge


def _body_clear(part: PartType, points: np.ndarray, normals: np.ndarray, cup: CupGeometry) -> np.ndarray:
    """(K,) does the cup's body (its cylinder) at each spot clear the part's own surface (every surface point
    more than ``seal_tol`` above the spot's plane lies outside the cylinder)?"""
    own = surface_points(part)
    ok = np.ones(len(points), bool)
    for i, (p, n) in enumerate(zip(points, normals)):
        rel = own - p
        up = rel @ n
        side = np.linalg.norm(rel - up[:, None] * n, axis=1)
        ok[i] = not np.any((up > cup.seal_tol) & (up < cup.body_length) & (side < cup.body_radius))
    return ok


@functools.lru_cache(maxsize=64)
def cup_spots(part: PartType, cup: CupGeometry, n: int = 400, seed: int = 0) -> CupSpots:
    """Where ``cup`` seals on ``part`` (object frame, cached per part type, cup, ``n`` and ``seed``): of ``n``
    points drawn over its surface (area-weighted, seeded: same seed, same spots) and the centres of its flat faces
    (``_face_centres``), those where the rim seals (``seal_margins``) and the cup's body clears the part's own
    other faces."""
    pts, idx = _surface_samples(part, n, seed)
    centres, centre_normals = _face_centres(part, cup.radius)
    pts = np.concatenate([centres, pts])
    normals = np.concatenate([centre_normals, _face_normals(part)[idx]])
    seal, edge = seal_margins(part, pts, normals, cup)
    keep = ~np.isnan(seal)
    keep[keep] = _body_clear(part, pts[keep], normals[keep], cup)
    pts, normals = pts[keep], normals[keep]
    rel = centre_of_mass(part) - pts
    com = np.linalg.norm(rel - np.einsum("ij,ij->i", rel, normals)[:, None] * normals, axis=1)
    return CupSpots(pts, normals, seal[keep], edge[keep], com)


def unsealable(parts: Iterable[PartType], cup: CupGeometry, n: int = 400, seed: int = 0) -> list[str]:
    """The names of the ``parts`` on which ``cup`` seals nowhere, whichever face is up (``cup_spots``: a face
    smaller than the rim, curved more than the seal tolerance across it, studded, or too near other faces for
    the cup's body)."""
    return [p.name for p in parts if not len(cup_spots(p, cup, n, seed).points)]


def _frames(points: np.ndarray, normals: np.ndarray, yaw: float) -> np.ndarray:
    """(K, 4, 4) tool poses at world ``points`` (K, 3) approaching along -``normals``: x the heading ``yaw`` (rad)
    projected onto the cup's plane (the wrist's least turn), y = z x x."""
    z = -normals
    d = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    x = d - (z @ d)[:, None] * z
    flat = np.linalg.norm(x, axis=1) < 1e-6  # z along the heading: any x across it
    x[flat] = np.cross(z[flat], [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    T = np.tile(np.eye(4), (len(points), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x, np.cross(z, x), z, points
    return T


def _turned(T: np.ndarray, deg: float) -> np.ndarray:
    """The tool poses ``T`` (K, 4, 4) turned by ``deg`` about their own z axis."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    out = T.copy()
    out[:, :3, 0], out[:, :3, 1] = c * T[:, :3, 0] + s * T[:, :3, 1], -s * T[:, :3, 0] + c * T[:, :3, 1]
    return out


def _cylinder_distance(local: np.ndarray, cup: CupGeometry) -> np.ndarray:
    """Signed distance (m; negative inside) of gripper-frame points (..., 3) to the cup's body: the cylinder of
    ``body_radius`` about z from the rim (z = 0) up to z = -``body_length``."""
    radial = np.sqrt(local[..., 0] * local[..., 0] + local[..., 1] * local[..., 1]) - cup.body_radius
    axial = np.maximum(-cup.body_length - local[..., 2], local[..., 2])
    return np.hypot(np.maximum(radial, 0.0), np.maximum(axial, 0.0)) + np.minimum(np.maximum(radial, axial), 0.0)


def _nearest(T: np.ndarray, pts: np.ndarray, cup: CupGeometry, body: bool) -> np.ndarray:
    """(K,) the least distance (m) from the tool at each pose ``T`` (K, 4, 4) to the world points ``pts`` (P, 3):
    its cup body (``body``) or its wrist boxes (``CupGeometry.boxes``); ``_CLEAR`` where none comes closer."""
    out = np.full(len(T), _CLEAR)
    if not len(pts):
        return out
    boxes = cup.boxes()
    for a in range(0, len(T), _CHUNK):
        Tc = T[a:a + _CHUNK]
        local = (pts[None] - Tc[:, None, :3, 3]) @ Tc[:, :3, :3]
        if body:
            d = _cylinder_distance(local, cup)
        else:  # only the points near the boxes can come within _CLEAR
            near = near_boxes(local, boxes, _CLEAR)
            d = np.full(near.shape, np.inf)
            d[near] = np.min([_box_distance(local[near], lo, hi) for lo, hi in boxes], axis=0, initial=np.inf)
        out[a:a + _CHUNK] = np.minimum(d.min(1), _CLEAR)
    return out


def seen_seals(T: np.ndarray, seen: np.ndarray, radius: float, tol: float, sectors: int = SEEN_SECTORS
               ) -> np.ndarray:
    """(K,) does the depth image agree that a cup at each pose ``T`` (K, 4, 4; world, origin at the rim's centre on
    the estimated face, z into the part) seals, the seal test of Dex-Net 3.0 made on the observed points ``seen``
    (P, 3; world, m) rather than on the estimated model? With h a point's depth below the rim's plane (along z) and
    rho its distance from the axis::

        every one of ``sectors`` equal sectors of the rim's ring, RING radius <= rho <= radius, holds points, and
        in each 3 in 4 of them lie within ``tol`` of the rim's plane (the face there: not past its edge, no gap)
        no point with rho <= radius has h < -tol                          (nothing rises into the cup)

    An estimate a few millimetres off puts the planned rim across the true face's edge, or over a neighbour, where
    the model says it seals."""
    out = np.zeros(len(T), bool)
    if not len(seen):
        return out
    for a in range(0, len(T), _CHUNK):
        Tc = T[a:a + _CHUNK]
        local = (seen[None] - Tc[:, None, :3, 3]) @ Tc[:, :3, :3]  # (k, P, 3)
        rho = np.hypot(local[..., 0], local[..., 1])
        h = local[..., 2]
        inside = rho <= radius
        ok = ~np.any(inside & (h < -tol), axis=1)
        ring = inside & (rho >= RING * radius)
        sector = np.minimum((np.arctan2(local[..., 1], local[..., 0]) + np.pi) / (2 * np.pi) * sectors,
                            sectors - 1).astype(int)
        for k in np.flatnonzero(ok):
            sk, on = sector[k][ring[k]], np.abs(h[k][ring[k]]) <= tol
            held = np.bincount(sk, minlength=sectors)
            ok[k] = bool(np.all(held > 0) and np.all(np.bincount(sk[on], minlength=sectors) >= 0.75 * held))
        out[a:a + _CHUNK] = ok
    return out


def _lowest_corner(T: np.ndarray, cup: CupGeometry) -> np.ndarray:
    """(K,) the height (m, world) of the wrist boxes' lowest corner with the tool at each pose ``T`` (K, 4, 4)."""
    corners = np.array([[x, y, z] for lo, hi in cup.boxes() for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    return (corners @ T[:, 2, :3].T).min(0, initial=np.inf) + T[:, 2, 3]


def _tool_clearance(T: np.ndarray, around: CupSurroundings, cup: CupGeometry, b: BinPickConfig,
                    body: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per tool pose ``T`` (K, 4, 4): is its cup body (``body``) or are its wrist boxes clear (``suction_clearance``
    from the others' points, ``suction_wall_clearance`` from the walls'), and its least distance (m) to them?"""
    d_other, d_wall = _nearest(T, around.others, cup, body), _nearest(T, around.walls, cup, body)
    return (d_other >= b.suction_clearance) & (d_wall >= b.suction_wall_clearance), np.minimum(d_other, d_wall)


def _within_reach(around: CupSurroundings, points: np.ndarray, normals: np.ndarray, cup: CupGeometry,
                  clearance: float) -> CupSurroundings:
    """``around`` without the points that no tool at the spots ``points`` (world, m; ``normals`` their outward
    normals) comes within ``clearance`` (m) of, however the wrist turns: those lower than the cup body's lowest rim
    point and the wrist box's lowest corner, and those farther sideways from the spots than the tool reaches below
    the highest point (the tool lies within ``rho`` of its axis; tilted by ``s`` = sin(tilt), a length ``up`` of
    it along the axis stays below that point and reaches ``up * s`` sideways)."""
    if not len(points):
        return around
    s, c = np.sqrt(np.clip(1.0 - normals[:, 2] ** 2, 0.0, 1.0)), normals[:, 2]
    boxes = cup.boxes()
    corner = max(np.hypot(x, y) for lo, hi in boxes for x in (lo[0], hi[0]) for y in (lo[1], hi[1]))
    nearest = max(hi[2] for _, hi in boxes)  # the boxes' face nearest the part (z <= 0)
    low = np.minimum(points[:, 2] - cup.body_radius * s, points[:, 2] - nearest * c - corner * s) - clearance
    rho = max(cup.body_radius, corner) + clearance
    pts = np.concatenate([around.others, around.walls])
    top = float(pts[:, 2].max(initial=points[:, 2].max()))
    length = max([cup.body_length] + [-lo[2] for lo, _ in boxes])
    up = np.clip((top - points[:, 2] + rho * s) / np.maximum(c, 1e-3), 0.0, length)
    centre = points[:, :2].mean(0)
    reach = float((np.linalg.norm(points[:, :2] - centre, axis=1) + up * s + rho).max())
    keep = lambda q: q[(q[:, 2] >= low.min()) & (np.linalg.norm(q[:, :2] - centre, axis=1) <= reach)]  # noqa: E731
    return CupSurroundings(keep(around.others), keep(around.walls), around.floor, around.yaw_now, around.seen)


def plan_suction(part: PartType, T_world_obj: np.ndarray, around: CupSurroundings, cup: CupGeometry,
                 b: BinPickConfig, seed: int = 0) -> list[SuctionGrasp]:
    """Feasible suction grasps on ``part`` at its estimated pose ``T_world_obj``, best first (the module's
    docstring): ``cup_spots`` (``b.suction_samples`` drawn with ``seed``) facing up within
    ``b.suction_max_tilt_deg``, the tool clear of the floor, ``around``'s points and the part's own surface, the
    wrist turned least; of grasps within 3 mm and 10 deg of each other only the best. Empty when the part shows no
    face the cup seals on."""
    spots = cup_spots(part, cup, b.suction_samples, seed)
    R = T_world_obj[:3, :3]
    normals, points = spots.normals @ R.T, transform_points(T_world_obj, spots.points)
    tilt = np.degrees(np.arccos(np.clip(normals[:, 2], -1.0, 1.0)))
    low = points[:, 2] - cup.body_radius * np.sqrt(np.clip(1.0 - normals[:, 2] ** 2, 0.0, 1.0))
    idx = np.flatnonzero((tilt <= b.suction_max_tilt_deg) & (low >= around.floor)
                         & (spots.edge_margin >= b.suction_min_edge_margin - 1e-9))
    T0 = _frames(points[idx], normals[idx], around.yaw_now)
    around = _within_reach(around, points[idx], normals[idx], cup, max(b.suction_clearance, b.suction_wall_clearance,
                                                                      _CLEAR))
    ok, clearance = _tool_clearance(T0, around, cup, b, body=True)
    idx, T0, clearance = idx[ok], T0[ok], clearance[ok]
    T, turn, found = T0.copy(), np.zeros(len(idx)), np.zeros(len(idx), bool)
    own = transform_points(T_world_obj, surface_points(part))
    for deg in _TURNS_DEG:
        todo = np.flatnonzero(~found)
        Tt = _turned(T0[todo], deg)
        ok, c = _tool_clearance(Tt, around, cup, b, body=False)
        ok &= (_nearest(Tt, own, cup, body=False) >= 0.0) & (_lowest_corner(Tt, cup) >= around.floor)
        hit = todo[ok]
        T[hit], found[hit], clearance[hit] = Tt[ok], True, np.minimum(clearance[hit], c[ok])
        turn[hit] = np.abs(_wrap(np.arctan2(Tt[ok, 1, 0], Tt[ok, 0, 0]) - around.yaw_now))
    idx, T, turn, clearance = idx[found], T[found], turn[found], clearance[found]
    if around.seen is not None and b.suction_seen_tol > 0:  # the seal as the camera sees it
        near = around.seen[np.linalg.norm(around.seen - T_world_obj[:3, 3], axis=1) <= part.diameter + cup.radius]
        ok = seen_seals(T, near, cup.radius, b.suction_seen_tol)
        idx, T, turn, clearance = idx[ok], T[ok], turn[ok], clearance[ok]
    top = float(transform_points(T_world_obj, part.vertices)[:, 2].max())
    score = (b.suction_margin_weight * (spots.seal_margin[idx] + spots.edge_margin[idx])
             - b.suction_com_weight * spots.com_distance[idx] - b.suction_tilt_weight * tilt[idx]
             - b.turn_weight * turn + b.height_weight * (top - around.floor))
    grasps: list[SuctionGrasp] = []
    for k in np.argsort(-score, kind="stable"):
        if any(np.linalg.norm(g.T_world_gripper[:3, 3] - T[k, :3, 3]) < _SAME[0]
               and g.T_world_gripper[:3, 2] @ T[k, :3, 2] > _SAME[1] for g in grasps):
            continue
        s = idx[k]
        grasps.append(SuctionGrasp(T[k], float(spots.seal_margin[s]), float(spots.edge_margin[s]),
                                   float(spots.com_distance[s]), float(clearance[k]), float(tilt[s]),
                                   float(turn[k]), float(score[k])))
    return grasps
