"""Bin picking's pick: the tool that picks (``Tool``: a fingered hand, ``Fingers``, or the suction cup, ``Cup``), how
each picks a part and hands it to its destination (``Destination``: the out-box, ``OutBox``, or the tray,
``tray.TrayPlace``), and the contact monitor that makes a protective stop.

The verdicts use the simulator's truth: a robot touching the tote's walls (a protective stop: "hit the wall"; so
is a hand that contacts turn ``tilt_stop_deg`` from the grasp's approach, "collision"), another part rising with the
target ("two parts lifted"); with the cup, a rim that does not seal on the part ("no seal") and a vacuum that lets
it go ("seal lost").
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np

from posegrasp.catalog import PartType
from posegrasp.geometry import axis_angle_R, transform_points
from posegrasp.grasping.config import holds_firmly
from posegrasp.grasping.controller import for_periods
from posegrasp.grasping.grasps import Grasp
from posegrasp.grasping.perception import Estimate
from posegrasp.grasping.record import Failure, Target
from posegrasp.grasping.suction_grasps import SuctionGrasp
from posegrasp.grasping.targets import Plan
from posegrasp.grasping.tasks.base import EpisodeFailed
from posegrasp.grasping.tasks.bin_pick.config import BinPickConfig
from posegrasp.grasping.tasks.bin_pick.planner import (CUP_PRESS, CUP_PRESS_SPEED, CUP_SETTLE_SPEED, CUP_SETTLE_TIME,
                                                       HYBRID_TIE, WALL_BACKOFF, WALL_BACKOFF_RISE,
                                                       WALL_BACKOFF_SPEED, HeapView, approach_end, choose_cup,
                                                       choose_part, off_the_walls, poorly_supported, pregrasp_height)
from posegrasp.grasping.tasks.bin_pick.record import Attempt
from posegrasp.grasping.tasks.bin_pick.roll import Roll, choose_roll, roll_off
from posegrasp.grasping.tasks.bin_pick.scene import Area
from posegrasp.grasping.tasks.bin_pick.squeeze import Squeeze, choose_squeeze
from posegrasp.sim.hybrid import extend
from posegrasp.sim.suction import Vacuum, seal_time
from posegrasp.sim.tote import WALLS, Tote
from posegrasp.sim.workcell import Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.episode import Episode
    from posegrasp.sim.camera import Frame



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


def _draw_off(ep: Episode, plan: Plan, area: Area) -> None:
    """Draw the held part of ``plan`` off the tote's walls it lies near (by its estimated pose): ``WALL_BACKOFF``."""
    off = off_the_walls(plan.est_block or plan.block, plan.T_world_obj, area.tote, WALL_BACKOFF) \
        if area.walls else np.zeros(3)
    if off.any():
        T = ep.ctl.target.copy()
        T[:3, 3] += off + [0.0, 0.0, WALL_BACKOFF_RISE]
        ep.ctl.move(T, speed=WALL_BACKOFF_SPEED)


def _watch(ep: Episode, area: Area, k: int) -> _Contacts:
    """The contact monitor of a pick of part ``k``: the tote's walls, its floor and the table."""
    m = ep.wc.model
    walls = np.array([m.geom(f"tote/{w}").id for w in WALLS]) if area.walls else np.zeros(0, int)
    floors = np.array([m.geom("table").id] + ([m.geom("tote/floor").id] if area.walls else []))
    return _Contacts(ep, walls, floors, k)


def pick_and_drop(ep: Episode, plan: Plan, area: Area, dest: Destination, att: Attempt) -> None:
    """Pick ``plan``'s part, draw it off the walls it lies near (``WALL_BACKOFF``; not a squeeze, which the wall
    holds), lift it clear of them and hand it to ``dest`` (the out-box or the tray) to let go of; marks
    ``att.grasped``; ``EpisodeFailed`` when the robot hits a wall, the floor on a failed grasp, the part slips or
    falls, or another part came up with it (after the drop). A neighbour that stops the hand short of the grasp
    (``_stopped_near``) does not end the attempt: the fingers close where the hand stopped."""
    ctl, cfg, k = ep.ctl, ep.cfg, plan.k
    g_cfg, b = cfg.grasp, cfg.bin_pick
    watch = _watch(ep, area, k)
    T_grasp = plan.grasp.T_world_gripper
    T_pre = T_grasp.copy()
    T_pre[2, 3] += pregrasp_height(cfg, area, T_grasp)
    opening = plan.grasp.width + b.finger_margin
    ctl.preshape(opening)
    ctl.monitor = watch
    try:
        if not ctl.move(T_pre, reposture=True):
            raise EpisodeFailed(Failure.TIMEOUT)
        watch.approach = T_grasp[:3, 2]
        squeeze = isinstance(plan.grasp, Squeeze)  # its hand leaning toward the wall: the posture term holds it off
        if not ctl.move(T_grasp, speed=g_cfg.approach_speed, reposture=squeeze,
                        max_lag=None if squeeze else b.approach_lag):
            if not _stopped_near(ep.wc.gripper_pose(), T_grasp, b) or watch.floor:
                raise EpisodeFailed(watch.blocked())
            ctl.target = ep.wc.gripper_pose()
        if not ctl.close(k, wait_all=cfg.firm_hold.finger_wait if holds_firmly(cfg) else 0):
            raise EpisodeFailed(Failure.COLLISION if watch.floor else Failure.SLIP)
        ep.log.stop("pick", ctl, add=True)
        ctl.pose_toward(None)  # the lift and the carry as ever
        start = _bottoms(ep.wc)
        T_hold = ep.wc.gripper_pose()
        if not isinstance(plan.grasp, Squeeze):  # a squeeze holds the part against its wall
            _draw_off(ep, plan, area)
        bottom_est, _ = plan.height_range()
        clear = max(area.top, dest.top_z) + b.wall_margin  # the part's bottom above both boxes' walls
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

        def let_go() -> None:
            if not ctl.finger_contacts(k).any():
                raise EpisodeFailed(Failure.DROP)
            ctl.release(k, opening, g_cfg.release_time)

        dest.deliver(plan, T_lift, T_hold, let_go)
        if double:
            raise EpisodeFailed(Failure.DOUBLE_PICK)
    finally:
        ctl.monitor = None
        ctl.pose_toward(None)


def pick_with_cup(ep: Episode, plan: Plan, area: Area, dest: Destination, att: Attempt, vacuum: Vacuum) -> None:
    """Pick ``plan``'s part with the suction cup (the hybrid hand's out, its fingers at the grasp's ``opening``):
    come down above the grasp, approach along its axis, take up the arm's offset (``ArmController.null_offset``: on a
    25 mm face a 20 mm cup has 2.5 mm to spare), press the cup on by ``CUP_PRESS`` of its stroke, switch the
    vacuum on (``EpisodeFailed`` "no seal" where the rim does not seal on the part's true surface), wait for the
    vacuum to build, draw a part lying near a wall off it (``WALL_BACKOFF``), lift clear of the walls with the hold
    model watching every control period ("seal lost"), and hand the part to ``dest`` (the out-box or the tray),
    which has the vacuum switched off (over the out-box the arm goes on once the part has left the cup); marks
    ``att.grasped``; "two parts lifted" after the drop when another part came up with it."""
    ctl, cfg, k, wc = ep.ctl, ep.cfg, plan.k, ep.wc
    g_cfg, b, s = cfg.grasp, cfg.bin_pick, wc.cfg.suction
    watch = _watch(ep, area, k)
    out_at = ctl.sim_time
    if wc.cfg.hand == "hybrid":  # the cup goes out, the fingers open or close round it as planned
        out_at += extend(wc, True)
        ctl.preshape(plan.grasp.opening)
    T_grasp = plan.grasp.T_world_gripper
    z = T_grasp[:3, 2]
    T_near, T_press = approach_end(plan.grasp), T_grasp.copy()
    T_press[:3, 3] += CUP_PRESS * s.stroke * z
    T_pre = T_near.copy()
    T_pre[2, 3] += pregrasp_height(cfg, area, T_near)

    def holding() -> None:
        watch()
        if not vacuum.check().held:
            raise EpisodeFailed(Failure.SEAL_LOST)

    ctl.monitor = watch
    try:
        if not ctl.move(T_pre, reposture=True) or not ctl.move(T_near, speed=g_cfg.approach_speed, reposture=True,
                                                               max_lag=b.approach_lag):
            raise EpisodeFailed(watch.blocked())
        watch.approach = z
        ctl.hold(max(0.0, out_at - ctl.sim_time))
        # the arm sways after its descent and stops a few mm off: still, the offset taken up, then press
        T_press[:2, 3] += ctl.null_offset(T_near, CUP_SETTLE_SPEED, CUP_SETTLE_TIME)
        ctl.move(T_press, speed=CUP_PRESS_SPEED)
        if watch.floor:
            raise EpisodeFailed(Failure.COLLISION)
        if not vacuum.on(k).sealed:
            raise EpisodeFailed(Failure.NO_SEAL)
        ctl.hold(seal_time(s))
        ep.log.stop("pick", ctl, add=True)
        ctl.pose_toward(None)  # the lift and the carry as ever
        start = _bottoms(wc)
        T_hold = wc.gripper_pose()
        _draw_off(ep, plan, area)
        bottom_est, _ = plan.height_range()
        T_lift = ctl.target.copy()
        T_lift[2, 3] += max(max(area.top, dest.top_z) + b.wall_margin - bottom_est, cfg.scoring.lift_min)
        ctl.monitor = holding
        ctl.move(T_lift)
        att.grasped = bool(vacuum.holding and _bottoms(wc)[k - 1] >= area.top + 0.5 * b.wall_margin)
        if not att.grasped:
            raise EpisodeFailed(Failure.SEAL_LOST if not vacuum.holding else Failure.TIMEOUT)
        rose = _bottoms(wc) - start
        rose[k - 1] = 0.0
        ep.log.stop("lift", ctl, add=True)
        watch.approach = None  # the carry turns the tool about the vertical with the arm's base

        def let_go() -> None:
            ctl.monitor = watch
            vacuum.off()
            if wc.cfg.hand == "hybrid":
                extend(wc, False)  # in again while the part falls and the arm goes back to the look
            ctl.hold(g_cfg.release_time, None if dest.keeps_pose else for_periods(lambda: not vacuum.touches(k)))

        dest.deliver(plan, T_lift, T_hold, let_go)
        if bool(np.any(rose > b.double_rise)):
            raise EpisodeFailed(Failure.DOUBLE_PICK)
    finally:
        ctl.monitor = None
        ctl.pose_toward(None)


class Destination(Protocol):
    """Where a picked part goes (``OutBox`` or ``tray.TrayPlace``): the height (m) of its top, which the carried
    part's bottom clears, and how it takes the part from the lifted hand."""

    #: Are the parts it holds taken out of the scene (parked) once counted?
    parks: bool
    #: Does a part's pose in the hand matter there (it is set down at a pose), so that a tool holds it as picked?
    keeps_pose: bool

    @property
    def top_z(self) -> float: ...

    def holds(self, T_world_obj: np.ndarray, block: PartType) -> bool:
        """Does a part of type ``block`` at ``T_world_obj`` (the simulator's truth) lie in it?"""

    def deliver(self, plan: Plan, T_lift: np.ndarray, T_hold: np.ndarray, let_go: Callable[[], None]) -> None: ...


class OutBox:
    """The out-box the parts are dropped into, in any pose."""

    parks, keeps_pose = True, False

    def __init__(self, ep: Episode, box: Tote):
        self.ep, self.box = ep, box

    @property
    def top_z(self) -> float:
        return self.box.top_z

    def holds(self, T_world_obj: np.ndarray, block: PartType) -> bool:
        """Every vertex of the part inside the out-box, within 5 mm."""
        return self.box.contains(transform_points(T_world_obj, block.vertices), 0.005)

    def deliver(self, plan: Plan, T_lift: np.ndarray, T_hold: np.ndarray, let_go: Callable[[], None]) -> None:
        """Carry the part from the lift pose ``T_lift`` over the out-box, the arm's base turning, and let go."""
        ctl = self.ep.ctl
        T_grasp = plan.grasp.T_world_gripper
        ctl.move(_swung(T_lift, np.asarray(self.box.center) + (T_grasp[:2, 3] - plan.T_world_obj[:2, 3])),
                 speed=self.ep.cfg.grasp.carry_speed)
        let_go()
        self.ep.log.stop("carry", ctl, add=True)


class Tool(Protocol):
    """What picks in a bin-picking attempt: how it chooses a part and its grasp from the estimates (``planner``),
    how it picks and drops it, what the record says of its grasp, and how it lets go after a failed pick."""

    def choose(self, wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray,
               heap: np.ndarray, yaw_now: float, failed: list[np.ndarray], frame: Frame | None = None
               ) -> tuple[int, object, np.ndarray]: ...

    def pick(self, ep: Episode, plan: Plan, area: Area, dest: Destination, att: Attempt) -> None: ...

    def target(self, k: int, block: PartType, class_ok: bool, grasp: object) -> Target: ...

    def let_go(self, ep: Episode) -> None: ...


class Fingers:
    """A fingered hand (``planner.choose_part``, ``pick_and_drop``)."""

    pick = staticmethod(pick_and_drop)

    @staticmethod
    def choose(wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray, heap: np.ndarray,
               yaw_now: float, failed: list[np.ndarray], frame: Frame | None = None) -> tuple[int, Grasp, np.ndarray]:
        return choose_part(wc, cfg, ests, T_world_cam, heap, yaw_now, failed)

    @staticmethod
    def target(k: int, block: PartType, class_ok: bool, g: Grasp) -> Target:
        return Target(k, block.name, class_ok, block.diameter, g.width, g.clearance, g.support, g.tilt_deg)

    @staticmethod
    def let_go(ep: Episode) -> None:
        """Open the hand wide."""
        ep.ctl.preshape(ep.cfg.grasp.max_width + ep.cfg.grasp.finger_margin, ep.ctl.cfg.release_speed)


class Cup:
    """The suction tool (``planner.choose_cup``, ``pick_with_cup``) and its vacuum."""

    def __init__(self, ep: Episode):
        self.vacuum = Vacuum(ep.wc)
        self.diameter = ep.wc.cfg.suction.diameter

    @staticmethod
    def choose(wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray, heap: np.ndarray,
               yaw_now: float, failed: list[np.ndarray], frame: Frame | None = None
               ) -> tuple[int, SuctionGrasp, np.ndarray]:
        return choose_cup(wc, cfg, ests, T_world_cam, heap, yaw_now, failed,
                          HeapView(wc, cfg, ests, T_world_cam, heap, frame))

    def pick(self, ep: Episode, plan: Plan, area: Area, dest: Destination, att: Attempt) -> None:
        pick_with_cup(ep, plan, area, dest, att, self.vacuum)

    def target(self, k: int, block: PartType, class_ok: bool, g: SuctionGrasp) -> Target:
        return Target(k, block.name, class_ok, block.diameter, self.diameter, g.clearance, g.seal_margin, g.tilt_deg)

    def let_go(self, ep: Episode) -> None:
        """Switch the vacuum off."""
        self.vacuum.off()


class Hybrid:
    """The hybrid hand: the 2-finger hand with a cup between its fingers (``sim.hybrid``), which picks each part
    with the cup or with the fingers. Both planners run on the estimates (``choose_cup``, ``choose_part``); the
    grasp on the higher part wins, the cup where both go for parts within ``HYBRID_TIE`` of each other's height (a
    suction pick neither reaches between neighbours nor needs a wall's room) or where the fingers' pinch is poorly
    supported (``min_support``): an ambidextrous policy. With
    ``cup_first`` (a destination that keeps the pose, the tray, without its second look), the cup wherever it has a
    grasp: it holds the part as the estimate has it, where closing fingers shift it (the second look sees the shift;
    with it the hand chooses as for the out-box, not leaving the parts only the fingers take for last). Where neither
    has a grasp, the fingers squeeze a part turned near a wall along the wall (``squeeze.choose_squeeze``;
    ``wall_squeeze``), or else roll a round part lying by a wall off it (``roll.choose_roll``; ``wall_roll``) for the
    next look to pick."""

    def __init__(self, ep: Episode, cup_first: bool = False):
        self.cup = Cup(ep)
        self.cup_first = cup_first

    def choose(self, wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray,
               heap: np.ndarray, yaw_now: float, failed: list[np.ndarray], frame: Frame | None = None
               ) -> tuple[int, object, np.ndarray]:
        found, why = [], []
        view = HeapView(wc, cfg, ests, T_world_cam, heap, frame)  # one view of the heap for both planners
        for bonus, choose in ((HYBRID_TIE, choose_cup), (0.0, choose_part)):
            if found and self.cup_first:
                break
            try:
                j, g, T = choose(wc, cfg, ests, T_world_cam, heap, yaw_now, failed, view)
            except EpisodeFailed as e:
                why.append(e.reason)
                continue
            found.append((not poorly_supported(g, cfg.bin_pick), view.tops[j] + bonus, j, g, T))
        if not found:
            for on, last_resort in ((cfg.bin_pick.wall_squeeze, choose_squeeze), (cfg.bin_pick.wall_roll, choose_roll)):
                if not on:
                    continue
                try:
                    return last_resort(wc, cfg, view, failed)
                except EpisodeFailed as e:
                    why.append(e.reason)
            raise EpisodeFailed(Failure.UNREACHABLE if Failure.UNREACHABLE in why else Failure.NOTHING_GRASPABLE)
        *_, j, g, T = max(found, key=lambda f: f[:2])
        return j, g, T

    def pick(self, ep: Episode, plan: Plan, area: Area, dest: Destination, att: Attempt) -> None:
        if isinstance(plan.grasp, SuctionGrasp):
            self.cup.pick(ep, plan, area, dest, att)
        elif isinstance(plan.grasp, Roll):
            roll_off(ep, plan.grasp, area, _watch(ep, area, plan.k))
        else:
            pick_and_drop(ep, plan, area, dest, att)

    def target(self, k: int, block: PartType, class_ok: bool, g: object) -> Target:
        return (self.cup if isinstance(g, SuctionGrasp) else Fingers).target(k, block, class_ok, g)

    def let_go(self, ep: Episode) -> None:
        """Switch the vacuum off, take the cup in and open the fingers wide."""
        self.cup.let_go(ep)
        extend(ep.wc, False)
        Fingers.let_go(ep)


def tool_of(ep: Episode, dest: Destination) -> Tool:
    """The tool of the episode's workcell (``WorkcellConfig.hand``) for the destination ``dest``."""
    hand = ep.wc.cfg.hand
    cup_first = dest.keeps_pose and not ep.cfg.bin_pick.tray.second_look
    return Cup(ep) if hand == "suction" else Hybrid(ep, cup_first) if hand == "hybrid" else Fingers()


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
