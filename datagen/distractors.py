"""Distractor objects: unlabelled primitives resting on the table around the pick area.

They are static world geoms that collide (blocks and the arm touch them) and occlude the blocks, but are not
in the catalogue, so they never get ground truth or masks of their own.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np
from dm_control import mjcf

from posegrasp.datagen.config import DistractorConfig
from posegrasp.geometry import R_to_quat, axis_angle_R
from posegrasp.sim.config import AreaConfig

KINDS = ("box", "cylinder", "sphere", "capsule")


@dataclass(frozen=True)
class Distractor:
    """One primitive: MuJoCo ``kind`` and ``size``, world pose (pos m, quat w-x-y-z) and RGBA."""

    kind: str
    size: tuple[float, ...]
    pos: tuple[float, float, float]
    quat: tuple[float, float, float, float]
    rgba: tuple[float, float, float, float]

    @property
    def radius(self) -> float:
        """Footprint radius on the table (m)."""
        if self.kind == "box":
            return float(np.hypot(self.size[0], self.size[1]))
        if self.kind == "capsule":
            return self.size[0] + self.size[1]
        return self.size[0]


def _resting(kind: str, half: np.ndarray, yaw: float) -> tuple[tuple[float, ...], float, np.ndarray]:
    """MuJoCo size, height of the centre above the table, and rotation of a primitive lying stably."""
    Rz = axis_angle_R([0.0, 0.0, 1.0], yaw)
    if kind == "box":
        return tuple(half), half[2], Rz
    if kind == "cylinder":  # standing on its base
        return (half[0], half[2]), half[2], Rz
    if kind == "sphere":
        return (half[0],), half[0], Rz
    return (half[0], half[1]), half[0], Rz @ axis_angle_R([1.0, 0.0, 0.0], np.pi / 2)  # capsule on its side


def sample_distractors(cfg: DistractorConfig, area: AreaConfig, rng: np.random.Generator) -> list[Distractor]:
    """``cfg.count`` random primitives in the band ``cfg.band`` (m) around ``area``, not overlapping each other."""
    n = int(rng.integers(cfg.count[0], cfg.count[1] + 1))
    c, h = np.asarray(area.center), np.asarray(area.half_size)
    out: list[Distractor] = []
    for _ in range(n):
        kind = KINDS[int(rng.integers(len(KINDS)))]
        half = rng.uniform(*cfg.size, 3)
        half[2] = rng.uniform(cfg.size[0], 2.0 * cfg.size[1])  # some tall ones, to occlude
        size, z, R = _resting(kind, half, rng.uniform(0.0, 2 * np.pi))
        hue = rng.uniform()
        rgb = colorsys.hsv_to_rgb(hue, rng.uniform(0.0, 1.0), rng.uniform(0.15, 1.0))
        for _attempt in range(50):
            xy = rng.uniform(c - h - cfg.band[1], c + h + cfg.band[1])
            outside = np.any(np.abs(xy - c) > h + cfg.band[0])
            d = Distractor(kind, tuple(float(s) for s in size), (float(xy[0]), float(xy[1]), float(z)),
                           tuple(float(q) for q in R_to_quat(R)), (*(float(v) for v in rgb), 1.0))
            if outside and all(np.hypot(xy[0] - o.pos[0], xy[1] - o.pos[1]) > d.radius + o.radius for o in out):
                out.append(d)
                break
    return out


def add_distractors(root: mjcf.RootElement, distractors: tuple[Distractor, ...] | list[Distractor]) -> None:
    """Static, colliding, visible world geoms ``distractor_<i>``."""
    for i, d in enumerate(distractors):
        root.worldbody.add("geom", name=f"distractor_{i}", type=d.kind, size=d.size, pos=d.pos, quat=d.quat,
                           rgba=d.rgba, contype=1, conaffinity=1, group=1, friction=(0.9, 0.01, 0.001))
