"""Perception providers: what the planner knows about the blocks, as pose estimates in the camera frame.

A provider receives the hand camera's captured ``Frame`` (RGB-D, K) and returns ``Estimate``s
``(obj_id, T_cam_obj, score)``. The planner never sees simulator ground truth except through a provider.
This module holds the protocol and the oracles (``grasping.provider_registry.make_provider`` builds any
provider from its ``--perception`` name):

- ``oracle``: the ground-truth ``T_cam_obj`` of every block with at least ``min_px`` visible mask pixels.
- ``noisy-oracle[:TRANS_M,ROT_DEG]``: the oracle plus Gaussian translation noise (sigma TRANS_M per axis)
  and a rotation about a uniformly random axis by an angle ~ |N(0, ROT_DEG)|; seeded per frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from posegrasp.errors import UserError
from posegrasp.geometry import axis_angle_R
from posegrasp.sim.camera import Frame


@dataclass(frozen=True)
class Estimate:
    """One detected block: catalogue id, pose in the (OpenCV) camera frame (m) and a confidence in [0, 1]."""

    obj_id: int
    T_cam_obj: np.ndarray
    score: float


class Provider(Protocol):
    """Turns a captured frame into pose estimates; ``seed`` makes any randomness repeatable."""

    name: str

    def estimate(self, frame: Frame, seed: int) -> list[Estimate]: ...


def visible_enough(pixels: int, shape: tuple[int, int], min_px: int) -> bool:
    """Does a mask of ``pixels`` in an image of ``shape`` (H, W) hold at least ``min_px`` pixels at 640x480?"""
    return pixels >= min_px * (shape[0] * shape[1]) / (640 * 480)


@dataclass(frozen=True)
class OracleProvider:
    """Ground truth for the blocks visible in the frame (at least ``min_px`` mask pixels at 640x480)."""

    min_px: int = 150
    name: str = "oracle"

    def estimate(self, frame: Frame, seed: int) -> list[Estimate]:
        counts = np.bincount(frame.mask.ravel(), minlength=len(frame.obj_ids) + 1)
        return [Estimate(int(frame.obj_ids[k - 1]), frame.T_cam_obj[k - 1].copy(), float(min(1.0, counts[k] / 5000)))
                for k in range(1, len(frame.obj_ids) + 1) if visible_enough(counts[k], frame.mask.shape, self.min_px)]


@dataclass(frozen=True)
class NoisyOracleProvider:
    """The oracle with seeded Gaussian translation noise (m, per axis) and random-axis rotation noise (deg)."""

    trans_m: float = 0.005
    rot_deg: float = 5.0
    min_px: int = 150

    @property
    def name(self) -> str:
        return f"noisy-oracle:{self.trans_m:g},{self.rot_deg:g}"

    def estimate(self, frame: Frame, seed: int) -> list[Estimate]:
        rng = np.random.default_rng(seed)
        out = []
        for e in OracleProvider(self.min_px).estimate(frame, seed):
            axis = rng.normal(size=3)
            angle = np.deg2rad(abs(rng.normal(0.0, self.rot_deg))) if self.rot_deg > 0 else 0.0
            dt = rng.normal(0.0, self.trans_m, size=3) if self.trans_m > 0 else np.zeros(3)
            T = e.T_cam_obj.copy()
            T[:3, :3] = axis_angle_R(axis, angle) @ T[:3, :3]
            T[:3, 3] += dt
            out.append(Estimate(e.obj_id, T, e.score))
        return out


def oracle_from_spec(args: str | None) -> OracleProvider:
    """The oracle for ``--perception oracle`` (``args``: the text after ``oracle:``, which must be empty)."""
    if args:
        raise UserError(f"perception 'oracle' takes no parameters, got 'oracle:{args}'")
    return OracleProvider()


def noisy_oracle_from_spec(args: str | None) -> NoisyOracleProvider:
    """The noisy oracle for ``--perception noisy-oracle[:TRANS_M,ROT_DEG]`` (``args``: the text after the colon)."""
    if not args:
        return NoisyOracleProvider()
    try:
        t, r = (float(v) for v in args.split(","))
    except ValueError:
        raise UserError(f"noisy-oracle parameters {args!r} are not TRANS_M,ROT_DEG, e.g. noisy-oracle:0.005,5") from None
    if not (0 <= t <= 0.2 and 0 <= r <= 180):
        raise UserError(f"noisy-oracle noise {args!r} out of range: TRANS_M in [0, 0.2] m, ROT_DEG in [0, 180]")
    return NoisyOracleProvider(t, r)
