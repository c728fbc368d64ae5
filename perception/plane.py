"""The supporting plane (table, bin floor) of an RGB-D frame: RANSAC on the depth image's points.

    sample 3 points, plane n . x + d = 0 through them; count inliers |n . x + d| < inlier_tol;
    keep the plane with the most inliers, refit it to them by least squares (smallest principal axis)

n is oriented towards the camera (d > 0: the camera centre lies in front of the plane). Points are
camera-frame metres. Used by the estimator to drop segmented pixels lying on the plane and to rule out
depth-refinement hypotheses that sink the object into it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from posegrasp.perception.crop import backproject


@dataclass
class PlaneConfig:
    """iterations: RANSAC samples. points: depth pixels drawn for it. inlier_tol (m). min_share: the plane's
    inliers must cover at least this share of the image (a table does; one face of a block seldom), else
    there is no supporting plane.
    mask_tol (m): segmented pixels closer than this to the plane become background (0 keeps them)."""

    iterations: int = 100
    points: int = 2000
    inlier_tol: float = 0.004
    min_share: float = 0.2
    mask_tol: float = 0.002


def plane_distance(plane: np.ndarray, depth: np.ndarray, K: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Signed distance (m, positive on the camera's side) from the plane of the points of ``pixels``
    (flat indices into depth (H, W), m)."""
    h, w = depth.shape
    return backproject(depth, K, (0, h, 0, w), pixels) @ plane[:3] + plane[3]


def fit_support_plane(depth: np.ndarray, K: np.ndarray, seed: int = 0, cfg: PlaneConfig | None = None
                      ) -> np.ndarray | None:
    """The dominant plane (n_x, n_y, n_z, d), |n| = 1, d > 0, of the depth image (m), or None."""
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
    counts = (np.abs(P @ n.T + d) < cfg.inlier_tol).sum(axis=0)  # (I,)
    best = int(counts.argmax())
    if counts[best] / len(P) * len(valid) < cfg.min_share * depth.size:
        return None
    inl = P[np.abs(P @ n[best] + d[best]) < cfg.inlier_tol]
    c = inl.mean(axis=0)
    normal = np.linalg.eigh((inl - c).T @ (inl - c))[1][:, 0]  # the least-variance direction
    plane = np.append(normal, -normal @ c)
    return plane if plane[3] > 0 else -plane


def clear_plane(labels: np.ndarray, depth: np.ndarray, K: np.ndarray, seed: int = 0, cfg: PlaneConfig | None = None
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """The class map ``labels`` (H, W) with its pixels within ``cfg.mask_tol`` of the frame's supporting plane set to
    0 (background), and the plane (None, and ``labels`` unchanged, when the frame has none)."""
    cfg = cfg or PlaneConfig()
    plane = fit_support_plane(depth, K, seed, cfg)
    if plane is not None and cfg.mask_tol > 0:
        labels = np.where(plane_pixels(plane, depth, K, labels > 0, cfg.mask_tol), 0, labels)
    return labels, plane


def plane_pixels(plane: np.ndarray, depth: np.ndarray, K: np.ndarray, where: np.ndarray, tol: float) -> np.ndarray:
    """Bool (H, W): the pixels of ``where`` (bool (H, W)) with valid depth within ``tol`` (m) of the plane."""
    idx = np.flatnonzero(where & (depth > 0))
    out = np.zeros(depth.shape, dtype=bool)
    out.flat[idx[np.abs(plane_distance(plane, depth, K, idx)) < tol]] = True
    return out
