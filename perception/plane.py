"""The supporting plane (table, bin floor) of an RGB-D frame: RANSAC on the depth image's points.

    sample 3 points, plane n . x + d = 0 through them; count inliers |n . x + d| < inlier_tol;
    keep the plane with the most inliers, refit it to them by least squares (smallest principal axis)

n is oriented towards the camera (d > 0: the camera centre lies in front of the plane). Points are
camera-frame metres. Used by the estimator to drop segmented pixels lying on the plane and to rule out
depth-fit starts that sink the object into it.

Given the objects' pixels, the plane is the one they rest on: when the pixels in a band around them lie above the
dominant plane (a tote's floor above the table it stands on, the table filling most of the view), the plane parallel
to it at the band's most common height, refitted to the drawn points within ``inlier_tol`` of it.
"""

from __future__ import annotations

from dataclasses import field

import cv2
import numpy as np

from posegrasp.config import settings, within
from posegrasp.perception.crop import backproject


@settings
class PlaneConfig:
    """Finding the supporting plane by RANSAC, and the plane the objects rest on."""

    #: RANSAC samples.
    iterations: int = field(default=100, metadata=within(1, 1000000))
    #: Depth pixels drawn for it.
    points: int = field(default=2000, metadata=within(3, 100000000))
    #: Distance (m) within which a point is an inlier of a plane.
    inlier_tol: float = field(default=0.004, metadata=within(0, 1))
    #: Share of the image the plane's inliers must cover (a table does; one face of a block seldom), else there is none.
    min_share: float = field(default=0.2, metadata=within(0, 1))
    #: Segmented pixels closer (m) than this to the plane become background (0 keeps them).
    mask_tol: float = field(default=0.002, metadata=within(0, 1))
    #: Median height (m) above the dominant plane of the pixels around the objects beyond which they rest on a plane
    #: above it (a tote's floor; 0: always the dominant plane).
    rest_lift: float = field(default=0.003, metadata=within(0, 1))
    #: Width (px at 640 px image width) of the band around the objects' pixels that finds the plane they rest on.
    rest_band: int = field(default=10, metadata=within(0, 10000))
    #: Share of the drawn points the plane the objects rest on must hold, else the dominant plane stays.
    rest_min_share: float = field(default=0.01, metadata=within(0, 1))


def plane_distance(plane: np.ndarray, depth: np.ndarray, K: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Signed distance (m, positive on the camera's side) from the plane of the points of ``pixels``
    (flat indices into depth (H, W), m)."""
    h, w = depth.shape
    return backproject(depth, K, (0, h, 0, w), pixels) @ plane[:3] + plane[3]


def fit_support_plane(depth: np.ndarray, K: np.ndarray, seed: int = 0, cfg: PlaneConfig | None = None,
                      objects: np.ndarray | None = None) -> np.ndarray | None:
    """The dominant plane (n_x, n_y, n_z, d), |n| = 1, d > 0, of the depth image (m), or None; given the objects'
    pixels ``objects`` (bool (H, W)), the plane they rest on (module doc)."""
    cfg = cfg or PlaneConfig()
    valid = np.flatnonzero(depth > 0)
    if len(valid) < 3:
        return None
    rng = np.random.default_rng(seed)
    h, w = depth.shape
    P = backproject(depth, K, (0, h, 0, w), np.sort(rng.choice(valid, min(cfg.points, len(valid)), replace=False)))
    tri = P[rng.integers(0, len(P), size=(cfg.iterations, 3))]  # (I, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    if not ok.any():
        return None
    n = n[ok] / norm[ok, None]
    d = -np.einsum("ij,ij->i", n, tri[ok, 0])
    dist = P @ n.T  # (N, I)
    dist += d
    counts = (np.abs(dist, out=dist) < cfg.inlier_tol).sum(axis=0)  # (I,)
    best = int(counts.argmax())
    if counts[best] / len(P) * len(valid) < cfg.min_share * depth.size:
        return None
    plane = _refit(P[np.abs(P @ n[best] + d[best]) < cfg.inlier_tol])
    if objects is not None and cfg.rest_lift > 0:
        plane = _resting_plane(plane, P, depth, K, objects, cfg)
    return plane


def _refit(inliers: np.ndarray) -> np.ndarray:
    """The least-squares plane (n, d), d > 0, through points (N, 3): n their least-variance direction."""
    c = inliers.mean(axis=0)
    normal = np.linalg.eigh((inliers - c).T @ (inliers - c))[1][:, 0]
    plane = np.append(normal, -normal @ c)
    return plane if plane[3] > 0 else -plane


def _resting_plane(plane: np.ndarray, P: np.ndarray, depth: np.ndarray, K: np.ndarray, objects: np.ndarray,
                   cfg: PlaneConfig) -> np.ndarray:
    """The plane the objects (bool (H, W)) rest on, from the dominant ``plane`` and the drawn points P (N, 3): the
    plane parallel to it at the most common height (1 mm bins) of the valid pixels in a band ``rest_band`` wide around
    the objects, refitted to the points of P within ``inlier_tol`` of it, when that band lies above ``plane`` by more
    than ``rest_lift`` in the median and the refit holds ``rest_min_share`` of P; else ``plane``."""
    r = max(1, round(cfg.rest_band * depth.shape[1] / 640))
    obj = objects.astype(np.uint8)
    band = (cv2.dilate(obj, np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > obj) & (depth > 0)
    idx = np.flatnonzero(band)
    if idx.size < 3:
        return plane
    h = plane_distance(plane, depth, K, idx)
    if np.median(h) <= cfg.rest_lift:
        return plane
    counts, edges = np.histogram(h, bins=np.arange(cfg.rest_lift, max(h.max(), cfg.rest_lift) + 0.002, 0.001))
    if not counts.any():
        return plane
    lift = 0.5 * (edges[counts.argmax()] + edges[counts.argmax() + 1])
    inl = P[np.abs(P @ plane[:3] + plane[3] - lift) < cfg.inlier_tol]
    return _refit(inl) if len(inl) >= max(3, cfg.rest_min_share * len(P)) else plane


def clear_plane(labels: np.ndarray, depth: np.ndarray, K: np.ndarray, seed: int = 0, cfg: PlaneConfig | None = None
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """The class map ``labels`` (H, W) with its pixels within ``cfg.mask_tol`` of the frame's supporting plane (the
    one its segmented objects rest on) set to 0 (background), and the plane (None, and ``labels`` unchanged, when the
    frame has none)."""
    cfg = cfg or PlaneConfig()
    plane = fit_support_plane(depth, K, seed, cfg, objects=labels > 0)
    if plane is not None and cfg.mask_tol > 0:
        labels = np.where(plane_pixels(plane, depth, K, labels > 0, cfg.mask_tol), 0, labels)
    return labels, plane


def plane_pixels(plane: np.ndarray, depth: np.ndarray, K: np.ndarray, where: np.ndarray, tol: float) -> np.ndarray:
    """Bool (H, W): the pixels of ``where`` (bool (H, W)) with valid depth within ``tol`` (m) of the plane."""
    idx = np.flatnonzero(where & (depth > 0))
    out = np.zeros(depth.shape, dtype=bool)
    out.flat[idx[np.abs(plane_distance(plane, depth, K, idx)) < tol]] = True
    return out
