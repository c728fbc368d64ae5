"""A training-free pose estimator for any object set: parts cut out of the depth image against their support, each
fitted by the depth fit with every model of the set that can explain it.

1. The support: the dominant plane of the depth image by RANSAC, then the plane the parts above it rest on (a tote's
   floor above the table; ``perception.plane.fit_support_plane``).
2. Blobs: the pixels standing more than ``min_height`` above the support, cut at depth steps over ``edge`` and at
   colour boundaries: steps over ``colour_edge`` in chromaticity c = rgb / (r + g + b), which shading hardly changes,
   between lit neighbours (two parts touching at one height, painted differently). Blobs under ``min_px`` pixels (at
   640x480) are dropped.
3. Candidates: every model that, resting on one of its rests (or bounding-box faces), stands as high as the blob and
   has a footprint along the plane as wide as the blob's in both of its principal directions (within ``size_tol``).
4. Fits: each (blob, candidate) pair is fitted by ``perception.depth_fit.fit_poses`` from a frame centred on the blob
   with axes along its principal directions on the plane (the 24 cube rotations, resting starts, turns about the
   normal, exact ICP steps, yaw and pattern searches on the depth score), all pairs of a frame in one batch.
5. Choice: per blob, the candidate with the lowest depth score + ``colour_weight`` |c_blob - c_model| (the blob's
   median chromaticity against the model's colour in the set, where a cell's parts have their set's colours); its
   confidence is exp(-that / ``score_scale``). Two fits of one model within ``duplicate`` of each other (a part cut
   in two by a colour step across it) are one part.

It reads nothing but the RGB-D frame, K and the object set's models, symmetries and colours. Points are camera-frame
metres (OpenCV: x right, y down, z forward).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.config import settings, within
from posegrasp.perception.crop import backproject
from posegrasp.perception.depth_fit import DepthFitConfig, FitConfig, ObjectModel, fit_poses
from posegrasp.perception.plane import fit_support_plane, plane_distance
from posegrasp.perception.runtime import torch_threads


@settings
class DepthIcpConfig:
    """The training-free estimator (``--perception depth-icp``): segmentation against the support, candidate models
    by size, depth fit, colour."""

    #: Keys of settings files under their old names (``posegrasp.config``).
    RENAMED = {"icp": "depth_fit"}

    #: Height (m) above the supporting plane from which a pixel belongs to a part.
    min_height: float = field(default=0.005, metadata=within(0, 10))
    #: Depth step (m) between neighbouring pixels that cuts two parts apart.
    edge: float = field(default=0.01, metadata=within(0, 10))
    #: Fewest pixels (px at 640x480) of a part; smaller blobs are dropped.
    min_px: int = field(default=150, metadata=within(1, 100000000))
    #: Slack (m) with which a model resting on one of its rests must match a blob's height and footprint to be fitted.
    size_tol: float = field(default=0.008, metadata=within(0, 10))
    #: Chromaticity step between neighbouring pixels that cuts two parts apart (0: depth steps only).
    colour_edge: float = field(default=0.1, metadata=within(0, 10))
    #: Least brightness r + g + b (0-765) of both pixels for a chromaticity step to count (dark pixels' is noise).
    min_brightness: float = field(default=90.0, metadata=within(0, 765))
    #: Weight (m) of the chromaticity distance between a blob and a model's colour in the object set in the choice of
    #: model; for cells whose parts have their set's colours (the trial scenes paint them from a palette: 0).
    colour_weight: float = field(default=0.0, metadata=within(0, 100))
    #: Distance (m) within which two fits of one model (to two pieces of a part cut apart) are one part: the more
    #: confident stays.
    duplicate: float = field(default=0.01, metadata=within(0, 10))
    #: Confidence scale (m): confidence = exp(-(score + colour term) / score_scale).
    score_scale: float = field(default=0.004, metadata=within(1e-9, 100))
    #: Depth fit of each blob's candidate models (``perception.depth_fit``).
    depth_fit: DepthFitConfig = field(default_factory=lambda: DepthFitConfig(fit=FitConfig(max_points=200)))


@dataclass(frozen=True)
class Candidate:
    """A model of the set as the estimator matches it to blobs: id, ``ObjectModel``, the sizes (R, 3) it shows resting
    on each of its rests and on each face of its bounding box (height, widest and narrowest footprint along the plane;
    m; ``footprints``) and chromaticity (3,)."""

    obj_id: int
    model: ObjectModel
    sizes: np.ndarray
    chroma: np.ndarray


def footprints(points: np.ndarray, ups: np.ndarray, turns: int = 36) -> np.ndarray:
    """For each up u (U, 3) (object frame) of a model with surface points (M, 3) (m) resting with u up: its height,
    and the widest and narrowest width of its footprint on the plane over ``turns`` directions (U, 3) (m)."""
    out = []
    for u in ups / np.linalg.norm(ups, axis=1, keepdims=True):
        e1 = np.cross(u, np.eye(3)[int(np.abs(u).argmin())])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        a = np.linspace(0.0, np.pi, turns, endpoint=False)
        widths = np.ptp(points @ (np.outer(np.cos(a), e1) + np.outer(np.sin(a), e2)).T, axis=0)
        out.append((np.ptp(points @ u), widths.max(), widths.min()))
    return np.array(out)


@dataclass(frozen=True)
class DepthIcpDetection:
    """One part found: its model's id, pose T_cam_obj (4, 4) (m, camera frame), confidence in (0, 1] and pixel mask
    (H, W) bool."""

    obj_id: int
    T_cam_obj: np.ndarray
    score: float
    mask: np.ndarray


def chromaticity(rgb: np.ndarray) -> np.ndarray:
    """rgb (..., 3) (any scale) as chromaticity rgb / (r + g + b) (..., 3); black gives (1/3, 1/3, 1/3)."""
    rgb = np.asarray(rgb, np.float64)
    s = rgb.sum(axis=-1, keepdims=True)
    return np.where(s > 0, rgb / np.maximum(s, 1e-12), 1.0 / 3.0)


class DepthIcp:
    """The estimator of ``models`` (a BOP models root: ``models/models_info.json`` and PLY files in mm) whose
    objects have the colours ``rgb`` (obj_id -> (3,) in [0, 1]; missing: grey). ``est(rgb, depth, K, seed)`` ->
    detections (module doc)."""

    def __init__(self, models: str | Path, rgb: dict[int, np.ndarray] | None = None,
                 cfg: DepthIcpConfig | None = None):
        self.cfg = cfg or DepthIcpConfig()
        infos = bop.load_models_info(models)
        rgb = rgb or {}
        self.candidates: list[Candidate] = []
        for o, info in sorted(infos.items()):
            model = ObjectModel.of_mesh(bop_models.load_model(models, o), info.symmetry_rotations(),
                                        self.cfg.depth_fit, seed=o)
            ups = np.concatenate([model.rests.ups, np.eye(3), -np.eye(3)])
            self.candidates.append(Candidate(o, model, footprints(model.points, ups),
                                             chromaticity(rgb.get(o, (0.5, 0.5, 0.5)))))

    def __call__(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, seed: int = 0) -> list[DepthIcpDetection]:
        """The parts seen in an RGB-D frame: rgb (H, W, 3) uint8, depth (H, W) (m, 0: none), K (3, 3)."""
        cfg = self.cfg
        depth, K = np.asarray(depth, np.float64), np.asarray(K, np.float64)
        plane = fit_support_plane(depth, K, seed)
        if plane is None:
            return []
        plane = fit_support_plane(depth, K, seed, objects=self._above(depth, K, plane)) if cfg.min_height else plane
        flat_rgb = np.asarray(rgb).reshape(-1, np.asarray(rgb).shape[-1])[:, :3].astype(np.float64)
        chroma = chromaticity(flat_rgb)
        rng = np.random.default_rng(seed)
        blobs, rows = [], []  # rows: (blob, candidate, start, observed points, colour distance)
        for idx in self._blobs(depth, K, plane, chroma, flat_rgb.sum(axis=1)):
            pts = backproject(depth, K, (0, depth.shape[0], 0, depth.shape[1]), idx)
            T, fit = self._candidates(pts, plane)
            if not fit:
                continue
            sub = pts[np.sort(rng.choice(len(pts), min(len(pts), cfg.depth_fit.fit.max_points), replace=False))]
            c = np.median(chroma[idx], axis=0)
            rows += [(len(blobs), p, T, sub, float(np.linalg.norm(c - p.chroma))) for p in fit]
            blobs.append(idx)
        if not rows:
            return []
        with torch_threads(1):  # small batched ops: threads only add overhead (and compete with other workers)
            fits = fit_poses([r[2] for r in rows], [r[1].model for r in rows], [r[3] for r in rows], depth, K,
                             cfg.depth_fit, plane)
        out = []
        for b, idx in enumerate(blobs):
            j = min((j for j, r in enumerate(rows) if r[0] == b),
                    key=lambda j: fits[j][1] + cfg.colour_weight * rows[j][4])
            mask = np.zeros(depth.shape, dtype=bool)
            mask.flat[idx] = True
            total = fits[j][1] + cfg.colour_weight * rows[j][4]
            out.append(DepthIcpDetection(rows[j][1].obj_id, fits[j][0], float(np.exp(-total / cfg.score_scale)), mask))
        return _distinct(out, cfg.duplicate)

    def _above(self, depth: np.ndarray, K: np.ndarray, plane: np.ndarray) -> np.ndarray:
        """Bool (H, W): the valid pixels standing more than ``min_height`` above ``plane``."""
        h = np.full(depth.size, -1.0)
        valid = np.flatnonzero(depth > 0)
        h[valid] = plane_distance(plane, depth, K, valid)
        return (h > self.cfg.min_height).reshape(depth.shape)

    def _blobs(self, depth: np.ndarray, K: np.ndarray, plane: np.ndarray, chroma: np.ndarray,
               brightness: np.ndarray) -> list[np.ndarray]:
        """Flat pixel indices of each blob standing on the plane, cut at depth steps and chromaticity steps
        (``chroma`` (H W, 3), ``brightness`` (H W,): r + g + b, 0-765)."""
        cfg = self.cfg
        above = self._above(depth, K, plane)
        edges = np.zeros_like(above)
        edges[:, 1:] |= np.abs(np.diff(depth, axis=1)) > cfg.edge
        edges[1:, :] |= np.abs(np.diff(depth, axis=0)) > cfg.edge
        if cfg.colour_edge > 0:  # chromaticity steps between pixels bright enough for it to mean something
            c, lit = chroma.reshape(*depth.shape, 3), (brightness >= cfg.min_brightness).reshape(depth.shape)
            edges[:, 1:] |= (np.linalg.norm(np.diff(c, axis=1), axis=2) > cfg.colour_edge) & lit[:, 1:] & lit[:, :-1]
            edges[1:, :] |= (np.linalg.norm(np.diff(c, axis=0), axis=2) > cfg.colour_edge) & lit[1:] & lit[:-1]
        labels, n = ndimage.label(above & ~edges)
        min_px = cfg.min_px * depth.size / (640 * 480)
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        out = []
        for k in np.flatnonzero(sizes >= min_px):
            if k == 0:
                continue
            out.append(np.flatnonzero(labels == k))
        return out

    def _candidates(self, pts: np.ndarray, plane: np.ndarray) -> tuple[np.ndarray, list[Candidate]]:
        """The start of a blob's fits (centred on its points (N, 3) (camera frame, m), axes along its principal
        directions on the plane and the plane's normal) and the parts whose size can explain it."""
        n = plane[:3]
        c = pts.mean(axis=0)
        flat = (pts - c) - np.outer((pts - c) @ n, n)
        major = np.linalg.eigh(flat.T @ flat)[1][:, -1]
        R = np.stack([major, np.cross(n, major), n], axis=1)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, c
        span = np.ptp(flat @ R[:, :2], axis=0)  # footprint along the plane, major axis first (m)
        height = float((pts @ n + plane[3]).max())  # highest point above the plane (m)
        tol = self.cfg.size_tol
        return T, [p for p in self.candidates if np.any((np.abs(p.sizes[:, 0] - height) <= tol) &
                                                        (span[0] <= p.sizes[:, 1] + tol) &
                                                        (span[1] <= p.sizes[:, 2] + tol))]


def _distinct(dets: list[DepthIcpDetection], within: float) -> list[DepthIcpDetection]:
    """``dets`` less each one whose model a more confident one places within ``within`` (m) of it, its mask
    joined to that one's."""
    kept: list[DepthIcpDetection] = []
    for d in sorted(dets, key=lambda d: -d.score):
        k = next((i for i, e in enumerate(kept) if e.obj_id == d.obj_id and
                  np.linalg.norm(e.T_cam_obj[:3, 3] - d.T_cam_obj[:3, 3]) < within), None)
        if k is None:
            kept.append(d)
        else:
            kept[k] = dataclasses.replace(kept[k], mask=kept[k].mask | d.mask)
    return kept
