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
from typing import TYPE_CHECKING, Callable

import mujoco
import numpy as np

from posegrasp.catalog import catalog_by_id
from posegrasp.errors import SimulationError
from posegrasp.grasping.config import ScoringConfig
from posegrasp.grasping.perception import Estimate, PerceptionError
from posegrasp.grasping.record import FalseTarget, Failure
from posegrasp.grasping.targets import Plan, blame, drive_to_look, gripper_yaw, look_down_q, match_block, pose_errors
from posegrasp.grasping.tasks.base import EpisodeFailed
from posegrasp.grasping.tasks.bin_pick.pick import Destination, OutBox, Tool, tool_of
from posegrasp.grasping.tasks.bin_pick.planner import depth_points, heap_points
from posegrasp.grasping.tasks.bin_pick.record import Attempt, BinPickRecord
from posegrasp.grasping.tasks.bin_pick.scene import Area, area_of, outbox_of, tray_of
from posegrasp.grasping.tasks.bin_pick.shake import Shake, shake_direction
from posegrasp.grasping.tasks.bin_pick.tray import TrayPlace
from posegrasp.sim.camera import Frame, instances
from posegrasp.sim.clutter import park
from posegrasp.sim.shaker import Shaker
from posegrasp.sim.workcell import HAND_CAMERA, Workcell, wrap_angle

if TYPE_CHECKING:
    from posegrasp.grasping.episode import Episode


def visible_fraction(ep: Episode, frame: Frame, k: int) -> float | None:
    """Part ``k``'s visible share at the capture ``frame``: its pixels in the frame's instance mask over those of
    its unoccluded silhouette (the part drawn alone, as datagen's ``visib_fract``); None when it is out of view."""
    cam = ep.cameras[HAND_CAMERA]
    m, r = ep.wc.model, cam.renderer
    geoms = np.flatnonzero((ep.wc.geom_instance[:-1] == k) & (m.geom_group == 1))
    saved = m.geom_group[geoms].copy()
    option = mujoco.MjvOption()
    option.geomgroup[:] = 0
    option.geomgroup[5] = 1
    m.geom_group[geoms] = 5
    try:
        r.update_scene(ep.wc.data, camera=cam.cam_id, scene_option=option)
        seg = r.read_segments()
    finally:
        m.geom_group[geoms] = saved
    every_geom = np.ones(len(ep.wc.geom_instance), np.uint16)  # any geom's pixels count (the part's alone are drawn)
    alone = int(np.count_nonzero(instances(r.scene, seg, every_geom)))
    return None if alone == 0 else min(1.0, int(np.count_nonzero(frame.mask == k)) / alone)


def _open_and_retreat(ep: Episode, area: Area, tool: Tool) -> None:
    """Let go (``Tool.let_go``) and raise the tool straight up above the walls from where it is (after a failed
    pick, before the look): a hand stopped by a wall or a part lags its target, and a move from the target would
    drag it across."""
    ctl = ep.ctl
    ctl.target = ep.wc.gripper_pose()
    tool.let_go(ep)
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


def tally(wc: Workcell, area: Area, dest: Destination, parts: list[int]) -> tuple[list[int], list[int]]:
    """Which of ``parts`` (1-based) lie in the destination ``dest`` (the out-box or the tray), and which of the
    others have left the heap's area (their centre outside it: thrown out)? The simulator's truth, for the
    verdicts."""
    poses = wc.block_poses()
    gone = [k for k in parts if dest.holds(poses[k - 1], wc.blocks[k - 1].block)]
    thrown = [k for k in parts if k not in gone and not area.holds(poses[k - 1][None, :3, 3])[0]]
    return gone, thrown


def empty_tote(ep: Episode) -> None:
    """The bin-picking episode: attempts until the robot sees nothing left, ``max_failures`` failed in a row or
    ``attempts_per_part`` per part, or when it sees again what it saw when it found nothing graspable or nothing
    the arm reaches (no attempt is recorded for that look: it would find no grasp to try again); fills in
    ``ep.rec`` (a ``BinPickRecord``). Raises ``EpisodeFailed`` with the episode's end reason unless every part went
    into the out-box."""
    run = _Emptying(ep)
    ep.rec.place = ep.cfg.bin_pick.place
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
        b = ep.cfg.bin_pick
        self.area = area_of(ep.wc, b)
        self.tray = TrayPlace(ep, tray_of(ep.wc.cfg, b)) if b.place == "tray" else None
        self.dest: Destination = self.tray or OutBox(ep, outbox_of(ep.wc.cfg, b))
        self.n = len(ep.wc.blocks)
        self.left = list(range(1, self.n + 1))  # parts neither in the out-box nor thrown out
        self.lost: list[int] = []
        self.failed: list[np.ndarray] = []  # grasp poses that failed: not tried again
        self.in_a_row = 0
        self.seen: list[tuple[int, np.ndarray]] = []  # the last look's estimates in the tote: (obj_id, T_world_obj)
        self.stuck: list[tuple[int, np.ndarray]] | None = None  # ``seen`` when it last found no grasp to try
        self.stuck_why = Failure.NOTHING_GRASPABLE  # and why: nothing graspable, or nothing the arm reaches
        self.end = Failure.PARTS_LEFT
        self.ests: list[Estimate] = []
        self.tool: Tool = tool_of(ep, self.dest)
        self.shaker = Shaker.of(ep.wc.model, ep.wc.data, b.shaker) if b.shakes else None  # the tote's stage, if on one
        self.shakes = 0
        self.shaking: Shake | None = None  # a shake under way while the arm is away (``shake_away``)

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
                _open_and_retreat(ep, self.area, self.tool)
        except SimulationError:
            att.failure = Failure.SIMULATION_ERROR
            self._finish(att, t0)
            raise
        self._shake(att)
        try:
            _look(ep, self.area)
        except EpisodeFailed:  # the arm is lost: the attempt and the episode end here
            att.failure = att.failure or Failure.TIMEOUT
            self._finish(att, t0)
            raise
        if self.shaking is not None:  # the parts at rest before the look's capture
            self.shaking.finish()
            self.shaking = None
        self._tally(att)
        self._finish(att, t0)
        self.in_a_row = 0 if att.outcome == "success" else self.in_a_row + 1
        self.stuck = self.seen if att.failure in (Failure.NOTHING_GRASPABLE, Failure.UNREACHABLE) else None
        self.stuck_why = att.failure if self.stuck is not None else self.stuck_why
        return True

    def _shake(self, att: Attempt) -> None:
        """After a look that found nothing graspable, shake the tote (``shake.py``) where the episode has shakes
        left and some estimate lies by a wall."""
        b = self.ep.cfg.bin_pick
        if att.failure != Failure.NOTHING_GRASPABLE or self.shaker is None or self.shakes >= b.shakes:
            return
        u = shake_direction(self.area, [T for _, T in self.seen], b.shake_margin)
        if u is not None:
            self._start_shake(att, u).finish()

    def _start_shake(self, att: Attempt, u: np.ndarray) -> Shake:
        """Set the tote shaking along ``u`` in attempt ``att``, one of the episode's shakes."""
        self.shakes += 1
        att.shaken = True
        return Shake(self.ep, self.shaker, u)

    def _away_shake(self, att: Attempt, T_target: np.ndarray) -> Destination:
        """The destination of the attempt's part: with ``shake_away`` and shakes left, one that sets the tote
        shaking (``Shake``) as the part leaves it, where another estimate than the target's (``T_target``) lies
        by a wall: the shake runs while the arm carries the part and comes back, and the next look sees those
        parts off the walls."""
        b = self.ep.cfg.bin_pick
        if not b.shake_away or self.shaker is None or self.shakes >= b.shakes:
            return self.dest
        others = [T for _, T in self.seen if np.linalg.norm(T[:3, 3] - T_target[:3, 3]) > 1e-6]
        u = shake_direction(self.area, others, b.shake_margin)
        if u is None:
            return self.dest

        def start() -> None:
            self.shaking = self._start_shake(att, u)

        return _Leaving(self.dest, start)

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
        self.seen = [(e.obj_id, T_world_cam @ e.T_cam_obj) for e in ests]
        if self.stuck is not None and _same_view(self.seen, self.stuck):  # it would find no grasp again: no attempt
            self.end = self.stuck_why
            return False
        if not ests:
            if len(heap) < 10:  # nothing seen, nothing above the floor: the robot believes the tote empty
                return False
            raise EpisodeFailed(Failure.NO_DETECTION)
        if self.tray is not None:  # only parts of a type with a free slot
            self.tray.placing = None
            ests = [e for e in ests if self.tray.free(cat[e.obj_id].name) is not None]
            if not ests:
                raise EpisodeFailed(Failure.NO_SLOT)
        try:
            j, self.grasp, T_est = self.tool.choose(wc, cfg, ests, T_world_cam, heap, gripper_yaw(ep.ctl.target),
                                                    self.failed, frame=frame)
        finally:
            ep.log.stop("plan", ep.ctl, add=True)
        k = match_block(wc, T_est)
        if k == 0:
            att.target = FalseTarget(0, ests[j].obj_id)
            raise EpisodeFailed(Failure.POSE_ERROR)
        block = wc.blocks[k - 1].block
        att.target = self.tool.target(k, block, block.obj_id == ests[j].obj_id, self.grasp)
        att.pose_error = pose_errors(block, T_est, wc.block_poses()[k - 1], cfg.scoring.pose_error_points)
        att.visib_fract = visible_fraction(ep, frame, k)
        self.tool.pick(ep, Plan(k, block, self.grasp, T_est, cat[ests[j].obj_id]), self.area,
                       self._away_shake(att, T_est), att)
        return True

    def _tally(self, att: Attempt) -> None:
        """After the attempt, the simulator's truth: the parts in the out-box (taken out of the scene) and those
        thrown out, and the attempt's verdict on its target."""
        wc = self.ep.wc
        gone, thrown = tally(wc, self.area, self.dest, self.left)
        for k in gone if self.dest.parks else ():
            park(wc, k)
        self.left = [k for k in self.left if k not in gone and k not in thrown]
        self.lost += thrown
        att.removed, att.thrown_out = gone, thrown
        target = att.target.instance if att.target is not None else 0
        if self.tray is not None and att.failure is None and target in gone:
            err, att.failure = self.tray.judge(target, wc.blocks[target - 1].block)
            att.place_error = err.to_json() if err is not None else None
            att.slot = self.tray.placing.slot if self.tray.placing is not None else None
            att.in_hand = self.tray.placing.in_hand if self.tray.placing is not None else None
        if att.failure is None and target not in gone:
            att.failure = Failure.DROP if target in self.left else Failure.MISPLACED
        if att.failure is None and [k for k in thrown if k != target]:
            att.failure = Failure.THROWN_OUT

    def _finish(self, att: Attempt, t0: float) -> None:
        _finish(self.rec, att, self.ep.ctl.sim_time - t0, self.n, self.left + self.lost, self.ep.cfg.scoring)


class _Leaving:
    """``dest`` that calls ``start()`` as the part, lifted clear of the tote, leaves for it."""

    def __init__(self, dest: Destination, start: Callable[[], None]):
        self.dest, self.start = dest, start

    def __getattr__(self, name: str):
        return getattr(self.dest, name)

    def deliver(self, plan: Plan, T_lift: np.ndarray, T_hold: np.ndarray, let_go: Callable[[], None]) -> None:
        self.start()
        self.dest.deliver(plan, T_lift, T_hold, let_go)


def _same_view(seen: list[tuple[int, np.ndarray]], before: list[tuple[int, np.ndarray]], tol: float = 1e-4
               ) -> bool:
    """Are the estimates ``seen`` ((obj_id, T_world_obj) each) those ``before`` (same objects, world poses within
    ``tol``: 0.1 mm, rotation entries 1e-4): the robot sees what it saw, though the arm settled a little differently
    at this look (``look_tol``, 0.01 rad a joint, turns the hand-eye calibration's error by a few micrometres)?"""
    return len(seen) == len(before) and all(
        i == j and np.allclose(a, b, atol=tol) for (i, a), (j, b) in zip(seen, before))


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
