"""A bin-picking episode (``grasping.tasks.bin_pick``): attempt after attempt, look down at the tote, perceive,
choose the next part, pick it, lift it clear of the walls and drop it into the out-box.

The planner sees the parts only through the provider's estimates and the hand camera's depth image, mapped to
the world with the calibrated mount (``Episode.T_world_cam``); the tote's and the out-box's geometry is the
workcell's, known. A grasp (``grasping.grasps.plan_grasps``, top-down) must keep the open fingers' meshes
(``controller.open_finger_points``, open ``finger_margin`` wider than the part) and the camera's box
(``hand.camera_box``) ``grasp.clearance_min`` from the tote's inner wall faces and rims, the open hand's boxes
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
only when nothing else is left).

The robot judges only from what it perceives: it stops when it sees no part in the tote and the depth image shows
nothing above the floor. The verdicts of an attempt use the simulator's truth: a robot touching the tote's walls
(a protective stop: "hit the wall"; so is a hand that contacts turn ``tilt_stop_deg`` from the grasp's approach,
"collision"), another part rising with the target ("two parts lifted"), a part leaving the
tote elsewhere than into the out-box ("part thrown out"), the target not landing in the out-box ("misplaced").
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from posegrasp.catalog import PartType, catalog_by_id
from posegrasp.errors import SimulationError
from posegrasp.geometry import axis_angle_R, transform_points
from posegrasp.grasping.config import ScoringConfig, TrialConfig, holds_firmly
from posegrasp.grasping.controller import open_finger_points
from posegrasp.grasping.grasps import Grasp, _box_distance, plan_grasps, surface_points
from posegrasp.grasping.hand import CONTACT_BAND, ON_PLANE_TOL, Hand, camera_box, hand_of
from posegrasp.grasping.perception import Estimate, PerceptionError
from posegrasp.grasping.record import Attempt, BinPickRecord, FalseTarget, Failure, Target
from posegrasp.grasping.support import rest_on_table
from posegrasp.grasping.targets import (Plan, blame, drive_to_look, gripper_yaw, look_down_q, match_block,
                                        pose_errors, reach_q)
from posegrasp.grasping.tasks.base import EpisodeFailed
from posegrasp.grasping.tasks.bin_pick import BinPickConfig, outbox_of
from posegrasp.sim.camera import Frame
from posegrasp.sim.clutter import park, tote_of
from posegrasp.sim.tote import WALLS, Tote
from posegrasp.sim.workcell import Workcell, wrap_angle

if TYPE_CHECKING:
    from posegrasp.grasping.episode import Episode


@dataclass(frozen=True)
class Area:
    """Where the heap lies: the tote (``walls``) or, for a pile, its footprint grown by the pile margin; ``floor``
    and ``top`` are the heights (m) of its floor and of its walls' top (the floor for a pile)."""

    tote: Tote
    walls: bool
    margin: float

    @property
    def floor(self) -> float:
        return self.tote.floor_z if self.walls else 0.0

    @property
    def top(self) -> float:
        return self.tote.top_z if self.walls else 0.0

    def holds(self, xy: np.ndarray, inset: float = 0.0) -> np.ndarray:
        """Per world point (N, 2 or more): does its xy lie in the area, ``inset`` (m) in from its edges?"""
        lo, hi = self.tote.inner_bounds()
        grow = self.margin - inset
        p = np.asarray(xy, float).reshape(-1, np.shape(xy)[-1])[:, :2]
        return np.all((p >= lo[:2] - grow) & (p <= hi[:2] + grow), axis=1)


def area_of(wc: Workcell, b: BinPickConfig) -> Area:
    """The heap's area in the workcell ``wc``."""
    walls = b.scene == "bin"
    return Area(tote_of(wc.cfg, b.clutter), walls, 0.0 if walls else b.clutter.pile_margin)


@functools.lru_cache(maxsize=8)
def wall_points(tote: Tote, spacing: float = 0.005) -> np.ndarray:
    """(N, 3) world points (m) every ``spacing`` on the tote walls' inner faces and on their top rims."""
    lo, hi = tote.inner_bounds()
    t = tote.cfg.thickness
    pts = []
    zs = np.arange(lo[2], hi[2] + 1e-9, spacing)
    for axis in (0, 1):
        other = 1 - axis
        s = np.arange(lo[other] - t, hi[other] + t + 1e-9, spacing)
        for side, inward in ((lo[axis], -1.0), (hi[axis], 1.0)):
            for off in np.arange(0.0, t + 1e-9, spacing):  # the inner face, then across the rim
                for z in (zs if off == 0.0 else [hi[2]]):
                    p = np.zeros((len(s), 3))
                    p[:, axis], p[:, other], p[:, 2] = side + inward * off, s, z
                    pts.append(p)
    return np.concatenate(pts)


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
    return all(_box_distance(local, np.asarray(lo), np.asarray(hi)).min() >= clearance for lo, hi in boxes)


def pregrasp_height(cfg: TrialConfig, area: Area, T_grasp: np.ndarray) -> float:
    """How far (m) above the grasp the approach starts: ``grasp.pregrasp_height``, or higher, so the fingertips
    start ``wall_margin`` above the walls."""
    start = area.top + cfg.grasp.fingertip_depth + cfg.bin_pick.wall_margin
    return max(cfg.grasp.pregrasp_height, start - T_grasp[2, 3])


def _tried(grasp: Grasp, failed: list[np.ndarray], b: BinPickConfig) -> bool:
    """Is ``grasp`` one of the ``failed`` grasp poses (world gripper), within ``retry_distance`` and
    ``retry_angle_deg``?"""
    T = grasp.T_world_gripper
    return any(np.linalg.norm(T[:3, 3] - F[:3, 3]) < b.retry_distance
               and T[:3, 0] @ F[:3, 0] > np.cos(np.radians(b.retry_angle_deg)) for F in failed)


def choose_part(wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray, heap: np.ndarray,
                yaw_now: float, failed: list[np.ndarray] = ()) -> tuple[int, Grasp, np.ndarray]:
    """The estimate to pick (index), its grasp and its levelled ``T_world_obj`` among the estimates in the tote,
    none of the grasps that ``failed`` before (``_tried``), at the first of ``part_clearance`` that gives a
    reachable grasp; ``EpisodeFailed``: "nothing graspable" when no part has a clear grasp at any, "unreachable"
    when the IK reaches none. ``heap``: the depth image's points on the heap (``heap_points``)."""
    b, g_cfg = cfg.bin_pick, cfg.grasp
    area = area_of(wc, b)
    cat = catalog_by_id(wc.cfg.objects)
    poses = [level(cat[e.obj_id], T_world_cam @ e.T_cam_obj, cfg, area.floor) for e in ests]
    tops = [float(transform_points(T, cat[e.obj_id].vertices)[:, 2].max()) for e, T in zip(ests, poses)]
    clouds = [transform_points(T, surface_points(cat[e.obj_id], g_cfg.neighbour_points)) for e, T in zip(ests, poses)]
    walls = wall_points(area.tote) if area.walls else np.zeros((0, 3))
    cam, hand = camera_box(wc.cfg.hand_camera.mount_pos), hand_of(wc.cfg)
    reach = g_cfg.max_width / 2 + b.finger_margin + 0.1  # the open hand and camera lie within this of the part

    @functools.cache
    def around(j: int) -> tuple[cKDTree, np.ndarray, np.ndarray]:
        """Part ``j``'s surface points (a tree), the obstacle points and the wall points near it (world)."""
        T, r = poses[j], reach + 0.5 * cat[ests[j].obj_id].diameter
        near = lambda p: p[np.linalg.norm(p[:, :2] - T[:2, 3], axis=1) < r]  # noqa: E731
        own = cKDTree(transform_points(T, surface_points(cat[ests[j].obj_id])))
        depth = near(heap)
        depth = depth[own.query(depth, distance_upper_bound=b.own_margin)[0] > b.own_margin] if len(depth) else depth
        return own, np.concatenate([near(c) for i, c in enumerate(clouds) if i != j] + [depth]), near(walls)

    seen_any = False
    for clearance in b.part_clearance:
        plan_cfg = dataclasses.replace(g_cfg, min_pinch_height=area.floor + g_cfg.min_pinch_height,
                                       finger_margin=b.finger_margin, clearance_min=clearance,
                                       score=dataclasses.replace(g_cfg.score, turn=b.turn_weight))
        options, parts = [], 0
        for j in sorted(range(len(ests)), key=lambda i: -tops[i]):
            own, others, wall = around(j)
            clear_of_walls = lambda g, c=g_cfg.clearance_min: _clear_of(g, wall, [cam], c) and (  # noqa: E731
                not area.walls or _fingers_inside(g, wc.cfg, b.finger_margin, area.tote, c))
            shifted_clear = lambda g: clear_of_walls(g, b.shift_clearance)  # noqa: E731
            grasps = [g for g0 in plan_grasps(cat[ests[j].obj_id], poses[j], others, plan_cfg, yaw_now,
                                              yaw_stable=holds_firmly(cfg), hand=hand)
                      for g in ([g0] if clear_of_walls(g0) else
                                _shifted(g0, own.data, others, b, clearance, shifted_clear, hand)
                                or _tilted(g0, own.data, others, b, clearance, shifted_clear, wc.cfg, area.floor,
                                           g_cfg.score.tilt, hand))
                      if not _tried(g, failed, b) and _clear_of(g, others, [cam], clearance)
                      and _clear_of(g, own.data, hand.boxes((g.width + b.finger_margin) / 2)[:-1], 0.0)
                      ][:g_cfg.grasps_per_block]
            options += [(g.score + g_cfg.detection_weight * ests[j].score + b.height_weight * (tops[j] - area.floor),
                         j, g) for g in grasps]
            parts += bool(grasps)
            if parts >= b.plan_parts:
                break
        seen_any |= bool(options)
        options.sort(key=lambda o: -o[0])
        for _, j, g in options[:g_cfg.ik_checks]:
            qs = reach_q(wc, g_cfg, g.T_world_gripper, pregrasp_height(cfg, area, g.T_world_gripper))
            if qs is not None and (not area.walls or arm_clear(wc.cfg, area.tote, *qs, g_cfg.clearance_min)):
                return j, g, poses[j]
    raise EpisodeFailed(Failure.UNREACHABLE if seen_any else Failure.NOTHING_GRASPABLE)


def _pad_overlap(T: np.ndarray, width: float, own: np.ndarray, hand: Hand) -> tuple[float, float]:
    """With the ``hand`` at ``T`` (world gripper) open on a part ``width`` (m) across, how far (m) along the gripper
    y axis the part's contact faces (its surface points ``own``, world, within the pads' height ``CONTACT_BAND``)
    meet finger 1's pad and the best of the facing fingers' (0 where a face is missing)."""
    local = (own - T[:3, 3]) @ T[:3, :3]
    band = (local[:, 2] > CONTACT_BAND[0]) & (local[:, 2] < CONTACT_BAND[1])
    faces = [local[band & (s * local[:, 0] > width / 2 - ON_PLANE_TOL), 1] for s in (1.0, -1.0)]
    return tuple(max((min(f.max(), y1) - max(f.min(), y0) for y0, y1 in spans), default=0.0) if len(f) else 0.0
                 for f, spans in zip(faces, (hand.finger1_y, hand.facing_y)))


def _fits(g: Grasp, need: float | np.ndarray, own: np.ndarray, others: np.ndarray, clearance: float,
          clear: Callable[[Grasp], bool], margin: float, hand: Hand) -> bool:
    """Does a moved grasp ``g`` still hold: the part's contact faces (surface points ``own``, world) meet the pads
    by ``need`` (m; finger 1, the facing fingers: ``_pad_overlap``), it is ``clear`` of the walls and the ``hand``,
    open ``margin`` (m) wider than the part, keeps ``clearance`` (m) from the ``others`` points?"""
    return bool(np.all(np.asarray(_pad_overlap(g.T_world_gripper, g.width, own, hand)) >= need)) and clear(g) \
        and _clear_of(g, others, hand.boxes((g.width + margin) / 2), clearance)


def _shifted(grasp: Grasp, own: np.ndarray, others: np.ndarray, b: BinPickConfig, clearance: float,
             clear: Callable[[Grasp], bool], hand: Hand) -> list[Grasp]:
    """``grasp`` with the hand moved along its y axis by each of ``wall_shifts`` (nearest first) where it still
    ``_fits`` (the pads meeting the faces by ``shift_contact``): the part sits off-centre in the hand, away from the
    wall that the fingers' sides would touch."""
    out = []
    for d in sorted(b.wall_shifts, key=abs):
        T = grasp.T_world_gripper.copy()
        T[:3, 3] += d * T[:3, 1]
        g = dataclasses.replace(grasp, T_world_gripper=T)
        if _fits(g, b.shift_contact, own, others, clearance, clear, b.finger_margin, hand):
            out.append(g)
    return out


def _tilted(grasp: Grasp, own: np.ndarray, others: np.ndarray, b: BinPickConfig, clearance: float,
            clear: Callable[[Grasp], bool], wc_cfg, floor: float, per_deg: float, hand: Hand) -> list[Grasp]:
    """``grasp`` with the hand turned about its pinch point by the least of ``wall_tilts_deg`` that gives any,
    about its squeeze axis x or its y axis, either way (the hand's top leaning away from a wall, its fingertips
    reaching under the part's side toward it), and raised until the open fingers keep ``tilt_floor_clearance``
    above the ``floor`` (m), where it still ``_fits`` (the pads meeting the faces as far as the untilted grasp's, up
    to ``shift_contact``); their score loses ``per_deg`` per degree. A tilt about y tilts the squeeze from the
    horizontal by as much: the contacts' friction bears it (``wall_tilts_deg`` up to 40 deg)."""
    tips = open_finger_points(wc_cfg, round(1000 * (grasp.width + b.finger_margin)))
    T0, out = grasp.T_world_gripper, []
    need = np.minimum(_pad_overlap(T0, grasp.width, own, hand), b.shift_contact) - ON_PLANE_TOL
    for deg in sorted(b.wall_tilts_deg):
        for axis in (T0[:3, 0], -T0[:3, 0], T0[:3, 1], -T0[:3, 1]):
            T = T0.copy()
            T[:3, :3] = axis_angle_R(axis, np.radians(deg)) @ T0[:3, :3]
            T[2, 3] += max(0.0, floor + b.tilt_floor_clearance - float(transform_points(T, tips)[:, 2].min()))
            g = dataclasses.replace(grasp, T_world_gripper=T, score=grasp.score - per_deg * deg)
            if _fits(g, need, own, others, clearance, clear, b.finger_margin, hand):
                out.append(g)
        if out:
            return out
    return out


def _fingers_inside(grasp: Grasp, wc_cfg, margin: float, tote: Tote, clearance: float) -> bool:
    """Do the fingers, open ``margin`` (m) wider than the ``grasp`` (``controller.open_finger_points``, their
    meshes), stay ``clearance`` (m) inside the tote's inner walls wherever they are lower than the walls' top plus
    ``clearance``?"""
    pts = transform_points(grasp.T_world_gripper, open_finger_points(wc_cfg, round(1000 * (grasp.width + margin))))
    lo, hi = tote.inner_bounds()
    low = pts[pts[:, 2] < hi[2] + clearance, :2]
    return bool(np.all((low >= lo[:2] + clearance) & (low <= hi[:2] - clearance)))


@functools.lru_cache(maxsize=4)
def _tote_robot(wc_cfg, tote: Tote) -> tuple[Workcell, np.ndarray, np.ndarray, np.ndarray]:
    """A robot-and-tote workcell (no parts), the tote walls' geoms, the robot's geoms and those but the fingers."""
    wc = Workcell(wc_cfg, extras=tote.add_to)
    m = wc.model
    walls = np.array([m.geom(f"tote/{w}").id for w in WALLS])
    robot = np.flatnonzero([m.body(b).name.startswith("jaco_arm/") for b in m.geom_bodyid] & (m.geom_contype > 0))
    return wc, walls, robot, np.array([g for g in robot if "finger" not in m.geom(g).name])


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


def visible_fraction(ep: Episode, frame: Frame, k: int) -> float | None:
    """Part ``k``'s visible share at the capture ``frame``: its pixels in the frame's instance mask over those of
    its unoccluded silhouette (the part drawn alone, as datagen's ``visib_fract``); None when it is out of view."""
    m, r = ep.wc.model, ep.camera.renderer
    geoms = np.flatnonzero((ep.wc.geom_instance[:-1] == k) & (m.geom_group == 1))
    saved = m.geom_group[geoms].copy()
    option = mujoco.MjvOption()
    option.geomgroup[:] = 0
    option.geomgroup[5] = 1
    m.geom_group[geoms] = 5
    try:
        r.disable_depth_rendering()
        r.enable_segmentation_rendering()
        r.update_scene(ep.wc.data, camera=ep.camera.cam_id, scene_option=option)
        seg = r.render()
        r.disable_segmentation_rendering()
    finally:
        m.geom_group[geoms] = saved
    alone = int(np.count_nonzero(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)))
    return None if alone == 0 else min(1.0, int(np.count_nonzero(frame.mask == k)) / alone)


class _Contacts:
    """Control-period monitor: has the robot touched the floor or the table (``floor``) or another part than the
    target ``k`` (``parts``)? A protective stop (``EpisodeFailed``, raised in the control period, the arm stopping
    where it is) when it touches the tote's walls ("hit the wall") or, while it has an ``approach`` axis (from the
    pre-grasp to the lift: those moves keep the hand's orientation), contacts turn the hand more than
    ``tilt_stop_deg`` from it ("collision")."""

    def __init__(self, ep: Episode, walls: np.ndarray, floors: np.ndarray, k: int):
        self.ep, self.walls, self.floors = ep, walls, floors
        inst = ep.wc.geom_instance[:-1]
        self.others = np.flatnonzero((inst > 0) & (inst != k))
        self.cos_tilt = float(np.cos(np.radians(ep.cfg.bin_pick.tilt_stop_deg)))
        self.floor = self.parts = False
        self.approach: np.ndarray | None = None  # the grasp's approach axis (world), once at the pre-grasp

    def __call__(self) -> None:
        d = self.ep.wc.data
        if d.ncon:
            g = d.contact.geom[: d.ncon]
            rob = self.ep.ctl.robot_geom[g]
            touch = [bool(np.any(rob[:, 0] & np.isin(g[:, 1], ids) | rob[:, 1] & np.isin(g[:, 0], ids)))
                     for ids in (self.walls, self.floors, self.others)]
            self.floor |= touch[1]
            self.parts |= touch[2]
            if touch[0]:
                raise EpisodeFailed(Failure.WALL_HIT)
        if self.approach is not None and d.site_xmat[self.ep.wc.gripper_site][2::3] @ self.approach < self.cos_tilt:
            raise EpisodeFailed(Failure.COLLISION)

    def blocked(self) -> Failure:
        """Why the hand did not get to the grasp or close on the part: it hit something, or (else) it timed out."""
        return Failure.COLLISION if self.floor or self.parts else Failure.TIMEOUT


def _bottoms(wc: Workcell) -> np.ndarray:
    """Lowest point (m, world z) of every part."""
    return np.array([transform_points(T, inst.block.vertices)[:, 2].min()
                     for T, inst in zip(wc.block_poses(), wc.blocks)])


def pick_and_drop(ep: Episode, plan: Plan, area: Area, box: Tote, att: Attempt) -> None:
    """Pick ``plan``'s part, lift it clear of the walls, carry it over the out-box ``box`` and let it go; marks
    ``att.grasped``; ``EpisodeFailed`` when the robot hits a wall, the floor on a failed grasp, the part slips or
    falls, or another part came up with it (after the drop). A neighbour that stops the hand short of the grasp
    (``_stopped_near``) does not end the attempt: the fingers close where the hand stopped."""
    ctl, cfg, k = ep.ctl, ep.cfg, plan.k
    g_cfg, b = cfg.grasp, cfg.bin_pick
    m = ep.wc.model
    walls = np.array([m.geom(f"tote/{w}").id for w in WALLS]) if area.walls else np.zeros(0, int)
    floors = np.array([m.geom("table").id] + ([m.geom("tote/floor").id] if area.walls else []))
    watch = _Contacts(ep, walls, floors, k)
    T_grasp = plan.grasp.T_world_gripper
    T_pre = T_grasp.copy()
    T_pre[2, 3] += pregrasp_height(cfg, area, T_grasp)
    opening = plan.grasp.width + b.finger_margin
    ctl.preshape(opening)
    ctl.monitor = watch
    try:
        if not ctl.move(T_pre):
            raise EpisodeFailed(Failure.TIMEOUT)
        watch.approach = T_grasp[:3, 2]
        if not ctl.move(T_grasp, speed=g_cfg.approach_speed):
            if not _stopped_near(ep.wc.gripper_pose(), T_grasp, b) or watch.floor:
                raise EpisodeFailed(watch.blocked())
            ctl.target = ep.wc.gripper_pose()
        if not ctl.close(k, wait_all=cfg.firm_hold.finger_wait if holds_firmly(cfg) else 0):
            raise EpisodeFailed(Failure.COLLISION if watch.floor else Failure.SLIP)
        ep.log.stop("pick", ctl, add=True)
        start = _bottoms(ep.wc)
        bottom_est, _ = plan.height_range()
        clear = max(area.top, box.top_z) + b.wall_margin  # the part's bottom above both boxes' walls
        T_lift = ctl.target.copy()  # the grasp, or where a neighbour stopped the hand above it
        T_lift[2, 3] += max(clear - bottom_est, ep.cfg.scoring.lift_min)
        ctl.move(T_lift)
        att.grasped = bool(_bottoms(ep.wc)[k - 1] >= area.top + 0.5 * b.wall_margin and ctl.finger_contacts(k).any())
        if not att.grasped:
            raise EpisodeFailed(Failure.SLIP)
        rose = _bottoms(ep.wc) - start
        rose[k - 1] = 0.0
        double = bool(np.any(rose > b.double_rise))
        ep.log.stop("lift", ctl, add=True)
        watch.approach = None  # the carry turns the hand about the vertical with the arm's base
        T_drop = _swung(T_lift, np.asarray(box.center) + (T_grasp[:2, 3] - plan.T_world_obj[:2, 3]))
        ctl.move(T_drop, speed=g_cfg.carry_speed)
        if not ctl.finger_contacts(k).any():
            raise EpisodeFailed(Failure.DROP)
        ctl.release(k, opening, g_cfg.release_time)
        ep.log.stop("carry", ctl, add=True)
        if double:
            raise EpisodeFailed(Failure.DOUBLE_PICK)
    finally:
        ctl.monitor = None


def _stopped_near(T: np.ndarray, T_grasp: np.ndarray, b: BinPickConfig) -> bool:
    """Did the hand stop (gripper pose ``T``, world) close enough to ``T_grasp`` to close there: at most
    ``close_slack`` above it and ``close_slack_side`` beside it?"""
    d = T[:3, 3] - T_grasp[:3, 3]
    return bool(0.0 <= d[2] <= b.close_slack and np.linalg.norm(d[:2]) <= b.close_slack_side)


def _swung(T: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``T`` (world gripper) moved over ``xy`` (m) at its height and turned about the vertical as the arm's base
    turns between them (the world origin), so the wrist keeps its angle: a dropped part's yaw does not matter,
    and the wrist's turn back to the look is what costs time."""
    turn = float(np.arctan2(xy[1], xy[0]) - np.arctan2(T[1, 3], T[0, 3]))
    out = T.copy()
    out[:3, :3] = axis_angle_R(np.array([0.0, 0.0, 1.0]), turn) @ T[:3, :3]
    out[:2, 3] = xy
    return out


def _open_and_retreat(ep: Episode, area: Area) -> None:
    """Open the hand wide and raise it straight up above the walls from where it is (after a failed pick, before the
    look): a hand stopped by a wall or a part lags its target, and a move from the target would drag it across."""
    ctl = ep.ctl
    ctl.target = ep.wc.gripper_pose()
    ctl.preshape(ep.cfg.grasp.max_width + ep.cfg.grasp.finger_margin, ctl.cfg.release_speed)
    ctl.hold(0.2)
    T = ctl.target.copy()
    T[2, 3] = max(T[2, 3], area.top + ep.cfg.grasp.fingertip_depth + ep.cfg.grasp.pregrasp_height)
    ctl.move(T)


def _look(ep: Episode, area: Area) -> None:
    """Drive the arm (the fingers held still) to the nearer of the two looks straight down at the tote's centre from
    the workcell's ``look_height``, the image's up along world +x or -x (the wrist turned half a turn: the nearer
    one spares the slow wrist most of its turn back after a pick); ``EpisodeFailed(TIMEOUT)`` if it does not get
    there."""
    wc = ep.wc
    qs = [look_down_q(wc.cfg, area.tote.center, wc.cfg.look_height, "look_height", up) for up in (1.0, -1.0)]
    q = min(qs, key=lambda q: float(np.max(np.abs(wrap_angle(q - wc.arm_q)) / wc.arm_velocity_limits())))
    wc.data.ctrl[wc.finger_act] = 0.0
    if not drive_to_look(wc, dataclasses.replace(ep.cfg.control, look_timeout=ep.cfg.bin_pick.look_timeout), q):
        raise EpisodeFailed(Failure.TIMEOUT)
    ep.ctl.check_stable()
    ep.ctl.target = wc.gripper_pose()
    ep.ctl.finger_target = None
    ep.ctl.finger_cmd = np.zeros_like(ep.ctl.finger_cmd)
    ep.log.stop("look", ep.ctl, add=True)


def tally(wc: Workcell, area: Area, box: Tote, parts: list[int]) -> tuple[list[int], list[int]]:
    """Which of ``parts`` (1-based) lie in the out-box ``box`` (every vertex, within 5 mm), and which of the others
    have left the heap's area (their centre outside it: thrown out)? The simulator's truth, for the verdicts."""
    poses = wc.block_poses()
    gone = [k for k in parts if box.contains(transform_points(poses[k - 1], wc.blocks[k - 1].block.vertices), 0.005)]
    thrown = [k for k in parts if k not in gone and not area.holds(poses[k - 1][None, :3, 3])[0]]
    return gone, thrown


def empty_tote(ep: Episode) -> None:
    """The bin-picking episode: attempts until the robot sees nothing left, ``max_failures`` failed in a row or
    ``attempts_per_part`` per part, or when it sees again what it saw when it found nothing graspable (no attempt
    is recorded for that look: it would find no grasp again); fills in ``ep.rec`` (a ``BinPickRecord``). Raises
    ``EpisodeFailed`` with the episode's end reason unless every part went into the out-box."""
    rec: BinPickRecord = ep.rec  # type: ignore[assignment]
    cfg, wc = ep.cfg, ep.wc
    b = cfg.bin_pick
    area, box = area_of(wc, b), outbox_of(wc.cfg, b)
    n = len(wc.blocks)
    left = list(range(1, n + 1))  # parts neither in the out-box nor thrown out
    lost: list[int] = []
    failed: list[np.ndarray] = []  # grasp poses that failed: not tried again
    in_a_row = 0
    stuck: list[Estimate] | None = None  # what the robot saw when it last found nothing graspable
    end = Failure.PARTS_LEFT
    ests: list[Estimate] = []
    _look(ep, area)
    for a in range(b.attempts_per_part * n):
        t0 = ep.ctl.sim_time
        att = Attempt(a)
        frame = ep.capture(a, images=True)
        if ep.captures_only:
            return
        try:
            seed = ep.percept_seed if a == 0 else ep.seed_for(a)
            try:
                ests = ep.perceive(frame, seed, a)
            except PerceptionError as e:
                rec.perception_error = str(e)
                raise EpisodeFailed(Failure.PERCEPTION_ERROR) from None
            T_world_cam = ep.T_world_cam()
            cat = catalog_by_id(wc.cfg.objects)
            ests = [e for e in ests if area.holds((T_world_cam @ e.T_cam_obj)[None, :3, 3])[0]]
            att.detected = len(ests)
            heap = heap_points(depth_points(frame, T_world_cam, b.depth_stride), area, b)
            ep.log.stop("perceive", ep.ctl, add=True)
            if stuck is not None and _same_view(ests, stuck):  # it would find no grasp again: no attempt
                end = Failure.NOTHING_GRASPABLE
                break
            if not ests:
                if len(heap) < 10:  # nothing seen, nothing above the floor: the robot believes the tote empty
                    break
                raise EpisodeFailed(Failure.NO_DETECTION)
            try:
                j, grasp, T_est = choose_part(wc, cfg, ests, T_world_cam, heap, gripper_yaw(ep.ctl.target), failed)
            finally:
                ep.log.stop("plan", ep.ctl, add=True)
            k = match_block(wc, T_est)
            if k == 0:
                att.target = FalseTarget(0, ests[j].obj_id)
                raise EpisodeFailed(Failure.POSE_ERROR)
            block = wc.blocks[k - 1].block
            att.target = Target(k, block.name, block.obj_id == ests[j].obj_id, block.diameter, grasp.width,
                                grasp.clearance, grasp.support, grasp.tilt_deg)
            att.pose_error = pose_errors(block, T_est, wc.block_poses()[k - 1], cfg.scoring.pose_error_points)
            att.visib_fract = visible_fraction(ep, frame, k)
            pick_and_drop(ep, Plan(k, block, grasp, T_est, cat[ests[j].obj_id]), area, box, att)
        except EpisodeFailed as f:
            att.failure = f.reason
            if att.target is not None and att.target.instance:
                failed.append(grasp.T_world_gripper)
                _open_and_retreat(ep, area)
        except SimulationError:
            att.failure = Failure.SIMULATION_ERROR
            _finish(rec, att, ep.ctl.sim_time - t0, n, left + lost, cfg.scoring)
            raise
        try:
            _look(ep, area)
        except EpisodeFailed:  # the arm is lost: the attempt and the episode end here
            att.failure = att.failure or Failure.TIMEOUT
            _finish(rec, att, ep.ctl.sim_time - t0, n, left + lost, cfg.scoring)
            raise
        gone, thrown = tally(wc, area, box, left)
        for k in gone:
            park(wc, k)
        left = [k for k in left if k not in gone and k not in thrown]
        lost += thrown
        att.removed, att.thrown_out = gone, thrown
        target = att.target.instance if att.target is not None else 0
        if att.failure is None and target not in gone:
            att.failure = Failure.DROP if target in left else Failure.MISPLACED
        if att.failure is None and [k for k in thrown if k != target]:
            att.failure = Failure.THROWN_OUT
        _finish(rec, att, ep.ctl.sim_time - t0, n, left + lost, cfg.scoring)
        in_a_row = 0 if att.outcome == "success" else in_a_row + 1
        stuck = ests if att.failure == Failure.NOTHING_GRASPABLE else None
        if in_a_row >= b.max_failures:
            if rec.removed < n:
                raise EpisodeFailed(Failure.FAILED_IN_A_ROW)
            return
    else:
        if rec.removed < n:
            raise EpisodeFailed(Failure.ATTEMPT_LIMIT)
    if rec.removed < n:
        raise EpisodeFailed(end)


def _same_view(ests: list[Estimate], before: list[Estimate], tol: float = 1e-6) -> bool:
    """Are ``ests`` the estimates ``before`` (same objects, poses within ``tol``): the robot sees what it saw?"""
    return len(ests) == len(before) and all(
        a.obj_id == b.obj_id and np.allclose(a.T_cam_obj, b.T_cam_obj, atol=tol) for a, b in zip(ests, before))


def _finish(rec: BinPickRecord, att: Attempt, sim_time: float, n: int, not_removed: list[int],
            s_cfg: ScoringConfig) -> None:
    """Judge attempt ``att`` (its failure blamed on the pose estimate where it was far off, ``episode.blame``), add
    it to the record and update the record's counts (``not_removed``: the parts still out of the out-box)."""
    if att.failure is None:
        att.outcome = "success"
    else:
        att.failure = blame(att.failure, att.pose_error, att.target, s_cfg)
    att.sim_time = round(sim_time, 3)
    rec.attempts.append(att)
    rec.detected = rec.attempts[0].detected
    rec.grasped = any(x.grasped for x in rec.attempts)
    rec.removed = n - len(not_removed)
    rec.cleared = rec.removed / n
