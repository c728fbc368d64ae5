"""One trial episode: the loop that runs it, and the phases a task strings together (``Episode``).

Episode ``i`` of a campaign with seed ``S`` draws everything random (block count, scene, perception noise,
place target) from ``SeedSequence([S, i])`` only, so its record never depends on the worker count.
The planner sees the blocks only through the perception provider's ``T_cam_obj`` estimates, mapped to
the world with the measured forward kinematics and the CALIBRATED camera mount:
``T_world_obj = T_world_gripper(q) @ T_gripper_cam @ T_cam_obj`` (the paper's T = T1 x T2).
The campaign's task (``TrialConfig.task``, ``grasping.tasks``) builds the scene and the record and runs the
episode (``Task.run``) by calling the ``Episode``'s phases; each fills in the episode's ``EpisodeRecord``
(``grasping.record``) and raises ``EpisodeFailed`` with the reason when the episode cannot go on.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import mujoco
import numpy as np

from posegrasp.catalog import catalog_by_id
from posegrasp.errors import DatasetError, SimulationError, UserError
from posegrasp.geometry import axis_angle_R, transform_points
from posegrasp.grasping.config import GraspConfig, ScoringConfig, TrialConfig, holds_firmly
from posegrasp.grasping.controller import ArmController
from posegrasp.grasping.grasps import Grasp, plan_grasps, surface_points
from posegrasp.grasping.hand import hand_of
from posegrasp.grasping.perception import PICK_LOOK, Estimate, PerceptionError, perceive, reads_labels
from posegrasp.grasping.provider_registry import make_provider
from posegrasp.grasping.record import EpisodeRecord, EpisodeTimings, FalseTarget, Failure, Target
from posegrasp.grasping.support import rest_on_table
from posegrasp.grasping.targets import (Plan, _look_q, blame, drive_to_look, gripper_yaw as _yaw,
                                        look_down_q, match_block as _match, pose_errors, reachable)
from posegrasp.grasping.tasks.base import EpisodeFailed, Goal, Pickable, SteadyConfig, Task
from posegrasp.sim.camera import CameraRenderer, Frame
from posegrasp.sim.config import CameraConfig
from posegrasp.sim.workcell import HAND_CAMERA, Workcell

_EPS = 1e-9  # slack for sums of control periods and capped distances compared with their thresholds


@dataclass(frozen=True)
class EpisodeJob:
    """What one worker needs to run episode ``index`` of a campaign of ``task`` (picklable): the task (the one
    ``cfg.task`` names, ``grasping.tasks.get_task``), the campaign's seed, provider and settings, the calibrated
    mount."""

    task: Task
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

    def stop(self, phase: str, ctl: ArmController | None, add: bool = False) -> None:
        """End ``phase`` now and start the next; ``add``: add to the phase's earlier times (a phase repeated
        in one episode, as bin picking's attempts repeat theirs)."""
        times = ((ctl.sim_time if ctl else 0.0) - self._t[0], time.perf_counter() - self._t[1],
                 time.process_time() - self._t[2])
        for log, t, digits in zip((self.sim, self.wall, self.cpu), times, (3, 4, 4)):
            log[phase] = round(t + (log.get(phase, 0.0) if add else 0.0), digits)
        self.start(ctl)


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


def _choose(wc: Workcell, cfg: TrialConfig, ests: list[Estimate], T_world_cam: np.ndarray, yaw_now: float,
            pickable: Pickable | None = None, unpickable: Failure = Failure.UNREACHABLE
            ) -> tuple[int, Grasp, np.ndarray] | None:
    """Target estimate index, its best reachable grasp and estimated ``T_world_obj`` (levelled by
    ``rest_on_table``), among the estimates ``pickable(block, T_world_obj)`` allows (all without it); None if
    none is feasible; ``EpisodeFailed(unpickable)`` if it allows none."""
    g_cfg = cfg.grasp
    cat = catalog_by_id(wc.cfg.objects)
    poses = [rest_on_table(cat[e.obj_id], T_world_cam @ e.T_cam_obj, cfg.rest) for e in ests]
    clouds = [transform_points(T, surface_points(cat[e.obj_id], g_cfg.neighbour_points)) for e, T in zip(ests, poses)]
    targets = [j for j, (e, T) in enumerate(zip(ests, poses)) if pickable is None or pickable(cat[e.obj_id], T)]
    if not targets:
        raise EpisodeFailed(unpickable)
    options = []
    for j in targets:
        e, T = ests[j], poses[j]
        others = [c for i, c in enumerate(clouds) if i != j]
        nb = np.concatenate(others) if others else np.zeros((0, 3))
        for g in plan_grasps(cat[e.obj_id], T, nb, g_cfg, yaw_now, yaw_stable=holds_firmly(cfg),
                             hand=hand_of(wc.cfg))[:g_cfg.grasps_per_block]:
            options.append((g.score + g_cfg.detection_weight * e.score, j, g))
    options.sort(key=lambda o: -o[0])
    for _, j, g in options[:g_cfg.ik_checks]:
        if reachable(wc, g_cfg, g.T_world_gripper):
            return j, g, poses[j]
    return None


def episode_draws(job: EpisodeJob) -> tuple[int, int, int, np.ndarray]:
    """Episode ``job.index``'s random draws: block count, scene seed, perception seed, place offset (m)."""
    cfg = job.cfg
    rng = np.random.default_rng(np.random.SeedSequence([job.seed, job.index]))
    lo, hi = job.task.blocks(cfg)
    n_blocks = int(rng.integers(lo, hi + 1))
    scene_seed, percept_seed = (int(v) for v in rng.integers(0, 2**31 - 1, size=2))
    place_offset = rng.uniform(-cfg.grasp.place_jitter, cfg.grasp.place_jitter, size=2)
    return n_blocks, scene_seed, percept_seed, place_offset


def check_draws(job: EpisodeJob, rec: EpisodeRecord, run_dir: Path) -> tuple[int, int, int, np.ndarray]:
    """``episode_draws(job)``, after checking that the record ``rec`` of the run in ``run_dir`` was drawn so
    (campaign seed, block count, scene seed): a DatasetError if not (an edited record, or other code)."""
    draws = episode_draws(job)
    if (rec.seed, rec.n_blocks, rec.scene_seed) != (job.seed, draws[0], draws[1]):
        raise DatasetError(f"episode {rec.episode} of {run_dir} does not re-simulate (seed {job.seed}, "
                           f"{draws[0]} blocks, scene seed {draws[1]} != recorded {rec.seed}, {rec.n_blocks}, "
                           f"{rec.scene_seed}): the record was edited or the code changed since the run; rerun the "
                           "trials into a new --out")
    return draws


def further_seed(job: EpisodeJob, j: int) -> int:
    """Episode ``job.index``'s seed for its ``j``-th further draw (j >= 1): from ``SeedSequence([S, i, j])``."""
    return int(np.random.default_rng(np.random.SeedSequence([job.seed, job.index, j])).integers(2**31 - 1))


def episode_workcell(task: Task, cfg: TrialConfig, scene_seed: int, n_blocks: int) -> Workcell:
    """The episode's settled scene for its ``task`` (``Task.scene``, settled with the scene defaults), then the
    trial's contact and solver settings (``trial_physics``)."""
    wc = task.scene(cfg, scene_seed, n_blocks, functools.partial(clear_grasp, cfg.grasp))
    trial_physics(wc, cfg)
    return wc


def trial_physics(wc: Workcell, cfg: TrialConfig) -> None:
    """Set the trial's contact and solver settings on a settled scene ``wc``: the supports' contact time constant,
    the friction cones, sleeping islands, and for the tasks that hold firmly (``config.holds_firmly``) noslip."""
    for name in ("table", "place_pad"):  # solmix: their contacts with the blocks take their solref
        g = wc.model.geom(name).id
        wc.model.geom_solref[g, 0], wc.model.geom_solmix[g] = cfg.support_timeconst, 1e3
    wc.model.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC if cfg.elliptic_cones else mujoco.mjtCone.mjCONE_PYRAMIDAL
    wc.model.opt.impratio = cfg.impratio
    if cfg.sleep:
        wc.model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_SLEEP)
        wc.model.opt.sleep_tolerance = cfg.sleep_tolerance
    if holds_firmly(cfg):
        wc.model.opt.noslip_iterations = cfg.firm_hold.noslip_iterations


def clear_grasp(g_cfg: GraspConfig, wc: Workcell, k: int) -> bool:
    """Does the grasp planner find scene block ``k`` (1-based) a yaw-stable grasp clear of its neighbours, at their
    true poses (a ``tasks.base.Graspable``)?"""
    poses = wc.block_poses()
    others = [transform_points(T, surface_points(inst.block, g_cfg.neighbour_points))
              for j, (inst, T) in enumerate(zip(wc.blocks, poses)) if j != k - 1]
    return bool(plan_grasps(wc.blocks[k - 1].block, poses[k - 1], np.concatenate([np.zeros((0, 3))] + others), g_cfg,
                            0.0, yaw_stable=True, hand=hand_of(wc.cfg)))


def capture_look(wc: Workcell) -> Frame:
    """The hand camera's frame (RGB-D, mask, ground truth) at the arm's current pose."""
    cam = CameraRenderer(wc, HAND_CAMERA, wc.cfg.hand_camera, wc.cfg.render)
    frame = cam.capture()
    cam.close()
    return frame


#: What sees every capture an episode makes for perception: (workcell, frame, im_id, camera name, its settings).
CaptureHook = Callable[[Workcell, Frame, int, str, CameraConfig], None]


def run_episode(job: EpisodeJob, on_capture: CaptureHook | None = None,
                on_step: Callable[[Workcell], None] | None = None) -> tuple[EpisodeRecord, EpisodeTimings]:
    """Run one episode; returns its record (deterministic) and the wall-clock and CPU timings of its phases
    (which vary run to run). ``on_capture`` (``CaptureHook``) sees every frame captured for perception, as it is
    taken (``grasping.captures``); ``on_step(workcell)`` runs after every physics step once
    the scene has settled (the report's films; it must not change the physics state). With ``job.captures_only``
    the episode stops after its last capture and its record judges nothing."""
    cfg = job.cfg
    n_blocks, scene_seed, percept_seed, place_offset = episode_draws(job)
    rec = job.task.new_record(job.index, job.seed, scene_seed, n_blocks, job.perception)
    log = _Log()
    log.start(None)
    try:
        wc = episode_workcell(job.task, cfg, scene_seed, n_blocks)
        rec.blocks = [inst.block.name for inst in wc.blocks]
        wc.on_step = on_step
        log.stop("scene", None)
        ctl = ArmController(wc, cfg.control, _look_q(wc))
        ep = Episode(job, wc, ctl, rec, log, percept_seed, place_offset, on_capture)
        try:
            job.task.run(ep)
        finally:
            for cam in ep.cameras.values():
                cam.close()
    except EpisodeFailed as f:
        rec.failure = f.reason
    except PerceptionError as e:
        rec.failure, rec.perception_error = Failure.PERCEPTION_ERROR, str(e)
    except SimulationError:  # unstable physics, or a scene that never settles (SceneUnsettled)
        rec.failure = Failure.SIMULATION_ERROR
    _judge(rec, cfg.scoring)
    rec.sim_time = round(sum(log.sim.values()), 3)
    rec.phases = log.sim
    return rec, EpisodeTimings(job.index, log.wall, log.cpu)


def _judge(rec: EpisodeRecord, s_cfg: ScoringConfig) -> None:
    """Set the outcome; a failure after a grasp attempt on an estimate too far off counts as "pose error"."""
    if rec.failure is None:
        rec.outcome = "success"
    else:
        rec.failure = blame(rec.failure, rec.pose_error, rec.target, s_cfg)


@dataclass
class Episode:
    """A running episode, as its task's ``run`` sees it (``grasping.tasks.base``): the worker's job, the settled
    workcell, the arm controller, the record and the phase log, the episode's draws, and its phases, each of which
    moves the simulated arm, fills in the record and raises ``EpisodeFailed`` when the episode cannot go on."""

    job: EpisodeJob
    wc: Workcell
    ctl: ArmController
    rec: EpisodeRecord
    log: _Log
    percept_seed: int  # the pick look's perception seed
    place_offset: np.ndarray  # the place point's offset (m) from the pad's centre
    on_capture: CaptureHook | None = None  # gets each capture, its im_id and its camera
    cameras: dict[str, CameraRenderer] = field(default_factory=dict)  # renderers by camera, made at their first capture

    @property
    def cfg(self) -> TrialConfig:
        return self.job.cfg

    @property
    def captures_only(self) -> bool:
        """Does the episode only drive to its looks and capture them (``--captures-only``)?"""
        return self.job.captures_only

    @property
    def place_xy(self) -> np.ndarray:
        """The episode's place point (world xy, m): the pad's centre plus the drawn offset."""
        return np.asarray(self.wc.cfg.place_area.center) + self.place_offset

    def seed_for(self, j: int) -> int:
        """A seed of the episode's own for its ``j``-th further draw (j >= 1): ``further_seed``."""
        return further_seed(self.job, j)

    def T_world_cam(self) -> np.ndarray:
        """The hand camera's pose in the world as the robot believes it: forward kinematics and the calibrated
        mount."""
        return self.wc.gripper_pose() @ np.asarray(self.job.T_gripper_cam)

    def look_down(self, xy, height: float, setting: str) -> bool:
        """Drive the arm so the hand camera looks straight down from ``height`` (m, the value of ``setting``)
        above the world point ``xy`` (m); False if it does not get there."""
        q = look_down_q(self.wc.cfg, (float(xy[0]), float(xy[1])), height, setting)
        return drive_to_look(self.wc, self.cfg.control, q)

    def capture(self, im_id: int, images: bool = False, camera: str = HAND_CAMERA, c: CameraConfig | None = None
                ) -> Frame:
        """The frame of ``camera`` (settings ``c``; default the hand camera and its settings) now, capture ``im_id``
        of the episode (shown to ``on_capture``); with its RGB-D when the capture hook or the provider needs it, or
        ``images``."""
        c = c or self.wc.cfg.hand_camera
        if (images := images or _needs_images(self)) and camera in self.cameras and not self.cameras[camera].antialias:
            self.cameras.pop(camera).close()
        if camera not in self.cameras:  # single-sampled while only masks are needed (the same masks, faster)
            self.cameras[camera] = CameraRenderer(self.wc, camera, c, self.wc.cfg.render, antialias=images)
        frame = self.cameras[camera].capture(images=images)
        if self.on_capture is not None:
            self.on_capture(self.wc, frame, im_id, camera, c)
        return frame

    def perceive(self, frame: Frame, seed: int, im_id: int) -> list[Estimate]:
        """The provider's checked estimates of capture ``im_id`` of the episode (``perception.perceive``: a
        ``PerceptionError`` if it fails, hangs or returns what the planner cannot use)."""
        try:
            provider = make_provider(self.job.perception, self.wc.cfg.objects, self.cfg.perception_timeout_s)
        except UserError as e:  # built in the main process before the campaign, but not in this worker
            raise PerceptionError(f"cannot build perception {self.job.perception!r} in this worker: {e}") from None
        return perceive(provider, frame, seed, self.job.index, im_id, known_ids=catalog_by_id(self.wc.cfg.objects),
                        timeout_s=self.cfg.perception_timeout_s)

    def look_and_perceive(self) -> list[Estimate]:
        """Drive to the look pose, capture the hand camera (``PICK_LOOK``) and ask the provider for pose estimates
        (none with ``captures_only``)."""
        if not drive_to_look(self.wc, self.cfg.control):
            raise EpisodeFailed(Failure.TIMEOUT)
        self.ctl.check_stable()
        self.ctl.target = self.wc.gripper_pose()
        self.log.stop("look", self.ctl)
        frame = self.capture(PICK_LOOK)
        if self.captures_only:
            return []
        ests = self.perceive(frame, self.percept_seed, PICK_LOOK)
        self.rec.detected = len(ests)
        self.log.stop("perceive", self.ctl)
        if not ests:
            raise EpisodeFailed(Failure.NO_DETECTION)
        return ests

    def plan(self, ests: list[Estimate], pickable: Pickable | None = None,
             unpickable: Failure = Failure.UNREACHABLE) -> Plan:
        """Choose the target (among the estimates ``pickable`` allows; ``unpickable`` if it allows none) and its
        grasp; record the target and its estimate's pose error."""
        choice = _choose(self.wc, self.cfg, ests, self.T_world_cam(), _yaw(self.ctl.target), pickable, unpickable)
        self.log.stop("plan", self.ctl)
        if choice is None:
            raise EpisodeFailed(Failure.UNREACHABLE)
        j, grasp, T_world_obj_est = choice
        k = _match(self.wc, T_world_obj_est)
        if k == 0:  # the chosen estimate is no block of the scene (a false detection)
            self.rec.target = FalseTarget(0, ests[j].obj_id)
            raise EpisodeFailed(Failure.POSE_ERROR)
        block = self.wc.blocks[k - 1].block
        self.rec.target = Target(k, block.name, block.obj_id == ests[j].obj_id, block.diameter, grasp.width,
                                 grasp.clearance, grasp.support, grasp.tilt_deg)
        self.rec.pose_error = pose_errors(block, T_world_obj_est, self.wc.block_poses()[k - 1],
                                          self.cfg.scoring.pose_error_points)
        return Plan(k, block, grasp, T_world_obj_est, catalog_by_id(self.wc.cfg.objects)[ests[j].obj_id])

    def pick(self, plan: Plan, steady: SteadyConfig | None = None) -> None:
        """Pre-shape the fingers, move above the grasp, approach it and close the fingers on the block (steadied
        by ``steady``, held firmly if the task does: ``config.holds_firmly``)."""
        ctl, g_cfg, k = self.ctl, self.cfg.grasp, plan.k
        T_grasp = plan.grasp.T_world_gripper
        T_pre = T_grasp.copy()
        T_pre[2, 3] += g_cfg.pregrasp_height
        ctl.preshape(plan.grasp.width + g_cfg.finger_margin)
        if not ctl.move(T_pre):
            raise EpisodeFailed(Failure.COLLISION if ctl.unexpected_contacts(k) else Failure.TIMEOUT)
        self.log.stop("pregrasp", ctl)
        hit = False  # did the hand touch the table or another block on the way down?

        def watch_approach() -> None:
            nonlocal hit
            hit = hit or ctl.unexpected_contacts(k)

        ctl.monitor = watch_approach
        reached = ctl.move(T_grasp, speed=steady.approach_speed if steady else g_cfg.approach_speed)
        ctl.monitor = None
        self.log.stop("approach", ctl)
        if not reached:
            raise EpisodeFailed(Failure.COLLISION if hit else Failure.TIMEOUT)
        if steady:  # the fingers close on the block where the plan put them, not mid-sway
            ctl.settle(steady.settle_speed, steady.settle_time)
        if not ctl.close(k, wait_all=self.cfg.firm_hold.finger_wait if holds_firmly(self.cfg) else 0):
            raise EpisodeFailed(Failure.COLLISION if hit else Failure.SLIP)
        self.log.stop("close", ctl)

    def lift_and_carry(self, plan: Plan, goal: Goal, steady: SteadyConfig | None = None) -> np.ndarray:
        """Lift the block, carry it above its place ``goal`` (turning it about the vertical by the goal's yaw) and
        hold it long enough to score the grasp (bottom >= lift_min for hold_time); returns the place pose
        ``T_world_gripper`` (the block's bottom the place gap above the goal's surface, its centre over the goal)."""
        ctl, g_cfg, s_cfg, k = self.ctl, self.cfg.grasp, self.cfg.scoring, plan.k
        T_grasp = plan.grasp.T_world_gripper
        bottom_est, _ = plan.height_range()
        watch = _HoldWatch(self, k)
        ctl.monitor = watch
        T_lift = T_grasp.copy()
        T_lift[2, 3] += g_cfg.lift_height - bottom_est
        lifted = ctl.move(T_lift)
        self.log.stop("lift", ctl)
        T_place = T_lift.copy()
        offset = T_grasp[:2, 3] - plan.T_world_obj[:2, 3]  # the gripper from the block's centre, turned with it
        if goal.yaw:
            Rz = axis_angle_R(np.array([0.0, 0.0, 1.0]), goal.yaw)
            T_place[:3, :3] = Rz @ T_place[:3, :3]
            offset = Rz[:2, :2] @ offset
        T_place[:2, 3] = goal.xy + offset
        T_place[2, 3] = T_grasp[2, 3] + (goal.surface_z + _place_gap(g_cfg, steady) - bottom_est)
        T_above = T_place.copy()
        T_above[2, 3] += g_cfg.place_approach
        carried = ctl.move(T_above, speed=g_cfg.carry_speed)
        if watch.max_held < s_cfg.hold_time:
            ctl.hold(s_cfg.hold_time - watch.held)
        ctl.monitor = None
        self.log.stop("carry", ctl)
        self.rec.grasped = watch.max_held >= s_cfg.hold_time - _EPS
        if not self.rec.grasped:
            raise EpisodeFailed(Failure.SLIP if lifted else Failure.TIMEOUT)
        if not carried or not ctl.finger_contacts(k).any():
            raise EpisodeFailed(Failure.DROP if not ctl.finger_contacts(k).any() else Failure.TIMEOUT)
        return T_place

    def place(self, plan: Plan, T_place: np.ndarray, steady: SteadyConfig | None = None) -> None:
        """Lower the block onto its surface (slowly for the last part, until it touches; with ``steady``, guarded
        and steadied), release it and retreat."""
        ctl, g_cfg, k = self.ctl, self.cfg.grasp, plan.k
        T_down = T_place.copy()
        T_down[2, 3] -= _place_gap(g_cfg, steady) + g_cfg.place_press
        if not steady:
            ctl.move(T_place, speed=g_cfg.approach_speed)
        elif not ctl.move(T_place, speed=steady.approach_speed, until=lambda: _block_supported(self.wc, k)) or \
                not _block_supported(self.wc, k):  # set down where the plan says, not mid-sway
            ctl.settle(steady.settle_speed, steady.settle_time)
        ctl.move(T_down, speed=g_cfg.place_descent_speed, until=lambda: _block_supported(self.wc, k))
        if not ctl.finger_contacts(k).any():
            raise EpisodeFailed(Failure.DROP)
        ctl.release(k, plan.grasp.width + g_cfg.finger_margin, g_cfg.release_time, g_cfg.release_push)
        _, top_est = plan.height_range()
        T_retreat = T_place.copy()  # the fingertips retreat_height above the block's top
        T_retreat[2, 3] += top_est - plan.grasp.T_world_gripper[2, 3] + g_cfg.fingertip_depth + g_cfg.retreat_height
        ctl.move(T_retreat)
        self.log.stop("place", ctl)

    def wait_for_rest(self, k: int) -> bool:
        """Hold until block ``k`` has been at rest for rest_periods control periods (True) or rest_timeout passed."""
        ctl, wc, s_cfg, dt = self.ctl, self.wc, self.cfg.scoring, self.cfg.control.dt
        rest = 0
        for _ in range(int(s_cfg.rest_timeout / dt)):
            v = wc.block_speeds()[k - 1]
            rest = rest + 1 if v[0] < s_cfg.rest_speed[0] and v[1] < s_cfg.rest_speed[1] else 0
            if rest >= s_cfg.rest_periods:
                break
            ctl.hold(dt)
        return rest >= s_cfg.rest_periods

    def released(self, k: int) -> bool:
        """Is the hand at least hand_away from block ``k`` and no finger touching it?"""
        s_cfg = self.cfg.scoring
        away = _hand_block_distance(self.wc, k, self.ctl, s_cfg.hand_away) >= s_cfg.hand_away - _EPS
        return away and not self.ctl.finger_contacts(k).any()


def _needs_images(ep: Episode) -> bool:
    """Do the episode's captures need RGB-D: for the capture hook (``--export-captures``) or a provider that
    sees images? The oracles read only the labels."""
    if ep.on_capture is not None:
        return True
    try:
        return not reads_labels(make_provider(ep.job.perception, ep.wc.cfg.objects, ep.cfg.perception_timeout_s))
    except UserError:  # Episode.perceive reports it
        return True


@dataclass
class _HoldWatch:
    """Control-period monitor: for how long (s) block ``k`` has been lifted (bottom >= ``lift_min``) in the
    fingers, now and at most."""

    ep: Episode
    k: int
    held: float = 0.0
    max_held: float = 0.0

    def __call__(self) -> None:
        wc, ctl = self.ep.wc, self.ep.ctl
        up = _block_bottom(wc, self.k) >= self.ep.cfg.scoring.lift_min and ctl.finger_contacts(self.k).any()
        self.held = self.held + self.ep.cfg.control.dt if up else 0.0
        self.max_held = max(self.max_held, self.held)


def _place_gap(g_cfg: GraspConfig, steady: SteadyConfig | None) -> float:
    """How far above its surface (m) the block is brought before the slow, guarded descent."""
    return steady.place_gap if steady else g_cfg.place_gap
