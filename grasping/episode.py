"""One grasp-and-place episode: scene, look, perceive, plan, pick, carry, place, score.

Episode ``i`` of a campaign with seed ``S`` draws everything random (block count, scene, perception noise,
place target) from ``SeedSequence([S, i])`` only, so its record never depends on the worker count.
The planner sees the blocks only through the perception provider's ``T_cam_obj`` estimates, mapped to
the world with the measured forward kinematics and the CALIBRATED camera mount:
``T_world_obj = T_world_gripper(q) @ T_gripper_cam @ T_cam_obj`` (the paper's T = T1 x T2).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import mujoco
import numpy as np

from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.controller import ArmController, SimulationError, robot_workcell
from posegrasp.grasping.grasps import Grasp, plan_grasps, surface_points
from posegrasp.grasping.perception import Estimate, make_provider
from posegrasp.grasping.render import EpisodeCamera
from posegrasp.grasping.support import rest_on_table
from posegrasp.catalog import BlockType, load_catalog
from posegrasp.geometry import invert, make_T, rotation_angle, transform_points
from posegrasp.sim.camera import Frame
from posegrasp.sim.scene import make_scene
from posegrasp.sim.workcell import HAND_CAMERA, Workcell

#: Failure reasons, in the order the summary lists them.
FAILURES = ("no detection", "pose error", "unreachable", "collision", "slip", "drop", "misplaced", "timeout",
            "simulation error")
_PAD_TOP = 0.003  # height of the place pad's surface (m)


@dataclass(frozen=True)
class EpisodeTask:
    """What one worker needs to run episode ``index`` (picklable)."""

    seed: int
    index: int
    perception: str
    cfg: TrialConfig
    T_gripper_cam: tuple[tuple[float, ...], ...]  # calibrated mount, row-major 4x4


@dataclass
class _Log:
    """Phase timings, filled as the episode runs: simulated, wall-clock and CPU seconds."""

    sim: dict[str, float] = field(default_factory=dict)
    wall: dict[str, float] = field(default_factory=dict)
    cpu: dict[str, float] = field(default_factory=dict)
    _t: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def start(self, ctl: ArmController | None) -> None:
        self._t = (ctl.sim_time if ctl else 0.0, time.perf_counter(), time.process_time())

    def stop(self, phase: str, ctl: ArmController | None) -> None:
        self.sim[phase] = round((ctl.sim_time if ctl else 0.0) - self._t[0], 3)
        self.wall[phase] = round(time.perf_counter() - self._t[1], 4)
        self.cpu[phase] = round(time.process_time() - self._t[2], 4)
        self.start(ctl)


class _Failure(Exception):
    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


def _block_bottom(wc: Workcell, k: int) -> float:
    """Lowest point (m) of scene block ``k`` in the world."""
    b = wc.blocks[k - 1].block
    return float(transform_points(wc.block_poses()[k - 1], b.vertices)[:, 2].min())


def _block_supported(wc: Workcell, k: int) -> bool:
    """Does block ``k`` touch the table, the place pad or another block?"""
    d = wc.data
    if not d.ncon:
        return False
    g = d.contact.geom[: d.ncon]
    inst = wc.geom_instance[g]
    static = np.isin(g, [wc.model.geom("table").id, wc.model.geom("place_pad").id])
    return bool(np.any((inst[:, 0] == k) & (static[:, 1] | (inst[:, 1] > 0) & (inst[:, 1] != k)))
                or np.any((inst[:, 1] == k) & (static[:, 0] | (inst[:, 0] > 0) & (inst[:, 0] != k))))


def _hand_block_distance(wc: Workcell, k: int, ctl: ArmController, dmax: float) -> float:
    """Smallest distance (m, capped at ``dmax``) between any hand/finger geom and block ``k``."""
    m, d = wc.model, wc.data
    hand = [i for i in range(m.ngeom) if ctl.robot_geom[i] and m.geom_contype[i]
            and "jaco_hand" in m.body(m.geom_bodyid[i]).name]
    block = [i for i in range(m.ngeom) if wc.geom_instance[i] == k and m.geom_contype[i]]
    best = dmax
    for a in hand:
        for b in block:
            best = min(best, mujoco.mj_geomDistance(m, d, a, b, dmax, None))
    return float(best)


def pose_errors(block: BlockType, T_est: np.ndarray, T_gt: np.ndarray) -> dict[str, float]:
    """Translation (m), rotation (deg), ADD and ADD-S (m) of an estimate; ``err`` is ADD-S for symmetric blocks."""
    from posegrasp.perception.metrics import add, adds, rotation_error_deg, translation_error

    pts = surface_points(block, 500)
    a = add(T_est[:3, :3], T_est[:3, 3], T_gt[:3, :3], T_gt[:3, 3], pts)
    s = adds(T_est[:3, :3], T_est[:3, 3], T_gt[:3, :3], T_gt[:3, 3], pts)
    symmetric = bool(block.symmetries_discrete or block.symmetries_continuous)
    return {"te": translation_error(T_est[:3, 3], T_gt[:3, 3]), "re_deg": rotation_error_deg(T_est[:3, :3], T_gt[:3, :3]),
            "add": a, "adds": s, "metric": "ADD-S" if symmetric else "ADD", "err": s if symmetric else a}


def _match(wc: Workcell, T_world_obj: np.ndarray) -> int:
    """The scene block (1-based) an estimate refers to: the one whose centre is nearest the estimated centre,
    if within that block's diameter, else 0 (a false detection). The estimate's class may be wrong: the
    robot then grasps with the wrong model, as a real one would (evaluation only)."""
    d = [float(np.linalg.norm(T[:3, 3] - T_world_obj[:3, 3])) for T in wc.block_poses()]
    k = int(np.argmin(d))
    return k + 1 if d[k] <= wc.blocks[k].block.diameter else 0


def _yaw(T: np.ndarray) -> float:
    return float(np.arctan2(T[1, 0], T[0, 0]))


def _choose(wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray,
            yaw_now: float) -> tuple[int, Grasp, np.ndarray] | None:
    """Target estimate index, its best reachable grasp and estimated ``T_world_obj`` (levelled by
    ``rest_on_table``); None if none is feasible."""
    cat = {b.obj_id: b for b in load_catalog().values()}
    poses = [rest_on_table(cat[e.obj_id], T_world_cam @ e.T_cam_obj, cfg.rest) for e in ests]
    clouds = [transform_points(T, surface_points(cat[e.obj_id], 300)) for e, T in zip(ests, poses)]
    options = []
    for j, (e, T) in enumerate(zip(ests, poses)):
        others = [c for i, c in enumerate(clouds) if i != j]
        nb = np.concatenate(others) if others else np.zeros((0, 3))
        for g in plan_grasps(cat[e.obj_id], T, nb, cfg.grasp, yaw_now)[:4]:
            options.append((g.score + 0.2 * e.score, j, g))
    options.sort(key=lambda o: -o[0])
    ik = robot_workcell(wc.cfg)
    for _, j, g in options[:8]:
        pre = g.T_world_gripper.copy()
        pre[2, 3] += cfg.grasp.pregrasp_height
        q, dp, _ = ik.solve_gripper_ik(pre, wc.arm_q)
        if dp < cfg.grasp.reach_tol:
            q, dp, _ = ik.solve_gripper_ik(g.T_world_gripper, q)
        if dp < cfg.grasp.reach_tol:
            return j, g, poses[j]
    return None


def episode_draws(task: EpisodeTask) -> tuple[int, int, int, np.ndarray]:
    """Episode ``task.index``'s random draws: block count, scene seed, perception seed, place offset (m)."""
    cfg = task.cfg
    rng = np.random.default_rng(np.random.SeedSequence([task.seed, task.index]))
    n_blocks = int(rng.integers(cfg.min_blocks, cfg.max_blocks + 1))
    scene_seed, percept_seed = (int(v) for v in rng.integers(0, 2**31 - 1, size=2))
    place_offset = rng.uniform(-cfg.grasp.place_jitter, cfg.grasp.place_jitter, size=2)
    return n_blocks, scene_seed, percept_seed, place_offset


def episode_workcell(cfg: TrialConfig, scene_seed: int, n_blocks: int) -> Workcell:
    """The episode's settled scene (settled with the scene defaults), then the trial's contact settings."""
    wc = make_scene(scene_seed, n_blocks, cfg.scene).workcell
    for name in ("table", "place_pad"):  # solmix: their contacts with the blocks take their solref
        g = wc.model.geom(name).id
        wc.model.geom_solref[g, 0], wc.model.geom_solmix[g] = cfg.support_timeconst, 1e3
    wc.model.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC if cfg.elliptic_cones else mujoco.mjtCone.mjCONE_PYRAMIDAL
    wc.model.opt.impratio = cfg.impratio
    return wc


def drive_to_look(wc: Workcell) -> bool:
    """Drive the arm to the look pose; False if it does not get there."""
    return wc.drive_arm(_look_q(wc), tol=0.01, timeout=4.0, gain=10.0)


def capture_look(wc: Workcell) -> Frame:
    """The hand camera's frame (RGB-D, mask, ground truth) at the arm's current pose."""
    cam = EpisodeCamera(wc, HAND_CAMERA, wc.cfg.hand_camera, wc.cfg.render)
    frame = cam.capture()
    cam.close()
    return frame


def run_episode(task: EpisodeTask) -> dict:
    """Run one episode; returns its JSON-ready record (deterministic), with the wall-clock and CPU
    timings of its phases (which vary run to run) under ``"_wall"``."""
    cfg = task.cfg
    n_blocks, scene_seed, percept_seed, place_offset = episode_draws(task)
    rec: dict = {"episode": task.index, "seed": task.seed, "scene_seed": scene_seed, "n_blocks": n_blocks,
                 "perception": task.perception, "blocks": [], "target": None, "outcome": "failure", "failure": None,
                 "grasped": False, "placed": False, "pose_error": None, "place_error": None, "detected": 0}
    log = _Log()
    log.start(None)
    ctl: ArmController | None = None
    try:
        wc = episode_workcell(cfg, scene_seed, n_blocks)
        rec["blocks"] = [inst.block.name for inst in wc.blocks]
        log.stop("scene", None)
        ctl = ArmController(wc, cfg.control, _look_q(wc))
        _execute(task, wc, ctl, rec, log, percept_seed, place_offset)
    except _Failure as f:
        rec["failure"] = f.reason
    except SimulationError:
        rec["failure"] = "simulation error"
    except RuntimeError as e:  # a scene that never settles
        if "did not come to rest" not in str(e):
            raise
        rec["failure"] = "simulation error"
    if rec["failure"] is None:
        rec["outcome"] = "success"
    elif rec["failure"] not in ("no detection", "simulation error") and rec["pose_error"]:
        if rec["pose_error"]["err"] > cfg.scoring.pose_error_frac * rec["target"]["diameter"]:
            rec["failure"] = "pose error"
    rec["sim_time"] = round(sum(log.sim.values()), 3)
    rec["phases"] = log.sim
    rec["_wall"] = {"wall_s": log.wall, "cpu_s": log.cpu}
    return _rounded(rec)


def _rounded(obj):
    if isinstance(obj, float):
        return round(obj, 6)
    if isinstance(obj, dict):
        return {k: _rounded(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_rounded(v) for v in obj]
    if isinstance(obj, np.generic):
        return _rounded(obj.item())
    return obj


def _look_q(wc: Workcell) -> np.ndarray:
    """Joint angles of the look pose, solved once per process on the robot-only model."""
    return robot_workcell(wc.cfg).look_q


def _execute(task: EpisodeTask, wc: Workcell, ctl: ArmController, rec: dict, log: _Log, percept_seed: int,
             place_offset: np.ndarray) -> None:
    cfg, g_cfg, s_cfg = task.cfg, task.cfg.grasp, task.cfg.scoring
    # -- look and perceive ---------------------------------------------------------------------------
    if not drive_to_look(wc):
        raise _Failure("timeout")
    ctl.check_stable()
    ctl.target = wc.gripper_pose()
    log.stop("look", ctl)
    frame = capture_look(wc)
    ests = make_provider(task.perception).estimate(frame, percept_seed)
    rec["detected"] = len(ests)
    log.stop("perceive", ctl)
    if not ests:
        raise _Failure("no detection")
    T_world_cam = wc.gripper_pose() @ np.asarray(task.T_gripper_cam)
    choice = _choose(wc, cfg, ests, T_world_cam, _yaw(ctl.target))
    log.stop("plan", ctl)
    if choice is None:
        raise _Failure("unreachable")
    j, grasp, T_world_obj_est = choice
    k = _match(wc, T_world_obj_est)
    if k == 0:  # the chosen estimate is no block of the scene (a false detection)
        rec["target"] = {"instance": 0, "obj_id": ests[j].obj_id}
        raise _Failure("pose error")
    block = wc.blocks[k - 1].block
    rec["target"] = {"instance": k, "type": block.name, "class_ok": block.obj_id == ests[j].obj_id,
                     "diameter": block.diameter, "grasp_width": grasp.width,
                     "clearance": grasp.clearance, "support": grasp.support, "tilt_deg": grasp.tilt_deg}
    rec["pose_error"] = pose_errors(block, T_world_obj_est, wc.block_poses()[k - 1])
    # -- pick ---------------------------------------------------------------------------------------
    T_grasp = grasp.T_world_gripper
    T_pre = T_grasp.copy()
    T_pre[2, 3] += g_cfg.pregrasp_height
    ctl.preshape(grasp.width + 0.03)
    if not ctl.move(T_pre):
        raise _Failure("collision" if ctl.unexpected_contacts(k) else "timeout")
    log.stop("pregrasp", ctl)
    hit = [False]  # did the hand touch the table or another block on the way down?

    def watch_approach() -> None:
        hit[0] = hit[0] or ctl.unexpected_contacts(k)

    ctl.monitor = watch_approach
    reached = ctl.move(T_grasp, speed=g_cfg.approach_speed)
    ctl.monitor = None
    log.stop("approach", ctl)
    if not reached:
        raise _Failure("collision" if hit[0] else "timeout")
    if not ctl.close(k):
        raise _Failure("collision" if hit[0] else "slip")
    log.stop("close", ctl)
    # -- lift, hold and carry (grasp success: bottom >= lift_min for hold_time) ------------------------
    z_est = transform_points(T_world_obj_est, block.vertices)[:, 2]
    bottom_est, top_est = float(z_est.min()), float(z_est.max())
    state = {"held": 0.0, "max_held": 0.0}

    def watch() -> None:
        up = _block_bottom(wc, k) >= s_cfg.lift_min and ctl.finger_contacts(k).any()
        state["held"] = state["held"] + cfg.control.dt if up else 0.0
        state["max_held"] = max(state["max_held"], state["held"])

    ctl.monitor = watch
    T_lift = T_grasp.copy()
    T_lift[2, 3] += g_cfg.lift_height - bottom_est
    lifted = ctl.move(T_lift)
    log.stop("lift", ctl)
    target_xy = np.asarray(wc.cfg.place_area.center) + place_offset
    T_place = T_lift.copy()  # the block's bottom place_gap above the pad, its centre over the target
    T_place[:2, 3] = target_xy + (T_grasp[:2, 3] - T_world_obj_est[:2, 3])
    T_place[2, 3] = T_grasp[2, 3] + (_PAD_TOP + g_cfg.place_gap - bottom_est)
    T_above = T_place.copy()
    T_above[2, 3] += g_cfg.place_approach
    carried = ctl.move(T_above, speed=g_cfg.carry_speed)
    if state["max_held"] < s_cfg.hold_time:
        ctl.hold(s_cfg.hold_time - state["held"])
    ctl.monitor = None
    log.stop("carry", ctl)
    rec["grasped"] = state["max_held"] >= s_cfg.hold_time - 1e-9
    if not rec["grasped"]:
        raise _Failure("slip" if lifted else "timeout")
    if not carried or not ctl.finger_contacts(k).any():
        raise _Failure("drop" if not ctl.finger_contacts(k).any() else "timeout")
    # -- place, release, retreat ----------------------------------------------------------------------
    T_down = T_place.copy()
    T_down[2, 3] -= g_cfg.place_gap + g_cfg.place_press  # then down slowly until the block touches the pad
    ctl.move(T_place, speed=g_cfg.approach_speed)
    ctl.move(T_down, speed=0.03, until=lambda: _block_supported(wc, k))
    if not ctl.finger_contacts(k).any():
        raise _Failure("drop")
    ctl.release(k, grasp.width + 0.03, g_cfg.release_time, g_cfg.release_push)
    T_retreat = T_place.copy()  # fingertips (1 cm below the pinch point) retreat_height above the block's top
    T_retreat[2, 3] += top_est - T_grasp[2, 3] + 0.012 + g_cfg.retreat_height
    ctl.move(T_retreat)
    log.stop("place", ctl)
    rest = 0
    for _ in range(int(s_cfg.rest_timeout / cfg.control.dt)):
        v = wc.block_speeds()[k - 1]
        rest = rest + 1 if v[0] < s_cfg.rest_speed[0] and v[1] < s_cfg.rest_speed[1] else 0
        if rest >= 3:
            break
        ctl.hold(cfg.control.dt)
    log.stop("settle", ctl)
    err = float(np.linalg.norm(wc.block_poses()[k - 1][:2, 3] - target_xy))
    rec["place_error"] = err
    away = _hand_block_distance(wc, k, ctl, s_cfg.hand_away) >= s_cfg.hand_away - 1e-9
    rec["placed"] = bool(err <= s_cfg.place_tol and rest >= 3 and away and not ctl.finger_contacts(k).any())
    if not rec["placed"]:
        raise _Failure("misplaced")
