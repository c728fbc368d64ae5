"""Merged segments split by the fitted model: the part of a mask its object's model does not explain.

The segmentation net is semantic, so two touching blocks often come out as one segment (and one
detection between them). Once a pose is fitted to a segment (pose net + depth refinement), each observed
point of the mask is tested against the model at that pose:

    explained(p) = min_j || R^T (p - t) - m_j || < tol        (p: the pixel's camera-frame point, m_j: model points)

The mask's valid-depth pixels left unexplained, opened by a 3x3 kernel, form connected parts; a part of at
least ``max(min_pixels, min_share x |mask|)`` pixels is another object: it becomes a segment of its own
(classified and fitted like any other), and the first object is fitted again to the rest of its mask, unless the
two fits are the same block (same type, the part's model points within ``same_block`` of the rest's model surface,
in the median: the part was a strip of the block, missed by a slightly wrong first fit), which undoes the split.
Rounds repeat this on the new detections. Points are camera-frame metres; K is the 3x3 intrinsic matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from perception.crop import backproject, padded_box


@dataclass
class SplitConfig:
    """tol (m): an observed point this close to the fitted model's surface is explained by it.
    min_pixels, min_share: an unexplained part must cover at least this many pixels and this share of the
    mask to be split off. same_block (m): a part whose fitted model lies this close to the rest's (median distance
    of its points to the rest's surface) is the same block, and the split is undone. rounds: split passes (0 turns
    splitting off). model_points: surface points per model for the distance test."""

    tol: float = 0.004
    min_pixels: int = 150
    min_share: float = 0.1
    same_block: float = 0.005
    rounds: int = 2
    model_points: int = 20000


class ModelSurface:
    """Distance from an object's surface, from dense surface points (object frame, m)."""

    def __init__(self, points: np.ndarray):
        self.tree = cKDTree(np.asarray(points, dtype=np.float64))

    def explained(self, T_cam_obj: np.ndarray, mask: np.ndarray, depth: np.ndarray, K: np.ndarray,
                  tol: float) -> np.ndarray:
        """Bool (H, W): the pixels of ``mask`` with valid depth (m) whose point lies within ``tol`` (m) of the
        surface placed at ``T_cam_obj`` (4x4, camera frame)."""
        out = np.zeros(depth.shape, dtype=bool)
        box = padded_box(mask, 0)
        if box is None:
            return out
        idx = np.flatnonzero(mask[box] & (depth[box] > 0))  # flat indices into the mask's box
        P = backproject(depth, K, (box[0].start, box[0].stop, box[1].start, box[1].stop), idx)
        dist, _ = self.tree.query((P - T_cam_obj[:3, 3]) @ T_cam_obj[:3, :3], distance_upper_bound=tol)
        out[box].flat[idx[dist < tol]] = True
        return out


def unexplained_parts(mask: np.ndarray, explained: np.ndarray, depth: np.ndarray, cfg: SplitConfig
                      ) -> list[np.ndarray]:
    """The parts (bool (H, W) each) of ``mask`` that its fitted model leaves unexplained and that are large
    enough to be another object (see module docstring)."""
    box = padded_box(mask, 1)  # the opening's and the components' results are the same in it as in the image
    if box is None:
        return []
    rest = (mask[box] & (depth[box] > 0) & ~explained[box]).astype(np.uint8)
    rest = cv2.morphologyEx(rest, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, comp, stats, _ = cv2.connectedComponentsWithStats(rest, connectivity=8)
    least = max(cfg.min_pixels, cfg.min_share * int(mask.sum()))
    parts = []
    for i in range(1, n):
        if stats[i, cv2.CC_STAT_AREA] >= least:
            parts.append(np.zeros_like(mask))
            parts[-1][box] = comp == i
    return parts
