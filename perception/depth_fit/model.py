"""What the perception stages know of one object's shape: an ``ObjectModel`` per object id."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from posegrasp.bop import models as bop_models
from posegrasp.perception.depth_fit.config import DepthFitConfig
from posegrasp.perception.depth_fit.distance_field import DistanceField
from posegrasp.perception.depth_fit.grids import NearestGrid
from posegrasp.perception.depth_fit.rests import Rests
from posegrasp.perception.depth_fit.starts import NO_SYMMETRY, Symmetries, distinct_rotations
from posegrasp.perception.split import ModelSurface


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """One object's shape, object frame, metres: its model points (M, 3) in random order (the depth fit's
    scores rank with the first ``ScoreConfig.rank_points``), the rotations (H, 3, 3) its fits start from, its
    ``NearestGrid`` (with the ``DistanceField`` of its surface), its symmetries (discrete rotations (S, 3, 3),
    continuous axes (A, 3)), its ``Rests`` on a plane, and the dense ``ModelSurface`` that tells which observed points
    it explains (``perception.split``; None: not built)."""

    points: np.ndarray
    hypotheses: np.ndarray
    grid: NearestGrid
    symmetries: Symmetries
    rests: Rests
    surface: ModelSurface | None = None

    @classmethod
    def of_points(cls, points: np.ndarray, cfg: DepthFitConfig | None = None, hypotheses: np.ndarray | None = None,
                  symmetries: Symmetries | None = None, rests: Rests | None = None,
                  grid: NearestGrid | None = None) -> ObjectModel:
        """A model of surface points (M, 3) (object frame, m). Defaults: the start rotations ``cfg.rotations()``, no
        symmetry, the six object axes as rests (labelled by the symmetries), and a grid whose distance field is that
        of the points, reaching ``cfg.score.truncation``."""
        cfg = cfg or DepthFitConfig()
        symmetries = NO_SYMMETRY if symmetries is None else symmetries
        return cls(points, cfg.rotations() if hypotheses is None else hypotheses,
                   grid or NearestGrid(points, field=DistanceField(points, margin=cfg.score.truncation)),
                   symmetries, Rests.axes(*symmetries) if rests is None else rests)

    @classmethod
    def of_mesh(cls, mesh, symmetries: Symmetries, cfg: DepthFitConfig, seed: int,
                surface_points: int = 0) -> ObjectModel:
        """The model of a trimesh (object frame, m) with its symmetries (``bop.ObjectInfo.symmetry_rotations``):
        ``cfg.fit.model_points`` points sampled on it (seeded), the start rotations distinct under the symmetries, its
        stable rests, the signed distance field of its surface, and a ``ModelSurface`` of ``surface_points`` points
        (0: none)."""
        points = bop_models.sample_model_points(mesh, cfg.fit.model_points, seed=seed)
        rests = Rests.of_mesh(mesh, *symmetries)
        hypotheses = distinct_rotations(cfg.rotations(), list(symmetries[0]), list(symmetries[1]))
        grid = NearestGrid(points, field=DistanceField.of_mesh(mesh, seed=seed, margin=cfg.score.truncation))
        surface = ModelSurface(bop_models.sample_model_points(mesh, surface_points, seed=seed)) if surface_points else None
        return cls(points, hypotheses, grid, symmetries, rests, surface)

    @property
    def smallest_side(self) -> float:
        """The shortest side (m) of the model points' bounding box."""
        return float(np.ptp(self.points, axis=0).min())

    @cached_property
    def hull(self) -> np.ndarray:
        """The model points' convex-hull vertices (V, 3) (all the points when they span no volume): a linear
        function's extremes over the points (``perception.depth_fit.starts.lowest``)."""
        from scipy.spatial import ConvexHull, QhullError

        try:
            return self.points[ConvexHull(self.points).vertices]
        except (QhullError, ValueError):
            return self.points

    @cached_property
    def radius(self) -> float:
        """The largest distance (m) of a model point from the object frame's origin."""
        return float(np.sqrt(np.max(np.einsum("ij,ij->i", self.points, self.points))))
