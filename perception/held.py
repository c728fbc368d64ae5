"""A held part's pose from a look at it in the hand: the pose it is believed held in, fitted to the depth image.

Closing fingers shift a part by millimetres, so the pose the pick's estimate gives it in the hand is a good start.
The observed points kept are those within ``reach`` of the model placed there (its seen faces; the fingers and the
arm beyond are left out), and the depth fit (``perception.depth_fit``) fits the model to them from that one start::

    P = { p : min_j || R0^T (p - t0) - m_j || < reach }     (p: a valid depth pixel's camera-frame point)

with no other start rotations, no resting starts, turns or searches: plain ICP, ``iterations`` steps, the last
``exact_steps`` with exact nearest model points. It needs no training and no plane: what a cell's in-hand check does
with the part's CAD model. Points are camera-frame metres; K is the 3x3 intrinsic matrix.
"""

from __future__ import annotations

from dataclasses import field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.config import settings, within
from posegrasp.perception.crop import backproject
from posegrasp.perception.depth_fit import DepthFitConfig, FitConfig, ObjectModel, StartConfig, TurnConfig, fit_pose
from posegrasp.perception.depth_fit.config import SearchConfig


@settings
class HeldFitConfig:
    """Fitting a held part's believed pose to a look's depth image (``perception.held``)."""

    #: Observed points farther (m) than this from the model at the believed pose are left out.
    reach: float = field(default=0.006, metadata=within(1e-4, 0.1))
    #: ICP steps, the exact ones included.
    iterations: int = field(default=40, metadata=within(1, 1000))
    #: Last steps with the exact nearest model points.
    exact_steps: int = field(default=3, metadata=within(0, 1000))
    #: Observed points fitted (a seeded random subset).
    max_points: int = field(default=1000, metadata=within(3, 1_000_000))
    #: Fewer observed points than this: no fit (the part is not seen).
    min_points: int = field(default=50, metadata=within(3, 1_000_000))

    def depth_fit(self) -> DepthFitConfig:
        """The depth fit's settings: one start, no rests, turns or searches."""
        return DepthFitConfig(starts=StartConfig(hypotheses="identity", level_rests=False),
                              fit=FitConfig(iterations=self.iterations, exact_steps=min(self.exact_steps,
                                                                                        self.iterations),
                                            max_points=self.max_points),
                              turns=TurnConfig(step_deg=0.0), search=SearchConfig(yaw_deg=0.0, pattern_rounds=0))


class HeldFit:
    """Held parts' poses fitted to depth images, with the models of the BOP models root ``models`` (each built at
    its first use)."""

    def __init__(self, models: str | Path, cfg: HeldFitConfig | None = None):
        self.root = Path(models)
        self.cfg = cfg or HeldFitConfig()
        self.infos = bop.load_models_info(self.root)
        self._models: dict[int, tuple[ObjectModel, cKDTree]] = {}

    def model(self, obj_id: int) -> tuple[ObjectModel, cKDTree]:
        """Object ``obj_id``'s ``ObjectModel`` for the fit and a k-d tree of its points (object frame, m)."""
        if obj_id not in self._models:
            m = ObjectModel.of_mesh(bop_models.load_model(self.root, obj_id), self.infos[obj_id].symmetry_rotations(),
                                    self.cfg.depth_fit(), seed=obj_id)
            self._models[obj_id] = m, cKDTree(m.points)
        return self._models[obj_id]

    def __call__(self, obj_id: int, T_cam_obj: np.ndarray, depth: np.ndarray, K: np.ndarray, seed: int = 0
                 ) -> np.ndarray | None:
        """Object ``obj_id`` believed at ``T_cam_obj`` (4, 4), fitted to the depth image (H, W) (m, 0: none) seen
        through K (3, 3): its fitted T_cam_obj, or None where fewer than ``min_points`` points lie near it (``seed``
        draws the points fitted)."""
        model, tree = self.model(obj_id)
        H, W = depth.shape
        P = backproject(depth, K, (0, H, 0, W), np.flatnonzero(depth > 0))
        local = (P - T_cam_obj[:3, 3]) @ T_cam_obj[:3, :3]
        near = P[tree.query(local, distance_upper_bound=self.cfg.reach)[0] < self.cfg.reach]
        if len(near) < self.cfg.min_points:
            return None
        if len(near) > self.cfg.max_points:
            near = near[np.sort(np.random.default_rng(seed).choice(len(near), self.cfg.max_points, replace=False))]
        return fit_pose(T_cam_obj, model, near, depth, K, self.cfg.depth_fit())[0]
