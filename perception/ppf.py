"""Point pair features (Drost et al. 2010) on OpenCV's detector: a training-free pose estimator for any object set.

1. Models: each mesh sampled with its face normals, averaged in voxels of ``sampling`` x its diameter, and an OpenCV
   ``ppf_match_3d.PPF3DDetector`` trained on it (``angles`` bins), once per estimator (OpenCV cannot save one).
2. Scene: the median-filtered depth image's points with normals from the pixels ``normal_px`` away, less those seen
   more obliquely than ``max_incidence_deg``, those within ``min_height`` of the plane the parts rest on (the
   dominant plane, or a parallel one above it covering ``floor_share``: a tote's floor) and wide planar patches
   (``scenery``: a tote's rim); cut into blobs of touching pixels (at least ``min_px``), a wide blob into tiles.
3. Votes: each model is matched to each blob; every ``ref_step``-th scene point votes for the model point and turn
   that explain its pairs, giving one pose per reference point with its votes.
4. Hypotheses: a blob's poses of a model, most votes first, grouped when their centres lie within ``cluster_dist`` x
   the diameter and their rotations within ``cluster_deg`` under the object's symmetries; the ``hypotheses`` groups
   with most votes go on, each as its best pose.
5. Verification: the model's points facing the camera (as the scene's, within ``max_incidence_deg``), projected
   into the depth image: inliers lie within
   ``inlier_dist`` of the seen depth, violations in front of it or ``sink_dist`` under the plane; score = (inliers -
   ``violation_weight`` x violations) / points inside the image; support: the surface area the inliers stand for.
6. Refinement: the ``refined`` best by score x support^``support_power`` (first with inliers within ``coarse_dist``,
   votes being a step and an angle bin off), at least ``min_score`` / 2, are refined (``refine``: the depth fit of
   ``perception.depth_fit`` or OpenCV's ``ICP``) on the blob's points near them, and scored again.
7. Instances: best first, a hypothesis is kept when its score reaches ``min_score`` and at most ``overlap`` of its
   inlier pixels belong to those kept before it: one estimate per part.

It reads nothing but the depth image, K and the object set's models and symmetries. Points are camera-frame metres
(OpenCV: x right, y down, z forward); OpenCV is given millimetres (its own pose clustering is by an absolute
distance that in mm keeps every pose apart: step 4 groups them).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.config import settings, within
from posegrasp.errors import ConfigError
from posegrasp.perception.crop import seen_facing
from posegrasp.perception.depth_fit import DepthFitConfig, FitConfig, ObjectModel, StartConfig, TurnConfig, fit_poses
from posegrasp.perception.plane import PlaneConfig, fit_support_plane, plane_distance
from posegrasp.perception.runtime import torch_threads

MM = 1000.0  #: OpenCV's detector and ICP work in mm
REFINERS = ("icp", "depth-fit", "none")  #: ``PpfConfig.refine``'s values


@settings
class PpfConfig:
    """The point-pair-feature estimator (``--perception ppf``): sampling, votes, hypotheses, verification."""

    #: Sampling step of model and scene points, and the pair distance step, as a fraction of the model's diameter.
    sampling: float = field(default=0.07, metadata=within(0.01, 0.5))
    #: Angle bins over 360 deg of the pair features' angles and of the turn about the normal.
    angles: int = field(default=30, metadata=within(4, 360))
    #: Every ref_step-th scene point (in the voxel order) is a reference point that votes.
    ref_step: int = field(default=5, metadata=within(1, 1000))
    #: Pixels (at 640 px width) between a pixel and the neighbours whose points give its normal.
    normal_px: int = field(default=3, metadata=within(1, 50))
    #: Side (px) of the median filter on the depth image before points and normals: 0 (none), 3 or 5.
    median_px: int = field(default=5, metadata=within(0, 5))
    #: Largest angle (deg) between a point's normal and its ray back to the camera: surfaces seen more obliquely
    #: (a tote's walls, noisy) are dropped.
    max_incidence_deg: float = field(default=75.0, metadata=within(0, 90))
    #: Height (m) above the supporting plane from which a point belongs to a part (0: no plane, all points).
    min_height: float = field(default=0.003, metadata=within(0, 1))
    #: Share of the image a plane parallel to the dominant one and above it must cover to be the one the parts rest on
    #: (a tote's floor above the table).
    floor_share: float = field(default=0.1, metadata=within(0, 1))
    #: Dense planar patches (2000 touching pixels at 640x480 within 3 mm of a plane) wider than this x the set's
    #: largest diameter are scenery (a tote's rim and walls), not parts: they are dropped (0: keep them).
    scenery: float = field(default=1.5, metadata=within(0, 1000))
    #: Fewest pixels (at 640x480) of a blob; smaller ones are dropped.
    min_px: int = field(default=100, metadata=within(1, 100000000))
    #: Poses of a model whose centres lie within this x its diameter (and rotations within cluster_deg) are one group.
    cluster_dist: float = field(default=0.1, metadata=within(0, 10))
    #: Rotation (deg, up to the object's symmetries) within which two poses are one group.
    cluster_deg: float = field(default=20.0, metadata=within(0, 180))
    #: Groups of most votes per blob and model that are verified.
    hypotheses: int = field(default=6, metadata=within(1, 10000))
    #: Distance (m) along the ray within which a model point is an inlier of the seen depth.
    inlier_dist: float = field(default=0.004, metadata=within(1e-6, 1))
    #: The inlier distance (m) of the first verification, which chooses the hypotheses refined (votes give poses a
    #: sampling step and an angle bin off).
    coarse_dist: float = field(default=0.012, metadata=within(1e-6, 1))
    #: Weight of the share of model points in front of the seen depth (seen free space) in the score.
    violation_weight: float = field(default=2.0, metadata=within(0, 100))
    #: Depth (m) beneath the supporting plane from which a model point is a violation (the part sinks into it).
    sink_dist: float = field(default=0.002, metadata=within(0, 1))
    #: Hypotheses are ranked by score x support^support_power (support: the model's surface area its inliers stand
    #: for; 0: by score alone, which prefers a small part fitting inside a larger one).
    support_power: float = field(default=1.0, metadata=within(0, 10))
    #: Least score of a detection; hypotheses from half of it are refined.
    min_score: float = field(default=0.3, metadata=within(0, 1))
    #: Share of a detection's inlier pixels that detections kept before it may hold (more: the same part).
    overlap: float = field(default=0.3, metadata=within(0, 1))
    #: How hypotheses are refined: "icp" (OpenCV's point-to-plane ICP), "depth-fit" (``perception.depth_fit``, with
    #: the settings ``depth_fit``) or "none".
    refine: str = "depth-fit"
    #: Iterations of OpenCV's ICP per refined hypothesis.
    icp_iterations: int = field(default=20, metadata=within(1, 10000))
    #: Hypotheses refined per frame at most, best first (score x support^support_power).
    refined: int = field(default=200, metadata=within(1, 100000))
    #: Surface points per model for the verification.
    verify_points: int = field(default=1000, metadata=within(10, 10000000))
    #: The depth fit of ``refine = "depth-fit"``: from each hypothesis (and it laid on its nearest rest), yaw and
    #: pattern searches, on the blob's points within ``coarse_dist`` of it.
    depth_fit: DepthFitConfig = field(default_factory=lambda: DepthFitConfig(
        starts=StartConfig(hypotheses="identity"), turns=TurnConfig(step_deg=0), fit=FitConfig(max_points=200)))

    def __post_init__(self) -> None:
        if self.refine not in REFINERS:
            raise ConfigError(f"PpfConfig.refine = {self.refine!r}: use one of {', '.join(REFINERS)}")
        if self.median_px in (2, 4):
            raise ConfigError(f"PpfConfig.median_px = {self.median_px}: use 0, 3 or 5")


@dataclass(frozen=True)
class PpfModel:
    """One object as the estimator knows it: its id, diameter (m), surface area (m^2), voxel step (m), trained
    detector, its sampled points with normals (N, 6) (object frame, m), verification points and normals (V, 3) each,
    and symmetry rotations (S, 3, 3) (identity first) and continuous axes (A, 3)."""

    obj_id: int
    diameter: float
    area: float
    step: float
    detector: cv2.ppf_match_3d.PPF3DDetector
    cloud: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    symmetries: np.ndarray
    axes: np.ndarray


@dataclass(frozen=True)
class PpfDetection:
    """One part found: its model's id, pose T_cam_obj (4, 4) (m, camera frame), score in [0, 1] and inlier pixel
    mask (H, W) bool."""

    obj_id: int
    T_cam_obj: np.ndarray
    score: float
    mask: np.ndarray


def voxel_mean(points: np.ndarray, normals: np.ndarray, step: float) -> np.ndarray:
    """Points (N, 3) with normals (N, 3) averaged in the voxels of side ``step`` (m) they fall in: (M, 6), unit
    normals, in voxel order."""
    keys = np.floor(points / step).astype(np.int64)
    _, inv, count = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    out = np.zeros((len(count), 6))
    np.add.at(out, inv, np.hstack([points, normals]))
    out[:, :3] /= count[:, None]
    out[:, 3:] /= np.maximum(np.linalg.norm(out[:, 3:], axis=1, keepdims=True), 1e-12)
    return out


def train_model(mesh, info: bop.ObjectInfo, obj_id: int, cfg: PpfConfig) -> PpfModel:
    """The ``PpfModel`` of a mesh (object frame, m) with its BOP info (diameter, symmetries); seeded by obj_id."""
    import trimesh

    dense, faces = trimesh.sample.sample_surface(mesh, max(20000, 4 * cfg.verify_points), seed=obj_id)
    normals = np.asarray(mesh.face_normals)[faces]
    step = cfg.sampling * info.diameter
    cloud = voxel_mean(np.asarray(dense), normals, step)
    detector = cv2.ppf_match_3d.PPF3DDetector(cfg.sampling, cfg.sampling, cfg.angles)
    detector.trainModel(_mm(cloud))
    pick = np.random.default_rng(obj_id).choice(len(dense), cfg.verify_points, replace=False)
    disc, axes = info.symmetry_rotations()
    syms = np.concatenate([np.eye(3)[None], np.asarray(disc, dtype=np.float64).reshape(-1, 3, 3)])
    return PpfModel(obj_id, info.diameter, float(mesh.area), step, detector, cloud, np.asarray(dense)[pick],
                    normals[pick], syms, np.asarray(axes, dtype=np.float64).reshape(-1, 3))


def _mm(cloud: np.ndarray) -> np.ndarray:
    """A cloud (N, 6) in m with normals as OpenCV's float32 (N, 6) in mm."""
    return np.hstack([cloud[:, :3] * MM, cloud[:, 3:]]).astype(np.float32)


@dataclass(frozen=True)
class _Scene:
    """A frame as the estimator sees it: its points (H, W, 3) and normals (H, W, 3) (camera frame, m; normals facing
    the camera), the pixels that may belong to parts (H, W) bool, depth (H, W) (m), K (3, 3) and the plane the parts
    rest on (4,: n . x + d = 0, n towards the camera) or None."""

    points: np.ndarray
    normals: np.ndarray
    usable: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    plane: np.ndarray | None = None


def scene_of(depth: np.ndarray, K: np.ndarray, cfg: PpfConfig, seed: int = 0, size: float = 0.0) -> _Scene:
    """The points, normals and usable pixels of a depth image (H, W) (m, 0: none) seen through K (3, 3), for parts
    of at most ``size`` (m) across (0: no scenery dropped)."""
    depth, K = np.asarray(depth, np.float32), np.asarray(K, np.float64)
    if cfg.median_px > 1:  # the sensor's noise tilts normals of neighbouring points by tens of degrees
        depth = np.where(depth > 0, cv2.medianBlur(depth, cfg.median_px), 0.0).astype(np.float32)
    depth = depth.astype(np.float64)
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    P = np.stack([(u - K[0, 2]) * depth / K[0, 0], (v - K[1, 2]) * depth / K[1, 1], depth], axis=-1)
    r = max(1, round(cfg.normal_px * w / 640))
    dx, dy = np.zeros_like(P), np.zeros_like(P)
    dx[:, r:-r], dy[r:-r] = P[:, 2 * r:] - P[:, :-2 * r], P[2 * r:] - P[:-2 * r]
    ok = depth > 0
    near = np.zeros_like(ok)  # both neighbours of each direction seen, and on the same surface (no depth step)
    near[r:-r, r:-r] = ok[r:-r, 2 * r:] & ok[r:-r, :-2 * r] & ok[2 * r:, r:-r] & ok[:-2 * r, r:-r]
    step = 4.0 * r * depth / K[0, 0] + 0.004  # the neighbours' span on a surface tilted up to ~60 deg, plus noise
    near &= (np.abs(dx[..., 2]) < step) & (np.abs(dy[..., 2]) < step)
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = n / np.maximum(norm, 1e-12)
    n = np.where((np.einsum("hwk,hwk->hw", n, P) > 0)[..., None], -n, n)  # facing the camera
    facing = -np.einsum("hwk,hwk->hw", n, P) / np.maximum(np.linalg.norm(P, axis=-1), 1e-12)
    usable = ok & near & (norm[..., 0] > 0) & (facing > np.cos(np.radians(cfg.max_incidence_deg)))
    plane = _support(depth, K, seed, cfg.floor_share) if cfg.min_height > 0 else None
    if plane is not None:
        usable &= (P.reshape(-1, 3) @ plane[:3] + plane[3]).reshape(h, w) > cfg.min_height
    if cfg.scenery > 0 and size > 0:
        _drop_scenery(P, depth, K, usable, cfg.scenery * size, seed)
    return _Scene(P, n, usable, depth, K, plane)


def _support(depth: np.ndarray, K: np.ndarray, seed: int, floor_share: float) -> np.ndarray | None:
    """The plane the parts rest on, or None: the dominant plane of the depth image (m), or a plane above it and
    parallel to it (within 10 deg) covering ``floor_share`` of the image (a tote's floor above the table)."""
    plane = fit_support_plane(depth, K, seed)
    if plane is None:
        return None
    valid = np.flatnonzero(depth > 0)
    above = np.zeros(depth.size, dtype=bool)
    above[valid] = plane_distance(plane, depth, K, valid) > 0.005
    floor = fit_support_plane(np.where(above.reshape(depth.shape), depth, 0.0), K, seed,
                              PlaneConfig(min_share=floor_share)) if floor_share > 0 else None
    if floor is not None and abs(float(floor[:3] @ plane[:3])) > np.cos(np.radians(10.0)):
        return floor
    return fit_support_plane(depth, K, seed, objects=above.reshape(depth.shape))


def _drop_scenery(P: np.ndarray, depth: np.ndarray, K: np.ndarray, usable: np.ndarray, width: float,
                  seed: int, planes: int = 6) -> None:
    """Mark unusable, in place, the dense patches of touching pixels (at least 2000 at 640x480) within 3 mm of each
    of ``planes`` planes fitted in turn to the usable pixels' points P (H, W, 3) (m) that span more than ``width``
    (m): a tote's rim and walls, not parts."""
    left = usable.copy()
    least = 2000 * depth.size / (640 * 480)
    for _ in range(planes):
        plane = fit_support_plane(np.where(left, depth, 0.0), K, seed, PlaneConfig(min_share=0.005))
        if plane is None:
            return
        on = left & (np.abs(P @ plane[:3] + plane[3]) < 0.003)
        left &= ~on
        labels, n = ndimage.label(on, structure=np.ones((3, 3)))
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        usable &= ~np.isin(labels, [k for k in range(1, n + 1)
                                    if sizes[k] >= least and np.ptp(P[labels == k], axis=0).max() > width])


def blobs(scene: _Scene, min_px: int) -> list[np.ndarray]:
    """Flat pixel indices of each blob of touching usable pixels with at least ``min_px`` pixels (at 640x480)."""
    labels, n = ndimage.label(scene.usable, structure=np.ones((3, 3)))
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    least = min_px * scene.depth.size / (640 * 480)
    order = np.argsort(labels.ravel(), kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)])
    return [order[starts[k]:starts[k + 1]] for k in range(1, n + 1) if sizes[k] >= least]


def rotation_gaps(R: np.ndarray, Rs: np.ndarray, model: PpfModel) -> np.ndarray:
    """Angles (rad) between the rotation R (3, 3) and each of Rs (N, 3, 3) up to the model's symmetries: the least
    over its discrete symmetries S of angle(R S, R_n); with a continuous axis a, the angle between R S a and R_n a."""
    if len(model.axes):
        a = model.axes[0]
        ref = np.einsum("ij,sj->si", R, model.symmetries @ a)  # (S, 3)
        cos = np.einsum("nij,j,si->ns", Rs, a, ref)
    else:
        RS = R @ model.symmetries  # (S, 3, 3)
        cos = (np.einsum("sij,nij->ns", RS, Rs) - 1.0) / 2.0
    return np.arccos(np.clip(cos.max(axis=1), -1.0, 1.0))


def cluster(poses: np.ndarray, votes: np.ndarray, model: PpfModel, cfg: PpfConfig) -> list[tuple[np.ndarray, int]]:
    """The groups of poses (N, 4, 4) (m) with their votes (N,): (its best pose, summed votes) for the ``hypotheses``
    groups with most votes (module doc, step 4)."""
    order = np.argsort(-votes, kind="stable")
    poses, votes = poses[order], votes[order]
    free = np.ones(len(poses), dtype=bool)
    out = []
    for i in range(len(poses)):
        if not free[i]:
            continue
        near = free & (np.linalg.norm(poses[:, :3, 3] - poses[i, :3, 3], axis=1) < cfg.cluster_dist * model.diameter)
        idx = np.flatnonzero(near)
        same = idx[rotation_gaps(poses[i, :3, :3], poses[idx, :3, :3], model) < np.radians(cfg.cluster_deg)]
        free[same] = False
        out.append((poses[i], int(votes[same].sum())))
    out.sort(key=lambda g: -g[1])
    return out[:cfg.hypotheses]


def verify(T: np.ndarray, model: PpfModel, scene: _Scene, cfg: PpfConfig, tol: float
           ) -> tuple[float, np.ndarray, float]:
    """The score of the model at pose T (4, 4) (m) against the seen depth with inlier distance ``tol`` (m; module
    doc, step 5), the flat indices of its inlier pixels and its support: the model's surface area (m^2) those inliers
    stand for."""
    p, pix, d = seen_facing(model.points, model.normals, T, scene.K, scene.depth,  # as the scene's points
                            np.cos(np.radians(cfg.max_incidence_deg)))
    if not len(pix):
        return 0.0, np.zeros(0, dtype=np.int64), 0.0
    sunk = np.zeros(len(p), dtype=bool) if scene.plane is None else \
        p @ scene.plane[:3] + scene.plane[3] < -cfg.sink_dist
    z, seen = p[:, 2], d > 0
    inlier = seen & (np.abs(z - d) < tol)
    violation = (seen & (z < d - tol)) | sunk
    score = (inlier.sum() - cfg.violation_weight * violation.sum()) / len(pix)
    return float(max(score, 0.0)), np.unique(pix[inlier]), float(inlier.sum() / len(model.points) * model.area)


def refine(T: np.ndarray, model: PpfModel, cloud: np.ndarray, icp: cv2.ppf_match_3d.ICP) -> np.ndarray:
    """T (4, 4) (m) fitted by OpenCV's point-to-plane ICP: the model's points facing the camera at T to the scene's
    points with normals ``cloud`` (N, 6) (camera frame, m) within its diameter."""
    src = np.hstack([model.cloud[:, :3] @ T[:3, :3].T + T[:3, 3], model.cloud[:, 3:] @ T[:3, :3].T])
    src = src[np.einsum("ij,ij->i", src[:, 3:], src[:, :3]) < 0]
    dst = cloud[np.linalg.norm(cloud[:, :3] - T[:3, 3], axis=1) < model.diameter]
    if len(src) < 6 or len(dst) < 6:
        return T
    _, _, P = icp.registerModelToScene(_mm(src), _mm(dst))
    P = np.asarray(P, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = P[:3, :3] @ T[:3, :3]
    out[:3, 3] = P[:3, :3] @ T[:3, 3] + P[:3, 3] / MM
    U, _, Vt = np.linalg.svd(out[:3, :3])  # float32 ICP: orthonormal again
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out


@dataclass
class _Hypothesis:
    """A pose of a model in a blob with its verification (``verify``)."""

    model: PpfModel
    T: np.ndarray
    blob: int
    score: float = 0.0
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    support: float = 0.0
    rank: float = 0.0  # its order among the frame's hypotheses: score x support^support_power

    def check(self, scene: _Scene, cfg: PpfConfig, tol: float) -> None:
        """Score it against the scene with inlier distance ``tol`` (m; ``verify``)."""
        self.score, self.inliers, self.support = verify(self.T, self.model, scene, cfg, tol)
        self.rank = self.score * self.support ** cfg.support_power


class Ppf:
    """The estimator of ``models`` (a BOP models root: ``models/models_info.json`` and PLY files in mm).
    ``est(depth, K, seed)`` -> detections (module doc). Training takes about a second per model."""

    def __init__(self, models: str | Path, cfg: PpfConfig | None = None):
        self.cfg = cfg or PpfConfig()
        infos = bop.load_models_info(models)
        self.models = [train_model(bop_models.load_model(models, o), info, o, self.cfg)
                       for o, info in sorted(infos.items())]
        self.icp = cv2.ppf_match_3d.ICP(self.cfg.icp_iterations)
        self.fit_models = {o: ObjectModel.of_mesh(bop_models.load_model(models, o), info.symmetry_rotations(),
                                                  self.cfg.depth_fit, seed=o)
                           for o, info in sorted(infos.items())} if self.cfg.refine == "depth-fit" else {}

    def __call__(self, depth: np.ndarray, K: np.ndarray, seed: int = 0) -> list[PpfDetection]:
        """The parts seen in a depth image (H, W) (m, 0: none) through K (3, 3)."""
        return _instances(self.hypotheses(depth, K, seed), np.shape(depth), self.cfg)

    def hypotheses(self, depth: np.ndarray, K: np.ndarray, seed: int = 0) -> list[_Hypothesis]:
        """The refined hypotheses of a depth image, best first (module doc, steps 2-6)."""
        cfg = self.cfg
        scene = scene_of(depth, K, cfg, seed, max(m.diameter for m in self.models))
        clouds, hyps = [], []
        for b, idx in enumerate(blobs(scene, cfg.min_px)):
            pts, nrm = scene.points.reshape(-1, 3)[idx], scene.normals.reshape(-1, 3)[idx]
            clouds.append(voxel_mean(pts, nrm, min(m.step for m in self.models) / 2))
            hyps += [_Hypothesis(m, T, b) for m in self.models for T, _ in self._votes(m, pts, nrm)]
        for h in hyps:
            h.check(scene, cfg, cfg.coarse_dist)
        hyps = [h for h in sorted(hyps, key=lambda h: -h.rank)[:cfg.refined] if h.score >= cfg.min_score / 2]
        if cfg.refine == "icp":
            fitted = [refine(h.T, h.model, clouds[h.blob], self.icp) for h in hyps]
        elif cfg.refine == "depth-fit":
            fitted = self._depth_fit(hyps, scene, clouds, seed)
        else:
            fitted = [h.T for h in hyps]
        best = []
        for h, T in zip(hyps, fitted):  # a fit may slide onto a neighbour: the better pose stays
            new = _Hypothesis(h.model, T, h.blob)
            for x in (h, new):
                x.check(scene, cfg, cfg.inlier_dist)
            best.append(new if new.rank >= h.rank else h)
        return sorted(best, key=lambda h: -h.rank)

    def _depth_fit(self, hyps: list[_Hypothesis], scene: _Scene, clouds: list[np.ndarray], seed: int
                   ) -> list[np.ndarray]:
        """Each hypothesis' pose fitted by the depth fit to its blob's points within ``coarse_dist`` of it (its own
        pose where there are fewer than 3), all in one batch."""
        from scipy.spatial import cKDTree

        rng = np.random.default_rng(seed)
        rows = []
        for i, h in enumerate(hyps):
            cloud = clouds[h.blob][:, :3]
            near = cKDTree(h.model.points @ h.T[:3, :3].T + h.T[:3, 3]).query(
                cloud, distance_upper_bound=self.cfg.coarse_dist)[0]
            seen = cloud[np.isfinite(near)]
            if len(seen) >= 3:
                n = min(len(seen), self.cfg.depth_fit.fit.max_points)
                rows.append((i, seen[np.sort(rng.choice(len(seen), n, replace=False))]))
        out = [h.T for h in hyps]
        if not rows:
            return out
        with torch_threads(1):  # small batched ops: threads only add overhead
            fits = fit_poses([hyps[i].T for i, _ in rows], [self.fit_models[hyps[i].model.obj_id] for i, _ in rows],
                             [seen for _, seen in rows], scene.depth, scene.K, self.cfg.depth_fit, scene.plane)
        for (i, _), (T, _) in zip(rows, fits):
            out[i] = T
        return out

    def _votes(self, model: PpfModel, pts: np.ndarray, nrm: np.ndarray) -> list[tuple[np.ndarray, int]]:
        """The hypotheses of ``model`` in a blob's points (N, 3) with normals (N, 3) (module doc, steps 3 and 4)."""
        poses, votes = [], []
        for cloud in tiles(voxel_mean(pts, nrm, model.step), model.diameter):
            extent = np.ptp(cloud[:, :3], axis=0)
            cloud[0, :3] += (extent < 1e-6) * 1e-5  # OpenCV's grid divides by each axis' range: none may be empty
            rel = float(np.clip(model.step / 2 / max(float(extent.max()), 1e-9), 0.01, 1.0))  # its grid: finer
            found = model.detector.match(_mm(cloud), 1.0 / self.cfg.ref_step, rel)
            poses += [np.asarray(r.pose, dtype=np.float64) for r in found]
            votes += [r.numVotes for r in found]
        if not poses:
            return []
        poses = np.array(poses)
        poses[:, :3, 3] /= MM
        return cluster(poses, np.array(votes), model, self.cfg)


def tiles(cloud: np.ndarray, diameter: float) -> list[np.ndarray]:
    """A blob's points with normals (N, 6) (m) in pieces that a part of ``diameter`` (m) lies wholly within one of:
    itself if it spans at most 3 diameters along x and y, else squares of 2 diameters widened by half of one on
    each side (pairs of points farther apart than a part cannot vote for it: they only cost time). Pieces of fewer
    than 10 points are left out."""
    lo, hi = cloud[:, :2].min(axis=0), cloud[:, :2].max(axis=0)
    if (hi - lo).max() <= 3 * diameter:
        return [cloud] if len(cloud) >= 10 else []
    out = []
    for x in np.arange(lo[0], hi[0], 2 * diameter):
        for y in np.arange(lo[1], hi[1], 2 * diameter):
            inside = np.all((cloud[:, :2] >= (x - diameter / 2, y - diameter / 2)) &
                            (cloud[:, :2] < (x + 2.5 * diameter, y + 2.5 * diameter)), axis=1)
            if inside.sum() >= 10:
                out.append(cloud[inside])
    return out


def _instances(hyps: list[_Hypothesis], shape: tuple[int, int], cfg: PpfConfig) -> list[PpfDetection]:
    """The hypotheses (best score first) kept as detections (module doc, step 7)."""
    claimed = np.zeros(shape, dtype=np.uint8)  # the kept detections' inlier pixels, grown to touch
    r = max(1, round(4 * shape[1] / 640))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    out = []
    for h in hyps:
        if h.score < cfg.min_score or not len(h.inliers) or claimed.flat[h.inliers].mean() > cfg.overlap:
            continue
        mask = np.zeros(shape, dtype=np.uint8)
        mask.flat[h.inliers] = 1
        mask = cv2.dilate(mask, kernel)
        claimed |= mask
        out.append(PpfDetection(h.model.obj_id, h.T, h.score, mask.astype(bool)))
    return out
