"""A depth-only pose estimator as a posegrasp perception plug-in: no learning, no colour.

    posegrasp trials --perception py:examples/providers/depth_only.py:make_provider --episodes 20 --out runs/depth

It is built from the project's own classical pieces and shows what a plug-in receives and returns
(``docs/estimators.md``):

1. the supporting plane of the depth image, by RANSAC (``posegrasp.perception.plane.fit_support_plane``);
2. the pixels standing more than ``min_height`` above it, cut at depth edges, as connected blobs (one per
   object, unless two touch at the same height);
3. for each blob, every model of the object set whose size can explain it is fitted by ICP from the 24
   axis-aligned starting rotations about the blob's principal axes (``posegrasp.perception.refine.refine_poses``,
   with the free-space and below-the-plane penalties); the model and pose with the lowest ICP score win. Depth
   alone cannot tell apart objects of the same shape and size: the ICP score picks among them.

The provider gets the observation (RGB uint8, depth in metres, K) and a seed, and returns
``Estimate(obj_id, T_cam_obj, score)`` with ``T_cam_obj`` in metres in the OpenCV camera frame.
ARGS (optional): ``MIN_HEIGHT_MM,MAX_POINTS``, e.g. ``make_provider:5,200``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from posegrasp import bop
from posegrasp import bop_models
from posegrasp.errors import UserError
from posegrasp.grasping.perception import Estimate, Observation
from posegrasp.perception.crop import backproject
from posegrasp.perception.refine import (FitConfig, NearestGrid, ObjectModel, RefineConfig, distinct_rotations,
                                         refine_poses)
from posegrasp.perception.plane import fit_support_plane, plane_distance


@dataclass
class _Model:
    """One object of the set: id, its shape for the ICP, size (m)."""

    obj_id: int
    model: ObjectModel
    extents: np.ndarray  # bounding-box size, sorted ascending
    diameter: float


@dataclass
class DepthOnlyProvider:
    """Plane + blobs + ICP over the set's models; see the module docstring. ``models``: a BOP models root
    (a folder holding ``models/models_info.json`` and the PLY files, mm)."""

    models: str
    min_height: float = 0.005  # blob pixels stand at least this far above the plane (m)
    edge: float = 0.01  # neighbouring pixels this far apart in depth are cut apart (m)
    min_px: int = 150  # blobs with fewer pixels (at 640x480) are dropped
    size_tol: float = 0.008  # a model is tried when its size matches the blob's within this (m)
    score_scale: float = 0.004  # score = exp(-ICP score / this)
    icp: RefineConfig = field(default_factory=lambda: RefineConfig(fit=FitConfig(max_points=200)))
    name: str = "depth-only"

    def __post_init__(self) -> None:
        infos = bop.load_models_info(self.models)
        self._models = []
        for o, info in sorted(infos.items()):
            pts = bop_models.sample_model_points(bop_models.load_model(self.models, o), 500, seed=o)
            rots = distinct_rotations(self.icp.rotations(), info.symmetries_discrete,
                                      [a for a, _ in info.symmetries_continuous])
            self._models.append(_Model(o, ObjectModel.of_points(pts, self.icp, rots, grid=NearestGrid(pts)),
                                       np.sort(np.ptp(pts, axis=0)), float(info.diameter)))

    def estimate(self, obs: Observation, seed: int) -> list[Estimate]:
        """Pose estimates (OpenCV camera frame, m) of the objects standing on the frame's supporting plane."""
        depth, K = np.asarray(obs.depth, np.float64), np.asarray(obs.K, np.float64)
        plane = fit_support_plane(obs.depth, K, seed)
        if plane is None:
            return []
        rng = np.random.default_rng(seed)
        blob, starts, models, observed = [], [], [], []  # one row per (blob, candidate model)
        for b, idx in enumerate(self._blobs(depth, K, plane)):
            pts = backproject(depth, K, (0, depth.shape[0], 0, depth.shape[1]), idx)
            T, fit = self._candidates(pts, plane)
            sub = pts[np.sort(rng.choice(len(pts), min(len(pts), self.icp.fit.max_points), replace=False))]
            blob += [b] * len(fit)
            starts += [T] * len(fit)
            models += fit
            observed += [sub] * len(fit)
        torch.set_num_threads(1)  # small batched ops: threads only add overhead (and compete with other workers)
        fits = refine_poses(starts, [m.model for m in models], observed, obs.depth, K, self.icp, plane)
        out = []
        for b in sorted(set(blob)):  # each blob: the candidate with the lowest ICP score
            j = min((j for j in range(len(blob)) if blob[j] == b), key=lambda j: fits[j][1])
            out.append(Estimate(models[j].obj_id, fits[j][0], float(np.exp(-fits[j][1] / self.score_scale))))
        return out

    def _blobs(self, depth: np.ndarray, K: np.ndarray, plane: np.ndarray) -> list[np.ndarray]:
        """Flat pixel indices of each blob standing on the plane, cut at depth edges, large enough."""
        h = np.full(depth.size, -1.0)
        valid = np.flatnonzero(depth > 0)
        h[valid] = plane_distance(plane, depth, K, valid)
        above = (h > self.min_height).reshape(depth.shape)
        edges = np.zeros_like(above)
        edges[:, 1:] |= np.abs(np.diff(depth, axis=1)) > self.edge
        edges[1:, :] |= np.abs(np.diff(depth, axis=0)) > self.edge
        labels, n = ndimage.label(above & ~edges)
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        min_px = self.min_px * depth.size / (640 * 480)
        return [np.flatnonzero(labels == k) for k in range(1, n + 1) if sizes[k] >= min_px]

    def _candidates(self, pts: np.ndarray, plane: np.ndarray) -> tuple[np.ndarray, list[_Model]]:
        """The starting pose of a blob's fit (centred on its points (camera frame, m), axes along its principal
        directions on the plane and the plane normal) and the models whose size can explain it."""
        n = plane[:3]
        c = pts.mean(axis=0)
        flat = (pts - c) - np.outer((pts - c) @ n, n)
        major = np.linalg.eigh(flat.T @ flat)[1][:, -1]
        R = np.stack([major, np.cross(n, major), n], axis=1)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, c
        span = np.ptp(flat @ R[:, :2], axis=0)  # extents seen along the plane, major axis first (m)
        height = float((pts @ n + plane[3]).max())  # highest point above the plane (m)
        return T, [m for m in self._models if self._explains(m.extents, span, height)]

    def _explains(self, extents: np.ndarray, span: np.ndarray, height: float) -> bool:
        """Can an object of bounding-box ``extents`` (m), resting on one of its faces, stand ``height`` high and
        show a footprint of ``span`` (major, minor; m; occlusion only shrinks it)?"""
        for k in range(3):
            a, b = np.delete(extents, k)
            if abs(height - extents[k]) <= self.size_tol and span[0] <= max(a, b) + self.size_tol \
                    and span[1] <= min(a, b) + self.size_tol:
                return True
        return False


def make_provider(args: str | None, objects: str) -> DepthOnlyProvider:
    """The plug-in's factory: ``py:examples/providers/depth_only.py:make_provider[:MIN_HEIGHT_MM,MAX_POINTS]``;
    ``objects`` is the object set's folder (posegrasp passes it)."""
    kw = {}
    if args:
        try:
            mm, n = args.split(",")
            kw = {"min_height": float(mm) / 1000, "icp": RefineConfig(fit=FitConfig(max_points=int(n)))}
        except ValueError:
            raise UserError(f"depth-only ARGS {args!r} are not MIN_HEIGHT_MM,MAX_POINTS, e.g. 5,200") from None
    return DepthOnlyProvider(str(Path(objects)), **kw)
