"""Bin picking's attempt loop: look down at the tote, perceive, choose the next part (``planner``), pick it,
lift it clear of the walls and drop it into the out-box, until the tote is believed empty.

The robot judges only from what it perceives: it stops when it sees no part in the tote and the depth image shows
nothing above the floor. The verdicts of an attempt use the simulator's truth: a robot touching the tote's walls
(a protective stop: "hit the wall"; so is a hand that contacts turn ``tilt_stop_deg`` from the grasp's approach,
"collision"), another part rising with the target ("two parts lifted"), a part leaving the
tote elsewhere than into the out-box ("part thrown out"), the target not landing in the out-box ("misplaced").
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from posegrasp.catalog import catalog_by_id
from posegrasp.errors import SimulationError
from posegrasp.geometry import axis_angle_R, transform_points
from posegrasp.grasping.config import ScoringConfig, holds_firmly
from posegrasp.grasping.perception import Estimate, PerceptionError
from posegrasp.grasping.record import FalseTarget, Failure, Target
from posegrasp.grasping.targets import Plan, blame, drive_to_look, gripper_yaw, look_down_q, match_block, pose_errors
from posegrasp.grasping.tasks.base import EpisodeFailed
from posegrasp.grasping.tasks.bin_pick.config import BinPickConfig
from posegrasp.grasping.tasks.bin_pick.planner import choose_part, depth_points, heap_points, pregrasp_height
from posegrasp.grasping.tasks.bin_pick.record import Attempt, BinPickRecord
from posegrasp.grasping.tasks.bin_pick.scene import Area, area_of, outbox_of
from posegrasp.sim.camera import Frame
from posegrasp.sim.clutter import park
from posegrasp.sim.tote import WALLS, Tote
from posegrasp.sim.workcell import Workcell, wrap_angle

if TYPE_CHECKING:
    from posegrasp.grasping.episode import Episode


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
    run = _Emptying(ep)
    _look(ep, run.area)
    b, n = ep.cfg.bin_pick, run.n
    for a in range(b.attempts_per_part * n):
        go_on = run.attempt(a)
        if ep.captures_only:
            return
        if not go_on:
            break
        if run.in_a_row >= b.max_failures:
            if run.rec.removed < n:
                raise EpisodeFailed(Failure.FAILED_IN_A_ROW)
            return
    else:
        if run.rec.removed < n:
            raise EpisodeFailed(Failure.ATTEMPT_LIMIT)
    if run.rec.removed < n:
        raise EpisodeFailed(run.end)


class _Emptying:
    """A bin-picking episode under way: the parts still in play and what the robot learnt from its attempts."""

    def __init__(self, ep: Episode):
        self.ep, self.rec = ep, ep.rec
        self.area, self.box = area_of(ep.wc, ep.cfg.bin_pick), outbox_of(ep.wc.cfg, ep.cfg.bin_pick)
        self.n = len(ep.wc.blocks)
        self.left = list(range(1, self.n + 1))  # parts neither in the out-box nor thrown out
        self.lost: list[int] = []
        self.failed: list[np.ndarray] = []  # grasp poses that failed: not tried again
        self.in_a_row = 0
        self.stuck: list[Estimate] | None = None  # what the robot saw when it last found nothing graspable
        self.end = Failure.PARTS_LEFT
        self.ests: list[Estimate] = []

    def attempt(self, a: int) -> bool:
        """Attempt ``a``: capture, perceive, pick and drop, look again, judge; False when the episode stops at
        this look (the robot believes the tote empty, or sees what it found nothing graspable in)."""
        ep, t0, att = self.ep, self.ep.ctl.sim_time, Attempt(a)
        frame = ep.capture(a, images=True)
        if ep.captures_only:
            return False
        try:
            if not self._pick(att, frame):
                return False
        except EpisodeFailed as f:
            att.failure = f.reason
            if att.target is not None and att.target.instance:
                self.failed.append(self.grasp.T_world_gripper)
                _open_and_retreat(ep, self.area)
        except SimulationError:
            att.failure = Failure.SIMULATION_ERROR
            self._finish(att, t0)
            raise
        try:
            _look(ep, self.area)
        except EpisodeFailed:  # the arm is lost: the attempt and the episode end here
            att.failure = att.failure or Failure.TIMEOUT
            self._finish(att, t0)
            raise
        self._tally(att)
        self._finish(att, t0)
        self.in_a_row = 0 if att.outcome == "success" else self.in_a_row + 1
        self.stuck = self.ests if att.failure == Failure.NOTHING_GRASPABLE else None
        return True

    def _pick(self, att: Attempt, frame: Frame) -> bool:
        """Perceive ``frame``, choose a part and pick and drop it (``EpisodeFailed`` when the attempt fails); False
        when the robot stops at this look instead."""
        ep, wc, cfg, b = self.ep, self.ep.wc, self.ep.cfg, self.ep.cfg.bin_pick
        a = att.attempt
        seed = ep.percept_seed if a == 0 else ep.seed_for(a)
        try:
            ests = ep.perceive(frame, seed, a)
        except PerceptionError as e:
            self.rec.perception_error = str(e)
            raise EpisodeFailed(Failure.PERCEPTION_ERROR) from None
        T_world_cam = ep.T_world_cam()
        cat = catalog_by_id(wc.cfg.objects)
        self.ests = ests = [e for e in ests if self.area.holds((T_world_cam @ e.T_cam_obj)[None, :3, 3])[0]]
        att.detected = len(ests)
        heap = heap_points(depth_points(frame, T_world_cam, b.depth_stride), self.area, b)
        ep.log.stop("perceive", ep.ctl, add=True)
        if self.stuck is not None and _same_view(ests, self.stuck):  # it would find no grasp again: no attempt
            self.end = Failure.NOTHING_GRASPABLE
            return False
        if not ests:
            if len(heap) < 10:  # nothing seen, nothing above the floor: the robot believes the tote empty
                return False
            raise EpisodeFailed(Failure.NO_DETECTION)
        try:
            j, self.grasp, T_est = choose_part(wc, cfg, ests, T_world_cam, heap, gripper_yaw(ep.ctl.target),
                                               self.failed)
        finally:
            ep.log.stop("plan", ep.ctl, add=True)
        k = match_block(wc, T_est)
        if k == 0:
            att.target = FalseTarget(0, ests[j].obj_id)
            raise EpisodeFailed(Failure.POSE_ERROR)
        block, g = wc.blocks[k - 1].block, self.grasp
        att.target = Target(k, block.name, block.obj_id == ests[j].obj_id, block.diameter, g.width, g.clearance,
                            g.support, g.tilt_deg)
        att.pose_error = pose_errors(block, T_est, wc.block_poses()[k - 1], cfg.scoring.pose_error_points)
        att.visib_fract = visible_fraction(ep, frame, k)
        pick_and_drop(ep, Plan(k, block, g, T_est, cat[ests[j].obj_id]), self.area, self.box, att)
        return True

    def _tally(self, att: Attempt) -> None:
        """After the attempt, the simulator's truth: the parts in the out-box (taken out of the scene) and those
        thrown out, and the attempt's verdict on its target."""
        wc = self.ep.wc
        gone, thrown = tally(wc, self.area, self.box, self.left)
        for k in gone:
            park(wc, k)
        self.left = [k for k in self.left if k not in gone and k not in thrown]
        self.lost += thrown
        att.removed, att.thrown_out = gone, thrown
        target = att.target.instance if att.target is not None else 0
        if att.failure is None and target not in gone:
            att.failure = Failure.DROP if target in self.left else Failure.MISPLACED
        if att.failure is None and [k for k in thrown if k != target]:
            att.failure = Failure.THROWN_OUT

    def _finish(self, att: Attempt, t0: float) -> None:
        _finish(self.rec, att, self.ep.ctl.sim_time - t0, self.n, self.left + self.lost, self.ep.cfg.scoring)


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
