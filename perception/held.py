"""A held part's position from a look at it in the hand: the pose it is believed held in, shifted onto the depth image.

Closing fingers shift a part by millimetres, so the pose the pick's estimate gives it in the hand is a good start.
The observed points kept are those within ``reach`` of the model placed there (its seen faces; the fingers and the
arm beyond are left out), and the model is shifted onto them, its turn R kept, by ICP on the translation alone::

    P = { p : min_j || R^T (p - t_0) - m_j || < reach }     (p: a valid depth pixel's camera-frame point)
    t_{k+1} = mean_i ( p_i - R m_j(i) ),   m_j(i) the model point nearest R^T (p_i - t_k), within reach

A face seen from below pins the part's position well; its turn about the face's normal it pins poorly (a full
rigid fit turned parts further off than the pick's estimate had), so the turn stays the estimate's. It needs no
training and no plane: what a cell's in-hand check does with the part's CAD model. Points are camera-frame metres;
K is the 3x3 intrinsic matrix.
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

    #: Observed points farther (m) than this from the model at the believed pose are left out, and in each step.
    reach: float = field(default=0.006, metadata=within(1e-4, 0.1))
    #: ICP steps.
    iterations: int = field(default=100, metadata=within(1, 1000))
    #: Observed points fitted (a seeded random subset) ...
    max_points: int = field(default=2000, metadata=within(3, 1_000_000))
    #: ... and fewer than this: no fit (the part is not seen).
    min_points: int = field(default=50, metadata=within(3, 1_000_000))
    #: Surface points sampled on each model.
    model_points: int = field(default=5000, metadata=within(3, 10_000_000))


class HeldFit:
    """Held parts' positions fitted to depth images, with the models of the BOP models root ``models`` (each
    sampled at its first use)."""

    def __init__(self, models: str | Path, cfg: HeldFitConfig | None = None):
        self.root = Path(models)
        self.cfg = cfg or HeldFitConfig()
        self._models: dict[int, tuple[np.ndarray, cKDTree]] = {}

    def model(self, obj_id: int) -> tuple[np.ndarray, cKDTree]:
        """Object ``obj_id``'s surface points (M, 3) (object frame, m) and their k-d tree."""
        if obj_id not in self._models:
            pts = bop_models.sample_model_points(bop_models.load_model(self.root, obj_id), self.cfg.model_points,
                                                 seed=obj_id)
            self._models[obj_id] = pts, cKDTree(pts)
        return self._models[obj_id]

    def __call__(self, obj_id: int, T_cam_obj: np.ndarray, depth: np.ndarray, K: np.ndarray, seed: int = 0
                 ) -> np.ndarray | None:
        """Object ``obj_id`` believed at ``T_cam_obj`` (4, 4), shifted onto the depth image (H, W) (m, 0: none) seen
        through K (3, 3): T_cam_obj with the fitted translation, or None where fewer than ``min_points`` points lie
        near it (``seed`` draws the points fitted)."""
        c = self.cfg
        pts, tree = self.model(obj_id)
        R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
        H, W = depth.shape
        P = backproject(depth, K, (0, H, 0, W), np.flatnonzero(depth > 0))
        P = P[tree.query((P - t) @ R, distance_upper_bound=c.reach)[0] < c.reach]
        if len(P) < c.min_points:
            return None
        if len(P) > c.max_points:
            P = P[np.sort(np.random.default_rng(seed).choice(len(P), c.max_points, replace=False))]
        for _ in range(c.iterations):
            d, j = tree.query((P - t) @ R, distance_upper_bound=c.reach)
            near = d < c.reach
            if near.sum() < c.min_points:
                return None
            t = np.mean(P[near] - pts[j[near]] @ R.T, axis=0)
        out = T_cam_obj.copy()
        out[:3, 3] = t
        return out
