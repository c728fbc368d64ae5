"""What the planner knows of a chosen target and how the arm reaches it, shared by the episode's phases
(``grasping.episode``) and bin picking (``grasping.bin_picking``): the ``Plan``, matching an estimate to a scene
block, its pose error, the IK reach check, the looks down, and blaming a failure on the pose estimate."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from posegrasp.catalog import PartType
from posegrasp.errors import UserError
from posegrasp.geometry import look_at_R, make_T, transform_points
from posegrasp.grasping.config import ControlConfig, GraspConfig, ScoringConfig
from posegrasp.grasping.controller import robot_workcell
from posegrasp.grasping.grasps import Grasp, surface_points
from posegrasp.grasping.record import NOT_POSE_ERRORS, FalseTarget, Failure, PoseDeviation, Target
from posegrasp.sim.workcell import Workcell


@dataclass(frozen=True)
class Plan:
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


def match_block(wc: Workcell, T_world_obj: np.ndarray) -> int:
    """The scene block (1-based) an estimate refers to: the one whose centre is nearest the estimated centre,
    if within that block's diameter, else 0 (a false detection). The estimate's class may be wrong: the
    robot then grasps with the wrong model, as a real one would (evaluation only)."""
    d = [float(np.linalg.norm(T[:3, 3] - T_world_obj[:3, 3])) for T in wc.block_poses()]
    k = int(np.argmin(d))
    return k + 1 if d[k] <= wc.blocks[k].block.diameter else 0


def gripper_yaw(T: np.ndarray) -> float:
    """Yaw (rad) of the x axis (the squeeze axis) of a pose ``T`` in the world xy plane."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def reachable(wc: Workcell, g_cfg: GraspConfig, T_grasp: np.ndarray) -> bool:
    """Does the arm's IK reach the grasp pose ``T_grasp`` (world gripper) and the pre-grasp above it
    (``reach_q``)?"""
    return reach_q(wc, g_cfg, T_grasp) is not None


def reach_q(wc: Workcell, g_cfg: GraspConfig, T_grasp: np.ndarray, pregrasp_height: float | None = None
            ) -> tuple[np.ndarray, np.ndarray] | None:
    """Joint angles (rad) of the pre-grasp ``pregrasp_height`` (m; default ``g_cfg.pregrasp_height``) above the grasp
    pose ``T_grasp`` (world gripper) and of the grasp, solved by the arm's IK from its current joint angles; None
    unless both are reached within ``reach_tol``."""
    ik = robot_workcell(wc.cfg)
    pre = T_grasp.copy()
    pre[2, 3] += g_cfg.pregrasp_height if pregrasp_height is None else pregrasp_height
    q_pre, dp, _ = ik.solve_gripper_ik(pre, wc.arm_q)
    if dp >= g_cfg.reach_tol:
        return None
    q, dp, _ = ik.solve_gripper_ik(T_grasp, q_pre)
    return (q_pre, q) if dp < g_cfg.reach_tol else None


def drive_to_look(wc: Workcell, cfg: ControlConfig, q: np.ndarray | None = None) -> bool:
    """Drive the arm to the look pose (or the joint angles ``q``); False if it does not get there."""
    return wc.drive_arm(_look_q(wc) if q is None else q, tol=cfg.look_tol, timeout=cfg.look_timeout,
                        gain=cfg.look_gain)


@functools.lru_cache(maxsize=8)
def look_down_q(wc_cfg, xy: tuple[float, float], height: float, setting: str, up: float = 1.0) -> np.ndarray:
    """Joint angles putting the hand camera ``height`` (m) above the world point ``xy`` (m), looking down, the
    image's up along world +x (``up`` 1) or -x (-1); a UserError naming the ``setting`` of the height if no joint
    angles do."""
    robot = robot_workcell(wc_cfg)
    T = make_T(look_at_R(np.array([0.0, 0.0, -1.0]), up_hint=np.array([up, 0.0, 0.0])), (*xy, height))
    q, dp, dr = robot.solve_camera_ik(T, robot.look_q)
    if dp > 1e-3 or dr > 1e-2:
        raise UserError(f"the look from {height} m above {tuple(xy)} ({setting}) is unreachable (residual "
                        f"{dp:.4f} m); set a lower {setting}")
    return q


def blame(failure: Failure, pose_error: PoseDeviation | None, target: Target | FalseTarget | None,
          s_cfg: ScoringConfig) -> Failure:
    """``failure``, or "pose error" when it came after a grasp attempt on an estimate farther off its block (ADD(-S))
    than ``pose_error_frac`` of the block's diameter."""
    if failure not in NOT_POSE_ERRORS and pose_error and pose_error.err > s_cfg.pose_error_frac * target.diameter:
        return Failure.POSE_ERROR
    return failure


def _look_q(wc: Workcell) -> np.ndarray:
    """Joint angles of the look pose, solved once per process on the robot-only model."""
    return robot_workcell(wc.cfg).look_q
