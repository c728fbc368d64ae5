"""A held part's position from a look at it in the hand: the pose it is believed held in, shifted onto the depth image.

Closing fingers shift a part by millimetres, so the pose the pick's estimate gives it in the hand is a good start.
The observed points kept are those within ``start_reach`` of the model placed there (its seen faces; the arm beyond
is left out), less those within ``self_filter`` of the hand's own surface where the caller gives it (the fingers
beside the part: a cell knows its hand's pose and meshes). Each step pairs points both ways within a reach that
shrinks from ``start_reach`` to ``reach``: each observed point p with its nearest model point, and each model point
facing the camera with its nearest observed point (so a face seen from below is pulled back over the points seen,
not only onto their plane), and shifts the model by the pairs' mean difference, its turn R kept::

    t_{k+1} = t_k + mean_i ( b_i - a_i )      (pairs a_i -> b_i: model point -> observed point, camera frame)

A face seen from below pins the part's position well; its turn about the face's normal it pins poorly (a turn
fitted as well turned more held parts past 3 deg than the pick's estimate had), so the turn stays the estimate's. It
needs no training and no plane: what a cell's in-hand check does with the part's CAD model. Points are camera-frame
metres; K is the 3x3 intrinsic matrix.
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
    """Shifting a held part's believed pose onto a look's depth image (``perception.held``)."""

    #: Observed points farther (m) than this from the model at the believed pose are left out; the pairs' reach
    #: starts there ...
    start_reach: float = field(default=0.012, metadata=within(1e-4, 0.1))
    #: ... and shrinks by 10 % a step down to this (m).
    reach: float = field(default=0.006, metadata=within(1e-4, 0.1))
    #: Observed points this near (m) the hand's own surface (the caller's ``exclude``: the fingers beside the part)
    #: are left out.
    self_filter: float = field(default=0.004, metadata=within(0.0, 0.05))
    #: ICP steps.
    iterations: int = field(default=120, metadata=within(1, 1000))
    #: Observed points fitted (a seeded random subset) ...
    max_points: int = field(default=3000, metadata=within(3, 1_000_000))
    #: ... and fewer than this, observed or paired: no fit (the part is not seen).
    min_points: int = field(default=50, metadata=within(3, 1_000_000))
    #: Surface points sampled on each model.
    model_points: int = field(default=5000, metadata=within(3, 10_000_000))


class HeldFit:
    """Held parts' positions fitted to depth images, with the models of the BOP models root ``models`` (each sampled
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

    def __call__(self, obj_id: int, T_cam_obj: np.ndarray, depth: np.ndarray, K: np.ndarray, seed: int = 0,
                 exclude: np.ndarray | None = None) -> np.ndarray | None:
        """Object ``obj_id`` believed at ``T_cam_obj`` (4, 4), shifted onto the depth image (H, W) (m, 0: none) seen
        through K (3, 3): T_cam_obj with the fitted translation, or None where fewer than ``min_points`` points lie
        near it or pair with it (``seed`` draws the points fitted). ``exclude``: (M, 3) camera-frame points (m) on
        the hand; observed points within ``self_filter`` of them are not the part's."""
        c = self.cfg
        pts, normals, tree = self.model(obj_id)
        R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3].copy()
        H, W = depth.shape
        P = backproject(depth, K, (0, H, 0, W), np.flatnonzero(depth > 0))
        P = P[tree.query((P - t) @ R, distance_upper_bound=c.start_reach)[0] < c.start_reach]
        if exclude is not None and len(exclude) and len(P) and c.self_filter > 0:
            P = P[cKDTree(exclude).query(P, distance_upper_bound=c.self_filter)[0] >= c.self_filter]
        if len(P) < c.min_points:
            return None
        if len(P) > c.max_points:
            P = P[np.sort(np.random.default_rng(seed).choice(len(P), c.max_points, replace=False))]
        seen, reach = cKDTree(P), c.start_reach
        facing = np.einsum("ij,ij->i", normals @ R.T, pts @ R.T + t) < 0.0  # toward the camera (the turn is kept)
        front = pts[facing]
        for _ in range(c.iterations):
            reach = max(c.reach, 0.9 * reach)
            d, j = tree.query((P - t) @ R, distance_upper_bound=reach)
            M = front @ R.T + t
            d2, i2 = seen.query(M, distance_upper_bound=reach)
            if (d < reach).sum() + (d2 < reach).sum() < c.min_points:
                return None
            t = t + np.concatenate([P[d < reach] - (pts[j[d < reach]] @ R.T + t), P[i2[d2 < reach]] - M[d2 < reach]]
                                   ).mean(axis=0)
        out = np.array(T_cam_obj, float)
        out[:3, 3] = t
        return out
