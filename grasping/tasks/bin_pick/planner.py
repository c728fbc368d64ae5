"""Bin picking's grasp planner: the next part to pick and its grasp, from the estimates and the depth image.

The planner sees the parts only through the provider's estimates and the hand camera's depth image, mapped to
the world with the calibrated mount (``Episode.T_world_cam``); the tote's and the out-box's geometry is the
workcell's, known. A grasp (``grasping.grasps.plan_grasps``, top-down) must keep the open fingers' meshes
(``controller.open_finger_points``, open ``finger_margin`` wider than the part) and the camera's box
(``hand.camera_box``) ``wall_clearance`` from the tote's inner wall faces and rims, the open hand's boxes
(``grasping.hand.Hand.boxes``) ``part_clearance`` (negative: the fingers may push into the heap that far) from
the other estimates' surfaces and the depth image's points above the floor (less those on the target's estimated
surface: they are the target); the open fingers must not land on the target's own estimated surface either (an
L-block's other leg: the descending finger shoves the part away). A grasp whose open fingers would reach a wall
is moved along the gripper's y axis (``wall_shifts``), the part off-centre in the hand, while the part's contact
faces still meet the pads (a part lying against a wall); one that no shift clears is tilted 10 or 20 deg about
its pinch point (``wall_tilts_deg``), the hand's top leaning away from the wall. Its pinch stays
``grasp.min_pinch_height`` above the floor; the approach starts above the walls and comes straight down. Among
the parts, highest first, the best grasps of ``plan_parts`` parts compete (score plus ``height_weight`` per metre of
the part's top); the first that passes the IK check is taken. ``part_clearance`` holds several distances,
strictest first: a looser one is tried only when no part has a reachable grasp at the stricter (a finger that lands
on a neighbour stalls there, and the fingers opposite push the part away: clean grasps first, a shove into the heap
only when nothing else is left). A pinch with too little of its pads on the part's flat faces (``min_support``: a part
leaning in the heap, pinched on its edges by a tilted hand; half of them slip) comes after all of them.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from dataclasses import dataclass
from typing import Callable, Iterable

import mujoco
import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from posegrasp.catalog import PartType, catalog_by_id
from posegrasp.errors import ConfigError
from posegrasp.geometry import axis_angle_R, invert, transform_points
from posegrasp.grasping.config import TrialConfig, holds_firmly
from posegrasp.grasping.controller import (_opening_table, finger_angle_for_opening, finger_geoms, open_finger_points,
                                           robot_workcell)
from posegrasp.grasping.grasps import Grasp, _box_distance, near_boxes, plan_grasps, surface_points
from posegrasp.grasping.hand import CONTACT_BAND, ON_PLANE_TOL, Hand, camera_box, hand_of
from posegrasp.grasping.perception import Estimate
from posegrasp.grasping.record import Failure
from posegrasp.grasping.suction_grasps import CupGeometry, CupSurroundings, SuctionGrasp, plan_suction
from posegrasp.grasping.support import rest_on_table
from posegrasp.grasping.targets import reach_q
from posegrasp.grasping.tasks.base import EpisodeFailed
from posegrasp.grasping.tasks.bin_pick.config import BinPickConfig
from posegrasp.grasping.tasks.bin_pick.scene import Area, area_of, wall_points
from posegrasp.sim.camera import Frame
from posegrasp.sim.hybrid import CARRIAGE_BODY, EXTEND_JOINT, T_gripper_cup, hybrid_boxes, hybrid_cylinders, rim_offset
from posegrasp.sim.suction import CUP_BODY, PALM_BOX, PALM_Z
from posegrasp.sim.tote import WALLS, Tote
from posegrasp.sim.workcell import Workcell


#: The cup comes down along its axis from this far (m) above the grasp ...
CUP_APPROACH = 0.02
#: ... and presses on by this share of its bellows' stroke ...
CUP_PRESS = 0.3
#: ... at this speed (m/s), once the arm has moved slower than ``CUP_SETTLE_SPEED`` (m/s) for 3 control periods,
#: waiting at most ``CUP_SETTLE_TIME`` (s) for it.
CUP_PRESS_SPEED, CUP_SETTLE_SPEED, CUP_SETTLE_TIME = 0.05, 0.005, 1.0
#: Once held (the cup sealed, the fingers closed) a part lying within this distance (m) of a tote's wall is drawn off
#: it to this distance, raised ``WALL_BACKOFF_RISE`` (m) off the floor, at ``WALL_BACKOFF_SPEED`` (m/s), before the
#: lift: rubbing on the wall as it rises, it would pull the cup off, or turn out of the fingers (a prism pinched on
#: its slopes, its end cap on a wall).
WALL_BACKOFF, WALL_BACKOFF_RISE, WALL_BACKOFF_SPEED = 0.010, 0.003, 0.05
#: The hybrid hand picks with its cup where the cup's part stands at most this far (m) below the fingers' part.
HYBRID_TIE = 0.005

def depth_points(frame: Frame, T_world_cam: np.ndarray, stride: int) -> np.ndarray:
    """(N, 3) world points (m) of every ``stride``-th valid depth pixel along each axis (the camera's pose as the
    robot believes it)."""
    d = frame.depth[::stride, ::stride]
    v, u = np.nonzero(d > 0)
    z = d[v, u].astype(float)
    K = frame.K
    x = (u * stride - K[0, 2]) * z / K[0, 0]
    y = (v * stride - K[1, 2]) * z / K[1, 1]
    return transform_points(T_world_cam, np.stack([x, y, z], 1))


def seen_points(frame: Frame, T_world_cam: np.ndarray, area: Area, b: BinPickConfig) -> np.ndarray:
    """(N, 3) world points (m) of every ``depth_stride // 2``-th depth pixel in the area, the floor's too: what the
    check of a suction grasp's seal on the depth image looks at (``suction_grasps.seen_seals``)."""
    pts = depth_points(frame, T_world_cam, max(1, b.depth_stride // 2))
    return pts[area.holds(pts, 0.002) & (pts[:, 2] < area.top + 0.2)]


def heap_points(pts: np.ndarray, area: Area, b: BinPickConfig) -> np.ndarray:
    """The depth points ``pts`` on the heap: in the area (clear of the walls by ``wall_band``), above the floor by
    ``floor_band``, below the hand camera's look."""
    keep = area.holds(pts, b.wall_band if area.walls else 0.0) & (pts[:, 2] > area.floor + b.floor_band)
    return pts[keep & (pts[:, 2] < area.top + 0.2)]


def level(block: PartType, T_world_obj: np.ndarray, cfg: TrialConfig, floor: float) -> np.ndarray:
    """An estimate levelled onto the floor when it lies near a resting pose on it (``support.rest_on_table``);
    one on other parts keeps its estimated pose."""
    T = rest_on_table(block, T_world_obj, cfg.rest, surface_z=floor)
    bottom = float(transform_points(T, block.vertices)[:, 2].min())
    return T if abs(bottom - floor) < 1e-6 else np.array(T_world_obj, float)


def _clear_of(grasp: Grasp, pts: np.ndarray, boxes: list, clearance: float) -> bool:
    """Are the axis-aligned ``boxes`` (gripper frame, ``hand.hand_boxes``' layout) at ``grasp`` at least
    ``clearance`` (m) from every point ``pts`` (world)?"""
    if not len(pts):
        return True
    T = grasp.T_world_gripper
    local = (pts - T[:3, 3]) @ T[:3, :3]
    local = local[near_boxes(local, [(np.asarray(lo), np.asarray(hi)) for lo, hi in boxes], clearance)]
    return all(_box_distance(local, np.asarray(lo), np.asarray(hi)).min(initial=np.inf) >= clearance
               for lo, hi in boxes)


def pregrasp_height(cfg: TrialConfig, area: Area, T_grasp: np.ndarray) -> float:
    """How far (m) above the grasp the approach starts: ``grasp.pregrasp_height``, or higher, so the fingertips
    start ``wall_margin`` above the walls."""
    start = area.top + cfg.grasp.fingertip_depth + cfg.bin_pick.wall_margin
    return max(cfg.grasp.pregrasp_height, start - T_grasp[2, 3])


def poorly_supported(grasp: object, b: BinPickConfig) -> bool:
    """Is ``grasp`` a pinch with under ``min_support`` of its pads on the part's flat faces (a last resort)?"""
    return isinstance(grasp, Grasp) and grasp.support < b.min_support


def _tried(grasp: Grasp, failed: list[np.ndarray], b: BinPickConfig) -> bool:
    """Is ``grasp`` one of the ``failed`` grasp poses (world gripper), within ``retry_distance`` and
    ``retry_angle_deg`` of its squeeze axis?"""
    return _tried_axis(grasp.T_world_gripper, failed, b, 0)


def _tried_axis(T: np.ndarray, failed: list[np.ndarray], b: BinPickConfig, axis: int) -> bool:
    """Is the grasp pose ``T`` (world gripper) one of the ``failed`` ones: within ``retry_distance``, its ``axis``
    (0: the squeeze axis x, 2: the approach z) within ``retry_angle_deg``?"""
    return any(np.linalg.norm(T[:3, 3] - F[:3, 3]) < b.retry_distance
               and T[:3, axis] @ F[:3, axis] > np.cos(np.radians(b.retry_angle_deg)) for F in failed)


class HeapView:
    """The heap as the planner sees it at one look: the estimates levelled (``poses``, world), their tops' heights,
    their surface points, the tote's wall points, the camera's box, per part what a grasp on it must clear
    (``around``) and, given the look's ``frame``, the depth points a suction grasp's seal is checked on (``seen``:
    ``seen_points``; None without it)."""

    def __init__(self, wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray,
                 heap: np.ndarray, frame: Frame | None = None):
        b, g_cfg = cfg.bin_pick, cfg.grasp
        self.ests, self.b, self.heap = ests, b, heap
        self.area = area_of(wc, b)
        self.seen = seen_points(frame, T_world_cam, self.area, b) if frame is not None else None
        self.cat = cat = catalog_by_id(wc.cfg.objects)
        self.poses = [level(cat[e.obj_id], T_world_cam @ e.T_cam_obj, cfg, self.area.floor) for e in ests]
        self.tops = [float(transform_points(T, cat[e.obj_id].vertices)[:, 2].max()) for e, T in zip(ests, self.poses)]
        self.clouds = [transform_points(T, surface_points(cat[e.obj_id], g_cfg.neighbour_points))
                       for e, T in zip(ests, self.poses)]
        self.walls = wall_points(self.area.tote) if self.area.walls else np.zeros((0, 3))
        self.reach = g_cfg.max_width / 2 + b.finger_margin + 0.1  # the open hand and camera lie within this of a part
        self.around = functools.cache(self._around)

    def part(self, j: int) -> PartType:
        """Estimate ``j``'s part type."""
        return self.cat[self.ests[j].obj_id]

    def highest_first(self) -> list[int]:
        """The estimates' indices, highest top first."""
        return sorted(range(len(self.ests)), key=lambda i: -self.tops[i])

    def _around(self, j: int) -> tuple[cKDTree, np.ndarray, np.ndarray]:
        """Part ``j``'s surface points (a tree), the obstacle points and the wall points near it (world)."""
        T, r, b = self.poses[j], self.reach + 0.5 * self.part(j).diameter, self.b
        near = lambda p: p[np.linalg.norm(p[:, :2] - T[:2, 3], axis=1) < r]  # noqa: E731
        own = cKDTree(transform_points(T, surface_points(self.part(j))))
        depth = near(self.heap)
        depth = depth[own.query(depth, distance_upper_bound=b.own_margin)[0] > b.own_margin] if len(depth) else depth
        return own, np.concatenate([near(c) for i, c in enumerate(self.clouds) if i != j] + [depth]), near(self.walls)


def choose_part(wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray, heap: np.ndarray,
                yaw_now: float, failed: list[np.ndarray] = (), view: HeapView | None = None
                ) -> tuple[int, Grasp, np.ndarray]:
    """The estimate to pick (index), its grasp and its levelled ``T_world_obj`` among the estimates in the tote,
    none of the grasps that ``failed`` before (``_tried``), at the first of ``part_clearance`` that gives a
    reachable grasp, the poorly supported pinches (``min_support``) after every clearance; ``EpisodeFailed``:
    "nothing graspable" when no part has a clear grasp at any, "unreachable" when the IK reaches none. ``heap``: the depth image's points on the heap (``heap_points``); ``view``: the
    ``HeapView`` of these, when the caller has it."""
    b, g_cfg = cfg.bin_pick, cfg.grasp
    view = view or HeapView(wc, cfg, ests, T_world_cam, heap)
    area, poses, tops = view.area, view.poses, view.tops
    cam, hand = camera_box(wc.cfg.hand_camera.mount_pos), hand_of(wc.cfg)

    def passes():  # one per clearance, strictest first; then the poorly supported pinches, as a last resort
        for poor in (False, True):
            for clearance in b.part_clearance:
                plan_cfg = dataclasses.replace(g_cfg, min_pinch_height=area.floor + g_cfg.min_pinch_height,
                                               finger_margin=b.finger_margin, clearance_min=clearance,
                                               score=dataclasses.replace(g_cfg.score, turn=b.turn_weight))
                yield functools.partial(ranked, clearance, plan_cfg, poor)

    def ranked(clearance: float, plan_cfg, poor: bool, j: int) -> list[tuple[float, Grasp]]:
        own, others, wall = view.around(j)
        clear_of_walls = lambda g, c=b.wall_clearance: _clear_of(g, wall, [cam], c) and (  # noqa: E731
            not area.walls or _fingers_inside(g, wc.cfg, b.finger_margin, area.tote, c))
        fit = _Fit(own.data, others, clearance, lambda g: clear_of_walls(g, b.shift_clearance), b, hand)
        grasps = list(itertools.islice((  # the first grasps_per_block, the later ones never moved or checked
            g for g0 in plan_grasps(view.part(j), poses[j], others, plan_cfg, yaw_now, yaw_stable=holds_firmly(cfg),
                                    hand=hand)
            for g in ([g0] if clear_of_walls(g0) else
                      fit.shifted(g0) or fit.tilted(g0, wc.cfg, area.floor, g_cfg.score.tilt))
            if poorly_supported(g, b) == poor and not _tried(g, failed, b)
            and _clear_of(g, others, [cam], clearance)
            and _clear_of(g, own.data, hand.boxes((g.width + b.finger_margin) / 2)[:-1], 0.0)), g_cfg.grasps_per_block))
        return [(g.score + g_cfg.detection_weight * ests[j].score + b.height_weight * (tops[j] - area.floor), g)
                for g in grasps]

    return _first_reachable(wc, cfg, view, passes())


def _first_reachable(wc: Workcell, cfg: TrialConfig, view: HeapView,
                     passes: Iterable[Callable[[int], list[tuple[float, object]]]]) -> tuple:
    """Per pass (a function giving an estimate's grasps with their ranks), strictest first: the ranked grasps of the
    first ``plan_parts`` parts that have some, highest first, and the best of them the arm reaches (``_reachable``);
    ``EpisodeFailed``: "unreachable" when some pass had grasps, none reachable, else "nothing graspable"."""
    seen_any = False
    for grasps_of in passes:
        options, parts = [], 0
        for j in view.highest_first():
            grasps = grasps_of(j)
            options += [(rank, j, g) for rank, g in grasps]
            parts += bool(grasps)
            if parts >= cfg.bin_pick.plan_parts:
                break
        seen_any |= bool(options)
        found = _reachable(wc, cfg, view, options)
        if found is not None:
            return found
    raise EpisodeFailed(Failure.UNREACHABLE if seen_any else Failure.NOTHING_GRASPABLE)


def off_the_walls(block: PartType, T_world_obj: np.ndarray, tote: Tote, distance: float) -> np.ndarray:
    """(3,) the horizontal move (m, world) that brings the part ``block`` at ``T_world_obj`` at least ``distance`` (m)
    off each of the ``tote``'s inner walls that it lies nearer to (zero where it lies farther from all)."""
    v = transform_points(T_world_obj, block.vertices)
    lo, hi = tote.inner_bounds()
    move = np.zeros(3)
    move[:2] = (np.maximum(0.0, lo[:2] + distance - v[:, :2].min(0))
                - np.maximum(0.0, v[:, :2].max(0) - hi[:2] + distance))
    return move


def approach_end(grasp: Grasp | SuctionGrasp) -> np.ndarray:
    """The gripper's pose (world) where a pick's straight descent from its pre-grasp ends: the grasp, or for the cup
    ``CUP_APPROACH`` back along its axis (the cup comes on from there)."""
    T = grasp.T_world_gripper.copy()
    if isinstance(grasp, SuctionGrasp):
        T[:3, 3] -= CUP_APPROACH * T[:3, 2]
    return T


def _reachable(wc: Workcell, cfg: TrialConfig, view: HeapView, options: list) -> tuple | None:
    """The best of ``options`` ((rank, estimate index, grasp), any order) whose pre-grasp and the end of its
    descent (``approach_end``: the poses the arm goes to) the arm reaches clear of the tote's walls, as (index,
    grasp, levelled pose); None if none of the ``ik_checks`` best."""
    g_cfg, area = cfg.grasp, view.area
    options.sort(key=lambda o: -o[0])
    for _, j, g in options[:g_cfg.ik_checks]:
        T = approach_end(g)
        qs = reach_q(wc, g_cfg, T, pregrasp_height(cfg, area, T))
        if qs is not None and (not area.walls or arm_clear(wc.cfg, area.tote, *qs, cfg.bin_pick.wall_clearance)):
            return j, g, view.poses[j]
    return None


def choose_cup(wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray, heap: np.ndarray,
               yaw_now: float, failed: list[np.ndarray] = (), view: HeapView | None = None
               ) -> tuple[int, SuctionGrasp, np.ndarray]:
    """With the suction tool: the estimate to pick (index), the cup's grasp on it (``suction_grasps.plan_suction``:
    a face the rim seals on, facing up within ``suction_max_tilt_deg``, the tool clear of walls and neighbours)
    and its levelled ``T_world_obj``; the best grasps of ``plan_parts`` parts, highest first, compete and the first
    the arm reaches is taken; none within ``retry_distance`` of a grasp that ``failed`` before (with its approach
    within ``retry_angle_deg``). The grasp's pose is the gripper's (the hybrid hand's cup lies ``rim_offset`` below
    it); given a ``view`` with the look's frame, only grasps whose seal its depth image confirms
    (``suction_seen_tol``). ``EpisodeFailed`` as ``choose_part``."""
    b, g_cfg = cfg.bin_pick, cfg.grasp
    view = view or HeapView(wc, cfg, ests, T_world_cam, heap)
    T_cup_gripper = invert(T_gripper_cup(wc.cfg)) if wc.cfg.hand == "hybrid" else np.eye(4)

    def ranked(cup: CupGeometry, opening: float | None, j: int) -> list[tuple[float, SuctionGrasp]]:
        _, others, wall = view.around(j)
        grasps = [dataclasses.replace(g, T_world_gripper=g.T_world_gripper @ T_cup_gripper, opening=opening)
                  for g in plan_suction(view.part(j), view.poses[j],
                                        CupSurroundings(others, wall, view.area.floor, yaw_now, view.seen), cup, b)]
        grasps = [g for g in grasps if not _tried_axis(g.T_world_gripper, failed, b, 2)][:g_cfg.grasps_per_block]
        return [(g.score + g_cfg.detection_weight * ests[j].score, g) for g in grasps]

    return _first_reachable(wc, cfg, view, (functools.partial(ranked, cup_of(wc.cfg, o), o)
                                            for o in cup_openings(wc.cfg, g_cfg.max_width + b.finger_margin)))


def cup_openings(wc_cfg, wide: float) -> tuple[float | None, ...]:
    """The fingers' openings (m) a suction pick is planned with, in order: none on the suction tool; on the hybrid
    hand ``wide`` (open: high above the cup's rim) then closed round the cup (``cup_opening``: nearer the axis, but
    lower), for a part the open fingers would reach a wall from."""
    return (None,) if wc_cfg.hand == "suction" else (wide, cup_opening(wc_cfg))


def cup_of(wc_cfg, opening: float | None = None) -> CupGeometry:
    """The cup of the workcell settings ``wc_cfg`` as the planner models it (cup frame): the suction tool's
    (``sim.suction``; the wrist may come the bellows' whole stroke nearer) or the hybrid hand's extended cup
    (``sim.hybrid``: the fingers ``opening`` (m) apart, ``finger_boxes``; the wrist coming as near as the pick
    presses, ``CUP_PRESS``)."""
    s = wc_cfg.suction
    if wc_cfg.hand == "suction":
        return CupGeometry(radius=s.diameter / 2, seal_tol=s.seal_tolerance, body_radius=s.diameter / 2,
                           body_length=-PALM_Z, stroke=s.stroke,
                           wrist=(PALM_BOX, camera_box(wc_cfg.hand_camera.mount_pos)))
    stem, _ = hybrid_cylinders(wc_cfg)
    dz = np.array([0.0, 0.0, rim_offset(wc_cfg)])
    moved = [(tuple(np.subtract(lo, dz)), tuple(np.subtract(hi, dz)))
             for lo, hi in (camera_box(wc_cfg.hand_camera.mount_pos), *finger_boxes(wc_cfg, opening))]
    return CupGeometry(radius=s.diameter / 2, seal_tol=s.seal_tolerance, body_radius=s.diameter / 2,
                       body_length=-stem.z0, stroke=CUP_PRESS * s.stroke,
                       wrist=tuple(hybrid_boxes(wc_cfg)[2:] + moved))


@functools.lru_cache(maxsize=4)
def cup_opening(wc_cfg) -> float:
    """The hybrid hand's fingers' opening (m, between their tips; ``controller.finger_angle_for_opening``) in a
    suction pick: the least, in millimetre steps, at which their collision meshes keep ``hybrid.cup_room`` (m) from
    the extended cup and its stem (closed further, the fingertips curl in onto the stem)."""
    robot = robot_workcell(wc_cfg)
    m, d = robot.model, mujoco.MjData(robot.model)
    d.qpos[m.joint(f"jaco_arm/jaco_hand/{EXTEND_JOINT}").qposadr[0]] = wc_cfg.hybrid.extension
    fingers = np.flatnonzero((finger_geoms(m) > 0) & (m.geom_contype > 0))
    cup = np.flatnonzero([m.body(b).name.endswith((CARRIAGE_BODY, CUP_BODY)) for b in m.geom_bodyid])
    widest = round(1000 * float(_opening_table(wc_cfg)[1].max()))  # the fingers wide open
    for mm in range(round(1000 * wc_cfg.suction.diameter), widest + 1):
        d.qpos[robot.finger_qadr] = finger_angle_for_opening(wc_cfg, mm / 1000.0)
        mujoco.mj_kinematics(m, d)
        if min(mujoco.mj_geomDistance(m, d, int(c), int(f), 0.1, None) for c in cup for f in fingers) \
                >= wc_cfg.hybrid.cup_room:
            return mm / 1000.0
    raise ConfigError(f"hybrid.cup_room = {wc_cfg.hybrid.cup_room!r} m: even wide open the fingers come nearer the "
                      "cup than that; use less")


@functools.lru_cache(maxsize=8)
def finger_boxes(wc_cfg, opening: float, band: float = 0.01) -> tuple[tuple[tuple, tuple], ...]:
    """The fingers held ``opening`` (m) apart at their tips as boxes (min corner, max corner; m, gripper frame):
    per finger (either side of the squeeze plane x = 0), the convex hull of its collision meshes' vertices
    (``controller.open_finger_points``) cut into slices ``band`` (m) high from the tips up, each slice's bounds, the
    top one up out of reach. The hull holds the finger, so the boxes do."""
    pts, out = open_finger_points(wc_cfg, round(1000 * opening)), []
    for side in (pts[pts[:, 0] > 0], pts[pts[:, 0] < 0]):
        hull = ConvexHull(side)
        v = side[hull.vertices]
        a, b = (side[[e for e in {tuple(sorted(p)) for t in hull.simplices for p in
                                   ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]))}]].transpose(1, 0, 2))
        lowest, z = float(v[:, 2].min()), float(v[:, 2].max())
        while z > lowest:
            cuts = [a + ((c - a[:, 2]) / (b[:, 2] - a[:, 2] + 1e-300))[:, None] * (b - a)
                    for c in (z - band, z)]
            cuts = [p[(p[:, 2] >= z - band - 1e-9) & (p[:, 2] <= z + 1e-9) & (np.minimum(a[:, 2], b[:, 2]) <= p[:, 2])
                      & (np.maximum(a[:, 2], b[:, 2]) >= p[:, 2])] for p in cuts]
            inside = np.concatenate([v[(v[:, 2] >= z - band) & (v[:, 2] <= z)], *cuts])
            top = z - band <= lowest
            out.append(((*inside[:, :2].min(0), -1.0 if top else z - band), (*inside[:, :2].max(0), z)))
            z -= band
    return tuple(out)


def _pad_overlap(T: np.ndarray, width: float, own: np.ndarray, hand: Hand) -> tuple[float, float]:
    """With the ``hand`` at ``T`` (world gripper) open on a part ``width`` (m) across, how far (m) along the gripper
    y axis the part's contact faces (its surface points ``own``, world, within the pads' height ``CONTACT_BAND``)
    meet finger 1's pad and the best of the facing fingers' (0 where a face is missing)."""
    local = (own - T[:3, 3]) @ T[:3, :3]
    band = (local[:, 2] > CONTACT_BAND[0]) & (local[:, 2] < CONTACT_BAND[1])
    faces = [local[band & (s * local[:, 0] > width / 2 - ON_PLANE_TOL), 1] for s in (1.0, -1.0)]
    return tuple(max((min(f.max(), y1) - max(f.min(), y0) for y0, y1 in spans), default=0.0) if len(f) else 0.0
                 for f, spans in zip(faces, (hand.finger1_y, hand.facing_y)))


@dataclass(frozen=True)
class _Fit:
    """Where a grasp moved off a wall (shifted or tilted) must still hold: the part's surface points ``own`` and
    the obstacle points ``others`` (world, m), the clearance (m) from them, ``clear`` (the walls' check) and the
    ``hand``, open ``b.finger_margin`` wider than the part."""

    own: np.ndarray
    others: np.ndarray
    clearance: float
    clear: Callable[[Grasp], bool]
    b: BinPickConfig
    hand: Hand

    def fits(self, g: Grasp, need: float | np.ndarray) -> bool:
        """Does the moved grasp ``g`` still hold: the part's contact faces meet the pads by ``need`` (m; finger 1,
        the facing fingers: ``_pad_overlap``), it is ``clear`` of the walls, keeps ``clearance`` from ``others``?"""
        return bool(np.all(np.asarray(_pad_overlap(g.T_world_gripper, g.width, self.own, self.hand)) >= need)) \
            and self.clear(g) and _clear_of(g, self.others, self.hand.boxes((g.width + self.b.finger_margin) / 2),
                                            self.clearance)

    def shifted(self, grasp: Grasp) -> list[Grasp]:
        """``grasp`` with the hand moved along its y axis by each of ``wall_shifts`` (nearest first) where it still
        ``fits`` (the pads meeting the faces by ``shift_contact``): the part sits off-centre in the hand, away from
        the wall that the fingers' sides would touch."""
        out = []
        for d in sorted(self.b.wall_shifts, key=abs):
            T = grasp.T_world_gripper.copy()
            T[:3, 3] += d * T[:3, 1]
            g = dataclasses.replace(grasp, T_world_gripper=T)
            if self.fits(g, self.b.shift_contact):
                out.append(g)
        return out

    def tilted(self, grasp: Grasp, wc_cfg, floor: float, per_deg: float) -> list[Grasp]:
        """``grasp`` with the hand turned about its pinch point by the least of ``wall_tilts_deg`` that gives any,
        about its squeeze axis x or its y axis, either way (the hand's top leaning away from a wall, its fingertips
        reaching under the part's side toward it), and raised until the open fingers keep ``tilt_floor_clearance``
        above the ``floor`` (m), where it still ``fits`` (the pads meeting the faces as far as the untilted grasp's,
        up to ``shift_contact``); their score loses ``per_deg`` per degree. A tilt about y tilts the squeeze from
        the horizontal by as much: the contacts' friction bears it (``wall_tilts_deg`` up to 40 deg)."""
        b = self.b
        tips = open_finger_points(wc_cfg, round(1000 * (grasp.width + b.finger_margin)))
        T0, out = grasp.T_world_gripper, []
        need = np.minimum(_pad_overlap(T0, grasp.width, self.own, self.hand), b.shift_contact) - ON_PLANE_TOL
        for deg in sorted(b.wall_tilts_deg):
            for axis in (T0[:3, 0], -T0[:3, 0], T0[:3, 1], -T0[:3, 1]):
                T = T0.copy()
                T[:3, :3] = axis_angle_R(axis, np.radians(deg)) @ T0[:3, :3]
                T[2, 3] += max(0.0, floor + b.tilt_floor_clearance - float(transform_points(T, tips)[:, 2].min()))
                g = dataclasses.replace(grasp, T_world_gripper=T, score=grasp.score - per_deg * deg)
                if self.fits(g, need):
                    out.append(g)
            if out:
                return out
        return out


def open_fingers(grasp: Grasp, wc_cfg, margin: float) -> np.ndarray:
    """(N, 3) the fingers' mesh points (world, m) open ``margin`` (m) wider than ``grasp``, at its pose
    (``controller.open_finger_points``)."""
    return transform_points(grasp.T_world_gripper, open_finger_points(wc_cfg, round(1000 * (grasp.width + margin))))


def _fingers_inside(grasp: Grasp, wc_cfg, margin: float, tote: Tote, clearance: float) -> bool:
    """Do the fingers, open ``margin`` (m) wider than the ``grasp`` (``controller.open_finger_points``, their
    meshes), stay ``clearance`` (m) inside the tote's inner walls wherever they are lower than the walls' top plus
    ``clearance``?"""
    pts = open_fingers(grasp, wc_cfg, margin)
    lo, hi = tote.inner_bounds()
    low = pts[pts[:, 2] < hi[2] + clearance, :2]
    return bool(np.all((low >= lo[:2] + clearance) & (low <= hi[:2] - clearance)))


@functools.lru_cache(maxsize=4)
def _tote_robot(wc_cfg, tote: Tote) -> tuple[Workcell, np.ndarray, np.ndarray, np.ndarray]:
    """A robot-and-tote workcell (no parts), the tote walls' geoms, the robot's geoms and those but the tool (the
    fingers or the suction cup: the planner checked them against the walls)."""
    wc = Workcell(wc_cfg, extras=tote.add_to)
    m = wc.model
    walls = np.array([m.geom(f"tote/{w}").id for w in WALLS])
    robot = np.flatnonzero([m.body(b).name.startswith("jaco_arm/") for b in m.geom_bodyid] & (m.geom_contype > 0))
    return wc, walls, robot, np.array([g for g in robot if not any(t in m.geom(g).name for t in ("finger", "suction"))])


def arm_clear(wc_cfg, tote: Tote, q_pre: np.ndarray, q: np.ndarray, clearance: float) -> bool:
    """Is the robot ``clearance`` (m) from the tote's walls at the pre-grasp joint angles ``q_pre`` (fingers open
    wide) and, but its fingers (``hand.hand_boxes`` checked them), at the grasp ``q``?"""
    wc, walls, robot, rigid = _tote_robot(wc_cfg, tote)
    for qq, geoms in ((q_pre, robot), (q, rigid)):
        wc.reset(qq)
        if min(mujoco.mj_geomDistance(wc.model, wc.data, int(a), int(w), 0.1, None) for a in geoms for w in walls) \
                < clearance:
            return False
    return True
