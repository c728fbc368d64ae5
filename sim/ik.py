"""Inverse kinematics of the arm with mink: joint angles that put a hand frame at a world pose.

Solved by iterating mink's differential IK (a QP per step, ``daqp``) on a robot-only copy of the
workcell model, so block joints never enter the problem. Used for named poses and viewpoints; the
closed-loop controller in ``grasping`` drives the real arm through its actuators.
"""

from __future__ import annotations

from ctypes import c_int
from typing import Sequence

import daqp
import mink
import mujoco
import numpy as np

from posegrasp.geometry import rotation_angle


def velocity(configuration: mink.Configuration, tasks: Sequence[mink.Task], dt: float, damping: float,
             limits: Sequence[mink.Limit]) -> np.ndarray:
    """``mink.solve_ik(configuration, tasks, dt, "daqp", damping=damping, limits=limits)``: the same QP
    (``mink.build_ik``) handed to DAQP as qpsolvers hands it, the same velocity (tangent space, per s), in a fifth less
    time (without qpsolvers' wrapper and mink's check of the joint limits, which only warns)."""
    qp = mink.build_ik(configuration, tasks, dt, damping, limits)
    m = 0 if qp.G is None else qp.G.shape[0]
    G, h = (qp.G, qp.h) if m else (np.zeros((0, qp.q.size)), np.zeros(0))
    x, _, exitflag, _ = daqp.solve(qp.P, qp.q, G, h, np.full(m, -1e30), np.zeros(m, dtype=c_int), primal_start=None)
    if exitflag <= 0:
        raise mink.NoSolutionFound("daqp")
    return x / dt


class ArmIK:
    """Pose IK for a site on the Jaco hand (e.g. the pinch site or the hand camera's site).

    The solution minimises ``||log(T_target^-1 T_site(q))||`` with joint-limit constraints, starting from
    ``q0``; a posture task pulls weakly toward ``q0`` to keep the solution near the start.
    """

    def __init__(self, robot_model: mujoco.MjModel, arm_qadr: np.ndarray):
        self.model = robot_model
        self.arm_qadr = arm_qadr
        self.configuration = mink.Configuration(robot_model)
        self.limits = [mink.ConfigurationLimit(robot_model)]

    def solve(self, site: str, T_world_site: np.ndarray, q0: np.ndarray, iters: int = 400,
              pos_tol: float = 1e-4, rot_tol: float = 1e-3) -> tuple[np.ndarray, float, float]:
        """Joint angles (6,) putting ``site`` at ``T_world_site``; also the residual position (m) and angle (rad)."""
        q = self.model.qpos0.copy()
        q[self.arm_qadr] = q0
        self.configuration.update(q)
        task = mink.FrameTask(site, "site", position_cost=1.0, orientation_cost=0.5, lm_damping=1e-3)
        task.set_target(mink.SE3.from_matrix(T_world_site))
        posture = mink.PostureTask(self.model, cost=1e-3)
        posture.set_target(q)
        dt = 0.05
        for _ in range(iters):
            v = velocity(self.configuration, [task, posture], dt, 1e-4, self.limits)
            self.configuration.integrate_inplace(v, dt)
            T = self.configuration.get_transform_frame_to_world(site, "site").as_matrix()
            dp = float(np.linalg.norm(T[:3, 3] - T_world_site[:3, 3]))
            dr = rotation_angle(T[:3, :3], T_world_site[:3, :3])
            if dp < pos_tol and dr < rot_tol:
                break
        q = self.configuration.q[self.arm_qadr].copy()
        free = self.model.jnt_limited[self.model.dof_jntid[self.arm_qadr]] == 0  # arm joints: qadr == dofadr
        q[free] = (q[free] + np.pi) % (2 * np.pi) - np.pi
        return q, dp, dr
