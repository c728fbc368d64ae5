"""A held part's pose from a look at it in the hand: the pose it is believed held in, shifted and turned about the
camera's axis onto the depth image.

Closing fingers shift a part by millimetres and an estimate is off by a few more and a few degrees, so the pose the
pick gives the part in the hand is a good start. The look's camera looks along the axis the part may be turned
about (the tray's, straight up: the vertical); its tilt, which the face it rests on fixes, is kept. The observed
points kept are those within ``start_reach`` of the model placed there (its seen faces; the fingers and the arm
beyond are left out). Each step pairs points both ways within a reach that shrinks from ``start_reach`` to
``reach``: each observed point p with its nearest model point, and each model point facing the camera with its
nearest observed point (so a face seen from below is pulled back over the points seen, not only onto their plane),
and solves for the turn theta about the camera's z axis and the shift that bring the pairs (a_i -> b_i) together::

    theta = atan2( sum_i (a_i x b_i)_z , sum_i a_i . b_i )      (xy of a_i, b_i less their means)
    x <- Rz(theta) (x - mean a) + mean b                         (the model's pose, camera frame)

It needs no training and no plane: what a cell's in-hand check does with the part's CAD model. Points are
camera-frame metres; K is the 3x3 intrinsic matrix.
"""

from __future__ import annotations

from dataclasses import field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from posegrasp.bop import models as bop_models
from posegrasp.config import settings, within
from posegrasp.perception.crop import backproject


@settings
class HeldFitConfig:
    """Fitting a held part's believed pose to a look's depth image (``perception.held``)."""

    #: Observed points farther (m) than this from the model at the believed pose are left out; the pairs' reach
    #: starts there ...
    start_reach: float = field(default=0.012, metadata=within(1e-4, 0.1))
    #: ... and shrinks by 10 % a step down to this (m).
    reach: float = field(default=0.006, metadata=within(1e-4, 0.1))
    #: Turn the pose about the camera's axis as well as shift it (false: shift only).
    turn: bool = True
    #: ICP steps.
    iterations: int = field(default=120, metadata=within(1, 1000))
    #: Observed points fitted (a seeded random subset) ...
    max_points: int = field(default=3000, metadata=within(3, 1_000_000))
    #: ... and fewer than this, observed or paired: no fit (the part is not seen).
    min_points: int = field(default=50, metadata=within(3, 1_000_000))
    #: Surface points sampled on each model.
    model_points: int = field(default=5000, metadata=within(3, 10_000_000))


class HeldFit:
    """Held parts' poses fitted to depth images, with the models of the BOP models root ``models`` (each sampled
    at its first use)."""

    def __init__(self, models: str | Path, cfg: HeldFitConfig | None = None):
        self.root = Path(models)
        self.cfg = cfg or HeldFitConfig()
        self._models: dict[int, tuple[np.ndarray, np.ndarray, cKDTree]] = {}

    def model(self, obj_id: int) -> tuple[np.ndarray, np.ndarray, cKDTree]:
        """Object ``obj_id``'s surface points (M, 3), their outward normals (M, 3) (object frame, m) and the
        points' k-d tree."""
        if obj_id not in self._models:
            pts, normals = bop_models.sample_model_surface(bop_models.load_model(self.root, obj_id),
                                                           self.cfg.model_points, seed=obj_id)
            self._models[obj_id] = pts, normals, cKDTree(pts)
        return self._models[obj_id]

    def __call__(self, obj_id: int, T_cam_obj: np.ndarray, depth: np.ndarray, K: np.ndarray, seed: int = 0
                 ) -> np.ndarray | None:
        """Object ``obj_id`` believed at ``T_cam_obj`` (4, 4), fitted to the depth image (H, W) (m, 0: none) seen
        through K (3, 3): T_cam_obj shifted and turned about the camera's z axis, or None where fewer than
        ``min_points`` points lie near it or pair with it (``seed`` draws the points fitted)."""
        c = self.cfg
        pts, normals, tree = self.model(obj_id)
        R, t = T_cam_obj[:3, :3].copy(), T_cam_obj[:3, 3].copy()
        H, W = depth.shape
        P = backproject(depth, K, (0, H, 0, W), np.flatnonzero(depth > 0))
        P = P[tree.query((P - t) @ R, distance_upper_bound=c.start_reach)[0] < c.start_reach]
        if len(P) < c.min_points:
            return None
        if len(P) > c.max_points:
            P = P[np.sort(np.random.default_rng(seed).choice(len(P), c.max_points, replace=False))]
        seen, reach = cKDTree(P), c.start_reach
        for _ in range(c.iterations):
            reach = max(c.reach, 0.9 * reach)
            M = pts @ R.T + t  # the model in the camera frame
            d, j = tree.query((P - t) @ R, distance_upper_bound=reach)
            facing = M[np.einsum("ij,ij->i", normals @ R.T, M) < 0.0]  # normals toward the camera at the origin
            d2, i2 = seen.query(facing, distance_upper_bound=reach)
            a = np.concatenate([M[j[d < reach]], facing[d2 < reach]])
            b = np.concatenate([P[d < reach], P[i2[d2 < reach]]])
            if len(a) < c.min_points:
                return None
            ma, mb = a.mean(axis=0), b.mean(axis=0)
            Rz = np.eye(3)
            if c.turn:
                u, v = a[:, :2] - ma[:2], b[:, :2] - mb[:2]
                th = np.arctan2(np.sum(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]), np.sum(u * v))
                Rz[:2, :2] = [[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]
            R, t = Rz @ R, Rz @ (t - ma) + mb
        out = np.array(T_cam_obj, float)
        out[:3, :3], out[:3, 3] = R, t
        return out
