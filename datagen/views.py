"""Viewpoints the robot can really see from: camera poses sampled on a spherical cap over the clutter, solved with
IK, the arm set there (``Workcell.place_arm``: the scene is at rest, so the way there is not simulated) unless it
would touch the scene. Unreachable ones are counted, not used.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Iterator

import numpy as np

from posegrasp.datagen.config import ViewConfig
from posegrasp.geometry import axis_angle_R, look_at_R, make_T, rotation_angle
from posegrasp.sim.workcell import Workcell


@dataclass
class ViewStats:
    """Counts for one scene: candidate poses drawn, rejected as out of reach (no IK), IK residual too large,
    blocked (the arm or hand would touch the scene there), and views captured."""

    candidates: int = 0
    out_of_reach: int = 0
    unreachable: int = 0
    blocked: int = 0
    reached: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def shoulder_position(wc: Workcell) -> np.ndarray:
    """World position (m) of the arm's shoulder joint (joint 2 axis), fixed while joint 1 turns."""
    j = wc.model.joint(wc.arm_joint_names[1]).id
    return wc.data.xanchor[j].copy()


def look_target(wc: Workcell, cfg: ViewConfig, rng: np.random.Generator) -> np.ndarray:
    """A look-at point among the blocks: between their centroid and one of them, jittered in the plane (m)."""
    P = wc.block_poses()[:, :3, 3]
    c = P.mean(axis=0)
    t = c + rng.random() * (P[int(rng.integers(len(P)))] - c)
    t[:2] += rng.normal(0.0, cfg.target_jitter, 2)
    return t


def sample_camera_pose(cfg: ViewConfig, target: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``T_world_cam`` on the cap around ``target`` (azimuth 0: on the side of the arm base, the origin)."""
    d = rng.uniform(*cfg.distance)
    el = np.deg2rad(rng.uniform(*cfg.elevation_deg))
    a = np.arctan2(-target[1], -target[0]) + np.deg2rad(rng.uniform(*cfg.azimuth_deg))
    pos = target + d * np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)])
    roll = np.deg2rad(rng.uniform(-cfg.roll_deg, cfg.roll_deg))
    return make_T(look_at_R(target - pos) @ axis_angle_R([0.0, 0.0, 1.0], roll), pos)


def tour(poses: list[np.ndarray], start: np.ndarray, rot_weight: float = 0.15) -> list[int]:
    """Greedy nearest-neighbour order of camera poses from ``start`` (distance: metres + ``rot_weight`` m/rad)."""
    left, order, cur = list(range(len(poses))), [], start
    while left:
        j = min(left, key=lambda i: np.linalg.norm(poses[i][:3, 3] - cur[:3, 3])
                + rot_weight * rotation_angle(poses[i][:3, :3], cur[:3, :3]))
        left.remove(j)
        order.append(j)
        cur = poses[j]
    return order


def visit_views(wc: Workcell, cfg: ViewConfig, n: int, rng: np.random.Generator, stats: ViewStats) -> Iterator[np.ndarray]:
    """Set the arm at up to ``n`` reachable viewpoints, yielding the target ``T_world_cam`` once there.

    Candidates come in batches of as many as are still missing (at most ``n * attempts_per_view`` in all),
    each visited completely in nearest-neighbour order with IK started from the previous view's solution (nearby
    solutions, as short arm moves would give). The pose actually reached is read from the simulation by the caller.
    """
    shoulder = shoulder_position(wc)
    q, here = wc.look_q, wc.look_camera_pose()
    budget = n * cfg.attempts_per_view
    max_rot = np.deg2rad(cfg.max_rot_residual_deg)
    while stats.reached < n and stats.candidates < budget:
        k = min(n - stats.reached, budget - stats.candidates)
        batch = [sample_camera_pose(cfg, look_target(wc, cfg, rng), rng) for _ in range(k)]
        for j in tour(batch, here):
            T = batch[j]
            stats.candidates += 1
            if np.linalg.norm(T[:3, 3] - shoulder) > cfg.max_reach:
                stats.out_of_reach += 1
                continue
            qs, dp, dr = wc.solve_camera_ik(T, q, iters=cfg.ik_iters)
            if dp > cfg.max_pos_residual or dr > max_rot:
                stats.unreachable += 1
                continue
            if not wc.place_arm(qs):
                stats.blocked += 1
                continue
            q, here = qs, T
            stats.reached += 1
            yield T
