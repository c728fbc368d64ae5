"""One grasp-and-place episode: scene, look, perceive, plan, pick, lift and carry, place, settle and score.

Episode ``i`` of a campaign with seed ``S`` draws everything random (block count, scene, perception noise,
place target) from ``SeedSequence([S, i])`` only, so its record never depends on the worker count.
The planner sees the blocks only through the perception provider's ``T_cam_obj`` estimates, mapped to
the world with the measured forward kinematics and the CALIBRATED camera mount:
``T_world_obj = T_world_gripper(q) @ T_gripper_cam @ T_cam_obj`` (the paper's T = T1 x T2).
Each phase is a function that fills in the episode's ``EpisodeRecord`` (``grasping.record``) and raises
``_Failure`` with the reason when the episode cannot go on. The task (``TrialConfig.task``, ``grasping.tasks``)
decides the scene, which estimates may be picked, where and at which yaw the block is set down (a turn
about the vertical while carrying it) and the verdict; in the stack task the arm first looks at the pad and
perceives the base through the same provider (its own seed, ``SeedSequence([S, i, 1])``).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from typing import Callable

import mujoco
import numpy as np

from posegrasp.catalog import PartType, catalog_by_id
from posegrasp.errors import UserError
from posegrasp.geometry import axis_angle_R, look_at_R, make_T, transform_points
from posegrasp.grasping.config import ControlConfig, ScoringConfig, TrialConfig, firm_hold
from posegrasp.grasping.controller import ArmController, SimulationError, robot_workcell
from posegrasp.grasping.grasps import Grasp, plan_grasps, surface_points
from posegrasp.grasping.perception import BASE_LOOK, PICK_LOOK, Estimate, PerceptionError, perceive, reads_labels
from posegrasp.grasping.provider_registry import make_provider
from posegrasp.grasping.record import BaseRecord, EpisodeRecord, EpisodeTimings, FalseTarget, PoseDeviation, Target
from posegrasp.grasping.support import rest_on_table
from posegrasp.grasping.task_scenes import kitting_scene, stack_scene
from posegrasp.grasping.tasks import (BASE_MOVED, MISALIGNED, NO_BASE, NO_UPRIGHT, PAD_TOP, WRONG_FACE, believed_upright, can_stack, kit_targets,
                                      kitting_verdict, stack_targets, stack_verdict)
from posegrasp.grasping.upright import match, standing_copies, upright_error, yaw_between
from posegrasp.sim.camera import CameraRenderer, Frame
from posegrasp.sim.scene import make_scene
from posegrasp.sim.workcell import HAND_CAMERA, Workcell

_EPS = 1e-9  # slack for sums of control periods and capped distances compared with their thresholds


@dataclass(frozen=True)
class EpisodeTask:
    """What one worker needs to run episode ``index`` (picklable)."""

    seed: int
    index: int
    perception: str
    cfg: TrialConfig
    T_gripper_cam: tuple[tuple[float, ...], ...]  # calibrated mount, row-major 4x4
    captures_only: bool = False  # only drive to the looks and capture (``--captures-only``): no perception, no grasp


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


@dataclass
class _Episode:
    """A running episode: its task, settled workcell, arm controller, record and phase log."""

    task: EpisodeTask
    wc: Workcell
    ctl: ArmController
    rec: EpisodeRecord
    log: _Log
    on_capture: Callable[[Workcell, Frame, int], None] | None = None  # gets each capture and its im_id
    camera: CameraRenderer | None = None  # the hand camera's renderer, made at the first capture (stack has two)

    @property
    def cfg(self) -> TrialConfig:
        return self.task.cfg


@dataclass(frozen=True)
class _Plan:
    """The chosen grasp on scene block ``k`` (1-based) and that block's estimated, levelled ``T_world_obj``
    and estimated type ``est_block`` (``block`` is its true type)."""

    k: int
    block: PartType
    grasp: Grasp
    T_world_obj: np.ndarray
    est_block: PartType | None = None

    def height_range(self) -> tuple[float, float]:
        """Bottom and top (world z, m) of the block at its estimated pose."""
        z = transform_points(self.T_world_obj, self.block.vertices)[:, 2]
        return float(z.min()), float(z.max())


@dataclass(frozen=True)
class _Goal:
    """Where the block is set down: its centre over ``xy`` (world, m), turned by ``yaw`` (rad) about the
    vertical while carried, its bottom onto a surface at height ``surface_z`` (m)."""

    xy: np.ndarray
    yaw: float = 0.0
    surface_z: float = PAD_TOP


@dataclass(frozen=True)
class _Base:
    """The stack task's base: its scene instance, true start pose and the perceived type and levelled pose."""

    k: int
    T_start: np.ndarray
    block: PartType | None = None
    T_est: np.ndarray | None = None


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


def pose_errors(block: PartType, T_est: np.ndarray, T_gt: np.ndarray, n_points: int = 500) -> PoseDeviation:
    """Translation (m), rotation (deg), ADD and ADD-S (m, over ``n_points`` surface samples) of an estimate
    ``T_est`` against ``T_gt`` (both world_obj); ``err`` is ADD-S for symmetric blocks, else ADD."""
    from posegrasp.perception.metrics import add, adds, rotation_error_deg, translation_error

    pts = surface_points(block, n_points)
    a = add(T_est[:3, :3], T_est[:3, 3], T_gt[:3, :3], T_gt[:3, 3], pts)
    s = adds(T_est[:3, :3], T_est[:3, 3], T_gt[:3, :3], T_gt[:3, 3], pts)
    symmetric = bool(block.symmetries_discrete or block.symmetries_continuous)
    return PoseDeviation(translation_error(T_est[:3, 3], T_gt[:3, 3]), rotation_error_deg(T_est[:3, :3], T_gt[:3, :3]),
                     a, s, "ADD-S" if symmetric else "ADD", s if symmetric else a)


def _match(wc: Workcell, T_world_obj: np.ndarray) -> int:
    """The scene block (1-based) an estimate refers to: the one whose centre is nearest the estimated centre,
    if within that block's diameter, else 0 (a false detection). The estimate's class may be wrong: the
    robot then grasps with the wrong model, as a real one would (evaluation only)."""
    d = [float(np.linalg.norm(T[:3, 3] - T_world_obj[:3, 3])) for T in wc.block_poses()]
    k = int(np.argmin(d))
    return k + 1 if d[k] <= wc.blocks[k].block.diameter else 0


def _yaw(T: np.ndarray) -> float:
    return float(np.arctan2(T[1, 0], T[0, 0]))


def _choose(wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray, yaw_now: float,
            accept: Callable[[PartType, np.ndarray], bool] | None = None) -> tuple[int, Grasp, np.ndarray] | None:
    """Target estimate index, its best reachable grasp and estimated ``T_world_obj`` (levelled by
    ``rest_on_table``), among the estimates ``accept(block, T_world_obj)`` allows (all without it); None if
    none is feasible; ``_Failure(NO_UPRIGHT)`` if it allows none."""
    g_cfg = cfg.grasp
    cat = catalog_by_id(wc.cfg.objects)
    poses = [rest_on_table(cat[e.obj_id], T_world_cam @ e.T_cam_obj, cfg.rest) for e in ests]
    clouds = [transform_points(T, surface_points(cat[e.obj_id], g_cfg.neighbour_points)) for e, T in zip(ests, poses)]
    targets = [j for j, (e, T) in enumerate(zip(ests, poses)) if accept is None or accept(cat[e.obj_id], T)]
    if not targets:
        raise _Failure(NO_UPRIGHT)
    options = []
    for j in targets:
        e, T = ests[j], poses[j]
        others = [c for i, c in enumerate(clouds) if i != j]
        nb = np.concatenate(others) if others else np.zeros((0, 3))
        for g in plan_grasps(cat[e.obj_id], T, nb, g_cfg, yaw_now, yaw_stable=firm_hold(cfg))[
                :g_cfg.grasps_per_block]:
            options.append((g.score + g_cfg.detection_weight * e.score, j, g))
    options.sort(key=lambda o: -o[0])
    ik = robot_workcell(wc.cfg)
    for _, j, g in options[:g_cfg.ik_checks]:
        pre = g.T_world_gripper.copy()
        pre[2, 3] += g_cfg.pregrasp_height
        q, dp, _ = ik.solve_gripper_ik(pre, wc.arm_q)
        if dp < g_cfg.reach_tol:
            q, dp, _ = ik.solve_gripper_ik(g.T_world_gripper, q)
        if dp < g_cfg.reach_tol:
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
    """The episode's settled scene for its task (settled with the scene defaults), then the trial's contact
    and solver settings (the tasks that hold firmly, ``config.firm_hold``: noslip and sleeping islands)."""
    if cfg.task == "kitting":
        wc = kitting_scene(cfg, scene_seed, n_blocks)
    elif cfg.task == "stack":
        wc = stack_scene(cfg, scene_seed, n_blocks)
    else:
        wc = make_scene(scene_seed, n_blocks, cfg.scene).workcell
    for name in ("table", "place_pad"):  # solmix: their contacts with the blocks take their solref
        g = wc.model.geom(name).id
        wc.model.geom_solref[g, 0], wc.model.geom_solmix[g] = cfg.support_timeconst, 1e3
    wc.model.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC if cfg.elliptic_cones else mujoco.mjtCone.mjCONE_PYRAMIDAL
    wc.model.opt.impratio = cfg.impratio
    if firm_hold(cfg):
        wc.model.opt.noslip_iterations = cfg.pose_noslip_iterations
        if cfg.pose_sleep:
            wc.model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_SLEEP)
            wc.model.opt.sleep_tolerance = cfg.pose_sleep_tolerance
    return wc


def drive_to_look(wc: Workcell, cfg: ControlConfig, q: np.ndarray | None = None) -> bool:
    """Drive the arm to the look pose (or the joint angles ``q``); False if it does not get there."""
    return wc.drive_arm(_look_q(wc) if q is None else q, tol=cfg.look_tol, timeout=cfg.look_timeout,
                        gain=cfg.look_gain)


@functools.lru_cache(maxsize=4)
def pad_look_q(wc_cfg, height: float) -> np.ndarray:
    """Joint angles putting the hand camera ``height`` (m) above the place pad's centre, looking down."""
    robot = robot_workcell(wc_cfg)
    T = make_T(look_at_R(np.array([0.0, 0.0, -1.0]), up_hint=np.array([1.0, 0.0, 0.0])),
               (*wc_cfg.place_area.center, height))
    q, dp, dr = robot.solve_camera_ik(T, robot.look_q)
    if dp > 1e-3 or dr > 1e-2:
        raise UserError(f"the pad look pose at stack.look_height {height} m is unreachable (residual {dp:.4f} m); "
                        "set a lower stack.look_height")
    return q


def capture_look(wc: Workcell) -> Frame:
    """The hand camera's frame (RGB-D, mask, ground truth) at the arm's current pose."""
    cam = CameraRenderer.from_config(wc, HAND_CAMERA, wc.cfg.hand_camera, wc.cfg.render)
    frame = cam.capture()
    cam.close()
    return frame


def run_episode(task: EpisodeTask, on_capture: Callable[[Workcell, Frame, int], None] | None = None
                ) -> tuple[EpisodeRecord, EpisodeTimings]:
    """Run one episode; returns its record (deterministic) and the wall-clock and CPU timings of its phases
    (which vary run to run). ``on_capture(workcell, frame, im_id)`` sees every frame the hand camera captures for
    perception, as it is taken (``grasping.captures``). With ``task.captures_only`` the episode stops after its
    last capture and its record judges nothing."""
    cfg = task.cfg
    n_blocks, scene_seed, percept_seed, place_offset = episode_draws(task)
    rec = EpisodeRecord(task.index, task.seed, scene_seed, n_blocks, task.perception,
                        task=None if cfg.task == "pick-place" else cfg.task)
    log = _Log()
    log.start(None)
    try:
        wc = episode_workcell(cfg, scene_seed, n_blocks)
        rec.blocks = [inst.block.name for inst in wc.blocks]
        log.stop("scene", None)
        ctl = ArmController(wc, cfg.control, _look_q(wc))
        ep = _Episode(task, wc, ctl, rec, log, on_capture)
        try:
            _execute(ep, percept_seed, place_offset)
        finally:
            if ep.camera is not None:
                ep.camera.close()
    except _Failure as f:
        rec.failure = f.reason
    except PerceptionError as e:
        rec.failure, rec.perception_error = "perception error", str(e)
    except SimulationError:  # unstable physics, or a scene that never settles (SceneUnsettled)
        rec.failure = "simulation error"
    _judge(rec, cfg.scoring)
    rec.sim_time = round(sum(log.sim.values()), 3)
    rec.phases = log.sim
    return rec, EpisodeTimings(task.index, log.wall, log.cpu)


def _judge(rec: EpisodeRecord, s_cfg: ScoringConfig) -> None:
    """Set the outcome; a failure after a grasp attempt on an estimate too far off counts as "pose error"."""
    if rec.failure is None:
        rec.outcome = "success"
    elif rec.failure not in ("no detection", "simulation error", *_TASK_REASONS) and rec.pose_error:
        if rec.pose_error.err > s_cfg.pose_error_frac * rec.target.diameter:
            rec.failure = "pose error"


_TASK_REASONS = (NO_UPRIGHT, NO_BASE, WRONG_FACE, MISALIGNED, BASE_MOVED)


def _look_q(wc: Workcell) -> np.ndarray:
    """Joint angles of the look pose, solved once per process on the robot-only model."""
    return robot_workcell(wc.cfg).look_q


def _execute(ep: _Episode, percept_seed: int, place_offset: np.ndarray) -> None:
    """The episode's phases after the scene, in order; raises ``_Failure`` at the first that fails."""
    name = ep.cfg.task
    base = _look_at_base(ep) if name == "stack" else None
    ests = _look_and_perceive(ep, percept_seed)
    if ep.task.captures_only:
        return
    plan = _plan(ep, ests, _acceptor(ep.cfg, base))
    target_xy = np.asarray(ep.wc.cfg.place_area.center) + place_offset
    goal = _goal(ep, plan, target_xy, base)
    _pick(ep, plan)
    T_place = _lift_and_carry(ep, plan, goal)
    _place(ep, plan, T_place)
    if name == "pick-place":
        _settle_and_score(ep, plan.k, target_xy)
    else:
        _settle_and_judge(ep, plan, target_xy, base)


def _acceptor(cfg: TrialConfig, base: _Base | None) -> Callable[[PartType, np.ndarray], bool] | None:
    """Which estimates the task may pick: kitting, those believed upright; stack, those believed upright that
    can stand on the perceived base; pick-and-place, all (None)."""
    if cfg.task == "kitting":
        return lambda b, T: believed_upright(b, T, cfg.kitting.belief_tol_deg)
    if cfg.task == "stack":
        return lambda b, T: can_stack(base.block, b) and believed_upright(b, T, cfg.stack.belief_tol_deg)
    return None


def _look_at_base(ep: _Episode) -> _Base:
    """Stack: look down at the pad, perceive the base through the provider and level its estimate onto the
    pad; records the base and its estimate's error."""
    wc, k = ep.wc, len(ep.wc.blocks)
    base = _Base(k, wc.block_poses()[k - 1].copy())
    ep.rec.base = BaseRecord(k, wc.blocks[k - 1].block.name)
    if not drive_to_look(wc, ep.cfg.control, pad_look_q(wc.cfg, ep.cfg.stack.look_height)):
        raise _Failure("timeout")
    ep.log.stop("look_base", ep.ctl)
    seed = int(np.random.default_rng(np.random.SeedSequence([ep.task.seed, ep.task.index, 1])).integers(2**31 - 1))
    frame = _capture(ep, BASE_LOOK)
    if ep.task.captures_only:
        return base
    ests = _perceive(ep, frame, seed, BASE_LOOK)
    T_world_cam = wc.gripper_pose() @ np.asarray(ep.task.T_gripper_cam)
    pad = wc.cfg.place_area
    cat = catalog_by_id(wc.cfg.objects)
    on_pad = [(float(np.linalg.norm(T[:2, 3] - pad.center)), e.obj_id, T)
              for e in ests for T in [T_world_cam @ e.T_cam_obj]
              if np.all(np.abs(T[:2, 3] - pad.center) <= np.add(pad.half_size, 0.02))]
    ep.log.stop("perceive_base", ep.ctl)
    if not on_pad:
        raise _Failure(NO_BASE)
    _, obj_id, T = min(on_pad, key=lambda o: o[0])
    block = cat[obj_id]
    T = rest_on_table(block, T, ep.cfg.rest, surface_z=PAD_TOP)
    ep.rec.base = BaseRecord(k, ep.rec.base.type, upright_error(block, T, base.T_start[None], standing=False))
    return _Base(k, base.T_start, block, T)


def _goal(ep: _Episode, plan: _Plan, target_xy: np.ndarray, base: _Base | None) -> _Goal:
    """Where and at which yaw the planner sets the block down: pick-and-place, over ``target_xy`` as it is;
    kitting, at the kit pose over ``target_xy``; stack, centred on the base's estimated top face, aligned with
    it. The yaw is the smallest turn, over the block's symmetries, that aligns the estimate with the target."""
    if ep.cfg.task == "pick-place":
        return _Goal(target_xy)
    block = plan.est_block
    if ep.cfg.task == "kitting":
        targets, surface = kit_targets(block, target_xy, PAD_TOP, ep.cfg.kitting), PAD_TOP
    else:
        targets = stack_targets(base.block, base.T_est, block)
        surface = float(transform_points(base.T_est, base.block.vertices)[:, 2].max())
    cands = standing_copies(block, plan.T_world_obj)
    i, j, _ = match(cands, targets)
    yaw = yaw_between(cands[i][:3, :3], targets[j][:3, :3])
    Rz = axis_angle_R(np.array([0.0, 0.0, 1.0]), yaw)
    xy = targets[j][:2, 3] - (Rz @ (cands[i][:3, 3] - plan.T_world_obj[:3, 3]))[:2]
    return _Goal(xy, yaw, surface)


def _capture(ep: _Episode, im_id: int) -> Frame:
    """The hand camera's frame at the arm's current pose, capture ``im_id`` of the episode (shown to
    ``ep.on_capture``)."""
    if ep.camera is None:
        ep.camera = CameraRenderer.from_config(ep.wc, HAND_CAMERA, ep.wc.cfg.hand_camera, ep.wc.cfg.render)
    frame = ep.camera.capture(images=_needs_images(ep))
    if ep.on_capture is not None:
        ep.on_capture(ep.wc, frame, im_id)
    return frame


def _needs_images(ep: _Episode) -> bool:
    """Do the episode's captures need RGB-D: for the capture hook (``--export-captures``) or a provider that
    sees images? The oracles read only the labels."""
    if ep.on_capture is not None:
        return True
    try:
        return not reads_labels(make_provider(ep.task.perception, ep.wc.cfg.objects))
    except UserError:  # _perceive reports it
        return True


def _perceive(ep: _Episode, frame: Frame, seed: int, im_id: int) -> list[Estimate]:
    """The provider's checked estimates of capture ``im_id`` of the episode (``perception.perceive``: a
    ``PerceptionError`` if it fails, hangs or returns what the planner cannot use)."""
    try:
        provider = make_provider(ep.task.perception, ep.wc.cfg.objects)
    except UserError as e:  # built in the main process before the campaign, but not in this worker
        raise PerceptionError(f"cannot build perception {ep.task.perception!r} in this worker: {e}") from None
    return perceive(provider, frame, seed, ep.task.index, im_id, known_ids=catalog_by_id(ep.wc.cfg.objects),
                    timeout_s=ep.cfg.perception_timeout_s)


def _look_and_perceive(ep: _Episode, percept_seed: int) -> list[Estimate]:
    """Drive to the look pose, capture the hand camera and ask the provider for pose estimates."""
    if not drive_to_look(ep.wc, ep.cfg.control):
        raise _Failure("timeout")
    ep.ctl.check_stable()
    ep.ctl.target = ep.wc.gripper_pose()
    ep.log.stop("look", ep.ctl)
    frame = _capture(ep, PICK_LOOK)
    if ep.task.captures_only:
        return []
    ests = _perceive(ep, frame, percept_seed, PICK_LOOK)
    ep.rec.detected = len(ests)
    ep.log.stop("perceive", ep.ctl)
    if not ests:
        raise _Failure("no detection")
    return ests


def _plan(ep: _Episode, ests: list[Estimate], accept: Callable[[PartType, np.ndarray], bool] | None) -> _Plan:
    """Choose the target (among the estimates ``accept`` allows) and its grasp; record the target and its
    estimate's pose error."""
    T_world_cam = ep.wc.gripper_pose() @ np.asarray(ep.task.T_gripper_cam)
    choice = _choose(ep.wc, ep.cfg, ests, T_world_cam, _yaw(ep.ctl.target), accept)
    ep.log.stop("plan", ep.ctl)
    if choice is None:
        raise _Failure("unreachable")
    j, grasp, T_world_obj_est = choice
    k = _match(ep.wc, T_world_obj_est)
    if k == 0:  # the chosen estimate is no block of the scene (a false detection)
        ep.rec.target = FalseTarget(0, ests[j].obj_id)
        raise _Failure("pose error")
    block = ep.wc.blocks[k - 1].block
    ep.rec.target = Target(k, block.name, block.obj_id == ests[j].obj_id, block.diameter, grasp.width,
                           grasp.clearance, grasp.support, grasp.tilt_deg)
    ep.rec.pose_error = pose_errors(block, T_world_obj_est, ep.wc.block_poses()[k - 1],
                                    ep.cfg.scoring.pose_error_points)
    if ep.rec.task:
        ep.rec.estimate_error = upright_error(block, T_world_obj_est, ep.wc.block_poses()[k - 1][None],
                                              standing=False)
    return _Plan(k, block, grasp, T_world_obj_est, catalog_by_id(ep.wc.cfg.objects)[ests[j].obj_id])


def _pick(ep: _Episode, plan: _Plan) -> None:
    """Pre-shape the fingers, move above the grasp, approach it and close the fingers on the block."""
    ctl, g_cfg, k = ep.ctl, ep.cfg.grasp, plan.k
    T_grasp = plan.grasp.T_world_gripper
    T_pre = T_grasp.copy()
    T_pre[2, 3] += g_cfg.pregrasp_height
    ctl.preshape(plan.grasp.width + g_cfg.finger_margin)
    if not ctl.move(T_pre):
        raise _Failure("collision" if ctl.unexpected_contacts(k) else "timeout")
    ep.log.stop("pregrasp", ctl)
    hit = False  # did the hand touch the table or another block on the way down?

    def watch_approach() -> None:
        nonlocal hit
        hit = hit or ctl.unexpected_contacts(k)

    ctl.monitor = watch_approach
    reached = ctl.move(T_grasp, speed=_approach_speed(ep.cfg))
    ctl.monitor = None
    ep.log.stop("approach", ctl)
    if not reached:
        raise _Failure("collision" if hit else "timeout")
    if ep.cfg.task == "stack":  # the fingers close on the block where the plan put them, not mid-sway
        ctl.settle(g_cfg.pose_settle_speed, g_cfg.pose_settle_time)
    if not ctl.close(k, wait_all=g_cfg.pose_finger_wait if firm_hold(ep.cfg) else 0):
        raise _Failure("collision" if hit else "slip")
    ep.log.stop("close", ctl)


@dataclass
class _HoldWatch:
    """Control-period monitor: for how long (s) block ``k`` has been lifted (bottom >= ``lift_min``) in the
    fingers, now and at most."""

    ep: _Episode
    k: int
    held: float = 0.0
    max_held: float = 0.0

    def __call__(self) -> None:
        wc, ctl = self.ep.wc, self.ep.ctl
        up = _block_bottom(wc, self.k) >= self.ep.cfg.scoring.lift_min and ctl.finger_contacts(self.k).any()
        self.held = self.held + self.ep.cfg.control.dt if up else 0.0
        self.max_held = max(self.max_held, self.held)


def _lift_and_carry(ep: _Episode, plan: _Plan, goal: _Goal) -> np.ndarray:
    """Lift the block, carry it above its place ``goal`` (turning it about the vertical by the goal's yaw) and
    hold it long enough to score the grasp (bottom >= lift_min for hold_time); returns the place pose
    ``T_world_gripper`` (the block's bottom place_gap above the goal's surface, its centre over the goal)."""
    ctl, g_cfg, s_cfg, k = ep.ctl, ep.cfg.grasp, ep.cfg.scoring, plan.k
    T_grasp = plan.grasp.T_world_gripper
    bottom_est, _ = plan.height_range()
    watch = _HoldWatch(ep, k)
    ctl.monitor = watch
    T_lift = T_grasp.copy()
    T_lift[2, 3] += g_cfg.lift_height - bottom_est
    lifted = ctl.move(T_lift)
    ep.log.stop("lift", ctl)
    T_place = T_lift.copy()
    offset = T_grasp[:2, 3] - plan.T_world_obj[:2, 3]  # the gripper from the block's centre, turned with it
    if goal.yaw:
        Rz = axis_angle_R(np.array([0.0, 0.0, 1.0]), goal.yaw)
        T_place[:3, :3] = Rz @ T_place[:3, :3]
        offset = Rz[:2, :2] @ offset
    T_place[:2, 3] = goal.xy + offset
    T_place[2, 3] = T_grasp[2, 3] + (goal.surface_z + _place_gap(ep.cfg) - bottom_est)
    T_above = T_place.copy()
    T_above[2, 3] += g_cfg.place_approach
    carried = ctl.move(T_above, speed=g_cfg.carry_speed)
    if watch.max_held < s_cfg.hold_time:
        ctl.hold(s_cfg.hold_time - watch.held)
    ctl.monitor = None
    ep.log.stop("carry", ctl)
    ep.rec.grasped = watch.max_held >= s_cfg.hold_time - _EPS
    if not ep.rec.grasped:
        raise _Failure("slip" if lifted else "timeout")
    if not carried or not ctl.finger_contacts(k).any():
        raise _Failure("drop" if not ctl.finger_contacts(k).any() else "timeout")
    return T_place


def _place_gap(cfg: TrialConfig) -> float:
    """How far above its surface (m) the block is brought before the slow, guarded descent."""
    return cfg.grasp.pose_place_gap if cfg.task == "stack" else cfg.grasp.place_gap


def _approach_speed(cfg: TrialConfig) -> float:
    """Peak speed (m/s) of the approach to the grasp and of the descent to the place pose."""
    return cfg.grasp.pose_approach_speed if cfg.task == "stack" else cfg.grasp.approach_speed


def _place(ep: _Episode, plan: _Plan, T_place: np.ndarray) -> None:
    """Lower the block onto the pad (slowly for the last part, until it touches), release it and retreat."""
    ctl, g_cfg, k = ep.ctl, ep.cfg.grasp, plan.k
    T_down = T_place.copy()
    T_down[2, 3] -= _place_gap(ep.cfg) + g_cfg.place_press
    if ep.cfg.task != "stack":
        ctl.move(T_place, speed=g_cfg.approach_speed)
    elif not ctl.move(T_place, speed=_approach_speed(ep.cfg), until=lambda: _block_supported(ep.wc, k)) or \
            not _block_supported(ep.wc, k):  # set down where the plan says, not mid-sway
        ctl.settle(g_cfg.pose_settle_speed, g_cfg.pose_settle_time)
    ctl.move(T_down, speed=g_cfg.place_descent_speed, until=lambda: _block_supported(ep.wc, k))
    if not ctl.finger_contacts(k).any():
        raise _Failure("drop")
    ctl.release(k, plan.grasp.width + g_cfg.finger_margin, g_cfg.release_time, g_cfg.release_push)
    _, top_est = plan.height_range()
    T_retreat = T_place.copy()  # the fingertips retreat_height above the block's top
    T_retreat[2, 3] += top_est - plan.grasp.T_world_gripper[2, 3] + g_cfg.fingertip_depth + g_cfg.retreat_height
    ctl.move(T_retreat)
    ep.log.stop("place", ctl)


def _wait_for_rest(ep: _Episode, k: int) -> bool:
    """Hold until block ``k`` has been at rest for rest_periods control periods (True) or rest_timeout passed."""
    ctl, wc, s_cfg, dt = ep.ctl, ep.wc, ep.cfg.scoring, ep.cfg.control.dt
    rest = 0
    for _ in range(int(s_cfg.rest_timeout / dt)):
        v = wc.block_speeds()[k - 1]
        rest = rest + 1 if v[0] < s_cfg.rest_speed[0] and v[1] < s_cfg.rest_speed[1] else 0
        if rest >= s_cfg.rest_periods:
            break
        ctl.hold(dt)
    return rest >= s_cfg.rest_periods


def _released(ep: _Episode, k: int) -> bool:
    """Is the hand at least hand_away from block ``k`` and no finger touching it?"""
    s_cfg = ep.cfg.scoring
    away = _hand_block_distance(ep.wc, k, ep.ctl, s_cfg.hand_away) >= s_cfg.hand_away - _EPS
    return away and not ep.ctl.finger_contacts(k).any()


def _settle_and_score(ep: _Episode, k: int, target_xy: np.ndarray) -> None:
    """Wait for block ``k`` to come to rest, then score the place: within place_tol of ``target_xy``, at
    rest, the hand away from it and no finger touching it."""
    at_rest = _wait_for_rest(ep, k)
    ep.log.stop("settle", ep.ctl)
    err = float(np.linalg.norm(ep.wc.block_poses()[k - 1][:2, 3] - target_xy))
    ep.rec.place_error = err
    ep.rec.placed = bool(err <= ep.cfg.scoring.place_tol and at_rest and _released(ep, k))
    if not ep.rec.placed:
        raise _Failure("misplaced")


def _settle_and_judge(ep: _Episode, plan: _Plan, target_xy: np.ndarray, base: _Base | None) -> None:
    """Kitting and stack: wait for the block to come to rest (stack: and stay there rest_time more), then
    judge its pose against the task's target (``grasping.tasks``); released and at rest, or "misplaced"."""
    k, wc = plan.k, ep.wc
    at_rest = _wait_for_rest(ep, k)
    if base is not None and at_rest:
        ep.ctl.hold(ep.cfg.stack.rest_time)
        v = wc.block_speeds()[k - 1]
        at_rest = bool(v[0] < ep.cfg.scoring.rest_speed[0] and v[1] < ep.cfg.scoring.rest_speed[1])
    ep.log.stop("settle", ep.ctl)
    T = wc.block_poses()
    if base is None:
        err, reason = kitting_verdict(plan.block, T[k - 1], target_xy, PAD_TOP, ep.cfg.kitting)
    else:
        base_block = wc.blocks[base.k - 1].block
        err, shift, reason = stack_verdict(base_block, base.T_start, T[base.k - 1], plan.block, T[k - 1],
                                           ep.cfg.stack)
        ep.rec.base = BaseRecord(base.k, base_block.name, ep.rec.base.estimate_error, shift)
    ep.rec.final_error, ep.rec.place_error = err, err.te
    released = _released(ep, k)
    ep.rec.placed = bool(reason is None and at_rest and released)
    if not ep.rec.placed:
        raise _Failure(reason or "misplaced")
