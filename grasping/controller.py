"""Closed-loop Cartesian control of the Jaco2 through its velocity actuators, with mink differential IK.

Every control period (``ControlConfig.dt``) the controller reads the MEASURED arm joints, solves one
mink QP (FrameTask on the pinch site, a weak PostureTask; configuration, joint-velocity and hand/table
collision-avoidance limits; ``daqp``) on a robot-only copy of the workcell, sends the resulting joint
velocities plus the gravity feed-forward to the actuators and steps the physics. Gripper poses
``T_world_gripper`` are the pinch site's (z = approach direction, x = across the fingers).
"""

from __future__ import annotations

import functools
from typing import Callable

import mink
import mujoco
import numpy as np

from posegrasp.errors import SimulationError
from posegrasp.grasping.config import ControlConfig
from posegrasp.geometry import make_T, rotation_angle
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.ik import velocity
from posegrasp.sim.workcell import GRIPPER_SITE, Workcell, wrap_angle

_SITE = f"jaco_arm/jaco_hand/{GRIPPER_SITE}"
#: ``wait_reached``: a hand slower than this (m/s) has stopped; where it lacks less than ``REACH_BAND`` times the
#: position tolerance (held off, not blocked), the tracked position moves on by ``REACH_GAIN`` of what it lacks each
#: control period.
STILL_SPEED, REACH_BAND, REACH_GAIN = 0.005, 2.0, 0.1
#: A locked grip (``ArmController.lock_grip``): rad/s of finger command per rad a finger is off its locked angle;
#: the share of its squeeze a finger keeps at least.
GRIP_GAIN, GRIP_KEEP = 8.0, 0.5
#: Robot bodies kept away from the table by the collision-avoidance limit (the base links never reach it).
_GUARDED_BODIES = ("b_4", "b_5", "b_6", "jaco_hand/hand", "jaco_hand/b_finger_1", "jaco_hand/b_finger_tip_1",
                   "jaco_hand/b_finger_2", "jaco_hand/b_finger_tip_2", "jaco_hand/b_finger_3",
                   "jaco_hand/b_finger_tip_3")


@functools.lru_cache(maxsize=4)
def robot_workcell(cfg: WorkcellConfig) -> Workcell:
    """A robot-only workcell (arm, hand, camera, table; no blocks) for IK, cached per process."""
    return Workcell(cfg)


def finger_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Per geom: finger number 1-3 for the finger geoms (knuckle and tip), 0 otherwise."""
    out = np.zeros(model.ngeom, dtype=np.int8)
    for i in range(model.ngeom):
        name = model.geom(i).name
        for f in (1, 2, 3):
            if name.endswith((f"finger_knuckle_{f}", f"finger_tip_{f}")):
                out[i] = f
    return out


def interpolate(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """Pose a fraction ``s`` in [0, 1] along the straight line (and the geodesic rotation) from T0 to T1."""
    R = mink.SO3.from_matrix(T0[:3, :3]).interpolate(mink.SO3.from_matrix(T1[:3, :3]), s).as_matrix()
    return make_T(R, (1 - s) * T0[:3, 3] + s * T1[:3, 3])


class ArmController:
    """Drives a workcell's arm along straight Cartesian segments and opens/closes the hand.

    ``monitor`` (if set) is called after every control period; ``sim_time`` is the simulated time (s).
    """

    def __init__(self, wc: Workcell, cfg: ControlConfig, q_posture: np.ndarray):
        self.wc, self.cfg = wc, cfg
        robot = robot_workcell(wc.cfg)
        m = self.model = robot.model
        self.r_arm_q, self.r_finger_q = robot.arm_qadr, robot.finger_qadr
        self.r_arm_v = robot.arm_dadr
        self.finger_range = m.jnt_range[[m.joint(n).id for n in robot.finger_joint_names]]
        self.configuration = mink.Configuration(m)
        self.q = m.qpos0.copy()
        self.task = mink.FrameTask(_SITE, "site", position_cost=1.0, orientation_cost=cfg.orientation_cost,
                                   gain=cfg.frame_gain, lm_damping=1e-3)
        self.posture = mink.PostureTask(m, cost=cfg.posture_cost)
        self.free = m.jnt_limited[[m.joint(n).id for n in robot.arm_joint_names]] == 0  # the arm's endless joints
        self.q_posture = self.q.copy()  # the look pose's arm angles, the model's own for the rest
        self.q_posture[self.r_arm_q] = q_posture
        self.free_q = self.r_arm_q[self.free]  # the endless joints' indices in ``q``
        self.pose_toward(None)
        guarded = [m.geom(i).name for i in range(m.ngeom)
                   if m.geom_contype[i] and any(m.body(m.geom_bodyid[i]).name == f"jaco_arm/{b}"
                                                for b in _GUARDED_BODIES)]
        vlim = 0.9 * wc.arm_velocity_limits()  # headroom for the gravity feed-forward within the ctrl range
        self.limits = [
            mink.ConfigurationLimit(m),
            mink.VelocityLimit(m, dict(zip(robot.arm_joint_names, vlim))),
            mink.CollisionAvoidanceLimit(m, [(guarded, ["table"])], minimum_distance_from_collisions=cfg.table_clearance,
                                         collision_detection_distance=0.03),
        ]
        self.nsub = max(1, round(cfg.dt / wc.model.opt.timestep))
        self.fingers = finger_geoms(wc.model)
        self.finger_dadr = np.array([wc.model.joint(n).dofadr[0] for n in wc.finger_joint_names])
        self.finger_cmd = np.zeros(len(wc.finger_numbers))  # finger velocity commands (rad/s), + closes
        self.finger_target: float | None = None  # pre-shape angle (rad) held by P control, or None
        self.finger_limit: float | None = None  # speed limit (rad/s) of that P control (default finger_speed)
        self.grip_hold: np.ndarray | None = None  # finger angles (rad) a locked grip holds (``lock_grip``)
        m = wc.model
        self.robot_geom = np.array([m.body(m.geom_bodyid[i]).name.startswith("jaco_arm/") for i in range(m.ngeom)])
        self.table_geom = m.geom("table").id
        self.target = wc.gripper_pose()
        self.monitor: Callable[[], None] | None = None

    # -- state -----------------------------------------------------------------------------------
    @property
    def sim_time(self) -> float:
        return float(self.wc.data.time)

    def check_stable(self) -> None:
        """Raise SimulationError on NaN state, runaway speeds or a MuJoCo instability warning."""
        d = self.wc.data
        if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            raise SimulationError("non-finite state")
        if np.abs(d.qvel).max() > self.cfg.max_speed:
            raise SimulationError(f"runaway velocity {np.abs(d.qvel).max():.1f}")
        for w in (mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_CONTACTFULL,
                  mujoco.mjtWarning.mjWARN_CNSTRFULL):
            if d.warning[int(w)].number > 0:
                raise SimulationError(f"MuJoCo warning {w.name}")

    def pose_error(self, T_target: np.ndarray) -> tuple[float, float]:
        """Position (m) and rotation (rad) error of the measured gripper pose from ``T_target``."""
        T = self.wc.gripper_pose()
        return float(np.linalg.norm(T[:3, 3] - T_target[:3, 3])), rotation_angle(T[:3, :3], T_target[:3, :3])

    def finger_contacts(self, k: int) -> np.ndarray:
        """(3,) bool: is finger 1, 2, 3 touching scene block ``k`` (1-based)?"""
        d = self.wc.data
        out = np.zeros(4, dtype=bool)
        if d.ncon:
            g = d.contact.geom[: d.ncon]
            inst = self.wc.geom_instance[g]
            fing = self.fingers[g]
            out[fing[:, 0][inst[:, 1] == k]] = True
            out[fing[:, 1][inst[:, 0] == k]] = True
        return out[1:]

    def finger_speed(self) -> float:
        """Largest finger joint speed (rad/s)."""
        return float(np.abs(self.wc.data.qvel[self.finger_dadr]).max())

    # -- control ---------------------------------------------------------------------------------
    def _period(self, T_target: np.ndarray) -> None:
        """One control period toward ``T_target``: measure, solve the IK QP, actuate, step the physics."""
        wc = self.wc
        self.q[self.r_arm_q] = wc.data.qpos[wc.arm_qadr]
        self.q[self.r_finger_q] = np.clip(wc.data.qpos[wc.finger_qadr], self.finger_range[:, 0], self.finger_range[:, 1])
        self.configuration.update(self.q)
        self._unwind_posture()
        self.task.set_target(mink.SE3.from_matrix(T_target))
        v = velocity(self.configuration, [self.task, self.posture], self.cfg.dt, 1e-3, self.limits)
        # Rounded: numpy's results can differ in the last bit with memory alignment, i.e. between processes;
        # the physics would amplify that, and episodes must not depend on which worker ran them.
        wc.command_arm(np.round(v[self.r_arm_v], 9) + wc.gravity_feedforward())
        if self.finger_target is not None:
            err = self.finger_target - wc.data.qpos[wc.finger_qadr]
            lim = self.finger_limit or self.cfg.finger_speed
            wc.data.ctrl[wc.finger_act] = np.clip(8.0 * err, -lim, lim)
        elif self.grip_hold is not None:
            back = GRIP_GAIN * (self.grip_hold - wc.data.qpos[wc.finger_qadr])
            wc.data.ctrl[wc.finger_act] = self.finger_cmd + np.maximum(back, -GRIP_KEEP * self.finger_cmd)
        else:
            wc.data.ctrl[wc.finger_act] = self.finger_cmd
        wc.step(self.nsub)
        self.check_stable()
        if self.monitor is not None:
            self.monitor()

    def pose_toward(self, q: np.ndarray | None) -> None:
        """Point the IK's posture term at the arm joint angles ``q`` (rad), or with None back at the look pose's."""
        qp = self.q_posture.copy()
        if q is not None:
            qp[self.r_arm_q] = q
        self.posture_q, self.posture_turns = qp, np.zeros(len(self.free_q))
        self.posture.set_target(qp)

    def _unwind_posture(self) -> None:
        """Keep the posture term's target for each endless joint within half a turn of the joint's angle, ``q_p -
        2 pi round((q_p - q) / 2 pi)``: the arm's angles are not wrapped, and a wrist wound whole turns (set-downs in a
        tray turn it on one way: -27 rad by an episode's end) would be pulled back by them against the hand's pose,
        the hand swinging a centimetre as it comes down. Within half a turn the target is left as set."""
        turns = np.round((self.posture_q[self.free_q] - self.q[self.free_q]) / (2.0 * np.pi))
        if not np.array_equal(turns, self.posture_turns):
            qp = self.posture_q.copy()
            qp[self.free_q] -= 2.0 * np.pi * turns
            self.posture.set_target(qp)
            self.posture_turns = turns

    def move(self, T_goal: np.ndarray, speed: float | None = None, until: Callable[[], bool] | None = None,
             reposture: bool = False, max_lag: float | None = None) -> bool:
        """Move the gripper along a straight segment from the current target to ``T_goal``.

        The reference follows a smooth (cubic) time law with peak speed ``speed`` (m/s, default from the
        config) and waits whenever the measured pose lags it by more than ``max_lag`` (m; the config's unless
        given: joint speed limits), so the hand stays on the line. True once the pose is within tolerance, False
        on timeout. If ``until()`` becomes true first, the hand stops where the reference is and the move returns
        True. With ``reposture``, a hand held off ``T_goal`` (a tilted goal far from the look pose, whose joint
        angles the posture term pulls the arm toward: 7 mm off at 38 deg) gets ``settle_timeout`` more with the
        posture term pointed at the IK's joint angles for ``T_goal`` from where the arm is, each endless joint's
        within half a turn of where it is (``pose_toward``; the caller points it back).
        """
        c = self.cfg
        T0 = self.target
        dist = float(np.linalg.norm(T_goal[:3, 3] - T0[:3, 3]))
        ang = rotation_angle(T0[:3, :3], T_goal[:3, :3])
        n = max(1, int(np.ceil(1.5 * max(dist / (speed or c.speed), ang / c.angular_speed) / c.dt)))
        budget = 3 * n + int(c.settle_timeout / c.dt)
        i, T_ref = 0, T0
        while i < n and budget > 0:
            dp, dr = self.pose_error(T_ref)
            if dp < (max_lag or c.max_lag) and dr < np.deg2rad(c.max_lag_deg):
                i += 1
                u = i / n
                T_ref = interpolate(T0, T_goal, 3 * u * u - 2 * u * u * u)
            self._period(T_ref)
            budget -= 1
            if until is not None and until():
                self.target = T_ref
                return True
        self.target = T_goal.copy()  # the controller's own: a caller's later change to T_goal does not move it
        if self.wait_reached(T_goal, max(budget * c.dt, c.settle_timeout)):
            return True
        if not reposture:
            return False
        now = self.wc.arm_q
        q, dp, _ = robot_workcell(self.wc.cfg).solve_gripper_ik(T_goal, now)
        if dp >= c.pos_tol:
            return False
        self.pose_toward(np.where(self.free, now + wrap_angle(q - now), q))  # an endless joint not wound a turn
        return self.wait_reached(T_goal, c.settle_timeout)

    def wait_reached(self, T_goal: np.ndarray, timeout: float) -> bool:
        """Keep tracking ``T_goal`` until within tolerance (True) or ``timeout`` simulated seconds (False). Where the
        hand has stopped just short of it (slower than ``STILL_SPEED``, within ``REACH_BAND`` tolerances) past half
        the timeout, the tracked position moves on by ``REACH_GAIN`` of what is missing each period (an integral
        action: in some arm poses the IK's posture term, which pulls toward the look pose, holds the hand a few
        millimetres off; a hand stopped by the table or a part, farther off, is not pushed on)."""
        c = self.cfg
        n = int(np.ceil(timeout / c.dt)) + 1
        T_ref, p = T_goal, self.wc.gripper_pose()[:3, 3]
        for i in range(n):
            dp, dr = self.pose_error(T_goal)
            if dp < c.pos_tol and dr < np.deg2rad(c.rot_tol_deg):
                return True
            p, p_prev = self.wc.gripper_pose()[:3, 3], p
            if 2 * i >= n and dp < REACH_BAND * c.pos_tol and np.linalg.norm(p - p_prev) < STILL_SPEED * c.dt:
                T_ref = T_ref.copy()
                T_ref[:3, 3] += REACH_GAIN * (T_goal[:3, 3] - p)
            self._period(T_ref)
        return False

    def settle(self, speed: float, timeout: float, periods: int = 3) -> bool:
        """Track the current target until the measured gripper position has moved slower than ``speed`` (m/s)
        for ``periods`` control periods in a row (True) or ``timeout`` simulated seconds passed (False): after a
        fast segment the arm sways by several millimetres, which a segment's ``pos_tol`` lets through."""
        still, p = 0, self.wc.gripper_pose()[:3, 3]
        for _ in range(int(np.ceil(timeout / self.cfg.dt))):
            self._period(self.target)
            p, p_prev = self.wc.gripper_pose()[:3, 3], p
            still = still + 1 if np.linalg.norm(p - p_prev) < speed * self.cfg.dt else 0
            if still >= periods:
                return True
        return False

    def null_offset(self, T: np.ndarray, speed: float, timeout: float, rounds: int = 2,
                    until: Callable[[], bool] | None = None) -> np.ndarray:
        """Settle at ``T`` (``settle(speed, timeout)``) and move the tracked target on by what the measured
        position lacks along world x and y, ``rounds`` times or until ``until()``; the xy shift (2,) (m, world)
        made. The arm settles a millimetre or two off its target, much the same nearby: a move that follows (a
        press, a set-down) takes the shift too."""
        off = np.zeros(2)
        for _ in range(rounds):
            self.settle(speed, timeout)
            if until is not None and until():
                break
            off += T[:2, 3] - self.wc.gripper_pose()[:2, 3]
            self.target[:2, 3] = T[:2, 3] + off
        return off

    def hold(self, duration: float, until: Callable[[], bool] | None = None) -> None:
        """Track the current target for ``duration`` simulated seconds, or until ``until()`` (asked after each
        control period) is true."""
        for _ in range(int(np.ceil(duration / self.cfg.dt))):
            self._period(self.target)
            if until is not None and until():
                return

    def preshape(self, opening: float, speed: float | None = None) -> None:
        """Move the fingers to (and hold them at) the angle leaving ``opening`` (m) between the fingertips."""
        self.finger_target = finger_angle_for_opening(self.wc.cfg, opening)
        self.finger_limit = speed
        self.grip_hold = None

    def lock_grip(self) -> None:
        """Hold a squeezing grip at the fingers' present angles until they next open or close.

        Equal squeezing torques on fingers that touch a part at unequal lever arms push it, slowly, toward the
        weaker finger: a lying cylinder crept 7 mm along the pinch axis between the tray's second look and its
        set-down. Locked, each finger's velocity command is its squeeze ``c`` plus
        ``max(GRIP_GAIN (q_lock - q), -GRIP_KEEP c)``: the finger the creep closes eases off (to no less than
        half its squeeze) until the two push alike."""
        self.grip_hold = self.wc.data.qpos[self.wc.finger_qadr].copy()

    def close(self, k: int, timeout: float = 1.5, wait_all: int = 0) -> bool:
        """Close the fingers on block ``k``: True once finger 1 and finger 2 or 3 have touched it for 3
        control periods in a row (a finger not touching it then stops, so it does not hook under the block);
        False when the fingers stall or time out without such a grip. With ``wait_all`` > 0 the fingers
        close up to that many periods longer, until all the hand's fingers touch (or they stall): on the 3-finger
        hand, finger 1 against finger 3 alone, 2.5 cm apart along the gripper y axis, is a couple that turns the
        block in the hand."""
        self.finger_target, self.grip_hold = None, None
        self.finger_cmd = np.full(len(self.wc.finger_numbers), self.cfg.finger_speed)
        mine = self.wc.finger_numbers - 1
        held = still = 0
        for _ in range(int(np.ceil(timeout / self.cfg.dt))):
            self._period(self.target)
            touch = self.finger_contacts(k)
            held = held + 1 if touch[0] and (touch[1] or touch[2]) else 0
            still = still + 1 if self.finger_speed() < 0.05 else 0
            if held >= 3 and (touch[mine].all() or held >= 3 + wait_all or still >= 5):
                self._balance_grip(touch[mine])
                return True
            if still >= 5:
                return False  # stalled without an opposing grip (closed on nothing or on something else)
        return False

    def _balance_grip(self, touch: np.ndarray) -> None:
        """Hold the grip with balanced squeezing torques: finger 1 against the fingers facing it (2 and 3, or 3)
        together; ``touch``: is each of the hand's fingers touching the block.

        At stall a velocity actuator pushes with ``kv * ctrl`` (clipped to its force range), so finger 1 gets
        the full torque and the touching fingers among 2 and 3 share it; a finger not touching stops. Equal
        commands would let fingers 2 and 3 push the block toward finger 1 until they reach their joint limits.
        """
        m, wc = self.wc.model, self.wc
        kv = m.actuator_gainprm[wc.finger_act, 0]
        full = m.actuator_forcerange[wc.finger_act, 1]
        n23 = max(1, int(touch[1:].sum()))
        torque = full / np.r_[1.0, np.full(len(touch) - 1, n23)] * touch
        self.finger_cmd = torque / kv

    def unexpected_contacts(self, k: int) -> bool:
        """Is the robot touching the table or a block other than ``k``?"""
        d = self.wc.data
        if not d.ncon:
            return False
        g = d.contact.geom[: d.ncon]
        inst = self.wc.geom_instance[g]
        other = (inst > 0) & (inst != k) | (g == self.table_geom)
        rob = self.robot_geom[g]
        return bool(np.any(rob[:, 0] & other[:, 1]) or np.any(rob[:, 1] & other[:, 0]))

    def release(self, k: int, opening: float, timeout: float, push: float = 0.0) -> bool:
        """Open the fingers to ``opening`` (m) until none has touched block ``k`` for 2 periods (True) or
        ``timeout`` (False), meanwhile pushing the hand ``push`` (m) down, so the curled fingertips, which
        often bear on a low block's top edges, slide off instead of dragging the block along."""
        self.preshape(opening, self.cfg.release_speed)
        T0, n = self.target, int(np.ceil(timeout / self.cfg.dt))
        free = for_periods(lambda: not self.finger_contacts(k).any())
        for i in range(n):
            T = T0.copy()
            T[:3, 3] += min(1.0, 2 * (i + 1) / n) * push * T0[:3, 2]
            self.target = T
            self._period(T)
            if free():
                return True
        return False


def for_periods(cond: Callable[[], bool], periods: int = 2) -> Callable[[], bool]:
    """A check asked once per control period: true once ``cond()`` has held ``periods`` periods in a row (a part
    off the fingers or the cup for that long has let go of them)."""
    run = 0

    def check() -> bool:
        nonlocal run
        run = run + 1 if cond() else 0
        return run >= periods

    return check


@functools.lru_cache(maxsize=4)
def _opening_table(cfg: WorkcellConfig) -> tuple[np.ndarray, np.ndarray]:
    """Finger angle (rad) against the gap (m) between the inner faces of fingertip 1 and the next (2; 3 on the
    2-finger hand)."""
    robot = robot_workcell(cfg)
    m = robot.model
    d = mujoco.MjData(m)
    d.qpos[robot.arm_qadr] = cfg.home_qpos
    tips = [m.geom(f"jaco_arm/jaco_hand/finger_tip_{f}") for f in robot.finger_numbers[:2]]
    verts = [m.mesh_vert[m.mesh_vertadr[g.dataid[0]]: m.mesh_vertadr[g.dataid[0]] + m.mesh_vertnum[g.dataid[0]]]
             for g in tips]
    lo, hi = m.jnt_range[m.joint(robot.finger_joint_names[0]).id]
    angles = np.linspace(lo, hi, 41)
    gaps = []
    for q in angles:
        d.qpos[robot.finger_qadr] = q
        mujoco.mj_kinematics(m, d)
        s = robot.gripper_site
        R_s, p_s = d.site_xmat[s].reshape(3, 3), d.site_xpos[s]
        x = [((v @ d.geom_xmat[g.id].reshape(3, 3).T + d.geom_xpos[g.id]) - p_s) @ R_s[:, 0] for g, v in zip(tips, verts)]
        gaps.append(x[0].min() - x[1].max())
    return angles, np.array(gaps)


def finger_angle_for_opening(cfg: WorkcellConfig, opening: float) -> float:
    """Finger joint angle (rad) leaving ``opening`` (m) between the fingertips (clipped to the joint range)."""
    angles, gaps = _opening_table(cfg)
    order = np.argsort(gaps)
    return float(np.interp(opening, gaps[order], angles[order]))


@functools.lru_cache(maxsize=64)
def open_finger_points(cfg: WorkcellConfig, opening_mm: int) -> np.ndarray:
    """(N, 3) vertices (m, gripper frame) of the three fingers' collision meshes, knuckles and tips, held at the
    angle leaving ``opening_mm`` (mm) between the fingertips: the hand as it comes down on a grasp. A mesh's
    extreme point along any direction is one of its vertices, so they give its exact distance to a plane."""
    robot = robot_workcell(cfg)
    m = robot.model
    d = mujoco.MjData(m)
    d.qpos[robot.arm_qadr] = cfg.home_qpos
    d.qpos[robot.finger_qadr] = finger_angle_for_opening(cfg, opening_mm / 1000.0)
    mujoco.mj_kinematics(m, d)
    s = robot.gripper_site
    R_s, p_s = d.site_xmat[s].reshape(3, 3), d.site_xpos[s]
    pts = []
    for g in np.flatnonzero((finger_geoms(m) > 0) & (m.geom_contype > 0) & (m.geom_dataid >= 0)):
        a, n = m.mesh_vertadr[m.geom_dataid[g]], m.mesh_vertnum[m.geom_dataid[g]]
        pts.append((m.mesh_vert[a:a + n] @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g] - p_s) @ R_s)
    return np.concatenate(pts)
