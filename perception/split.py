"""Merged segments split by the fitted model: the part of a mask its object's model does not explain.

The segmentation net is semantic, so two touching blocks often come out as one segment (and one
detection between them). Once a pose is fitted to a segment (pose net + depth fit), each observed
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

from dataclasses import field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from posegrasp.config import settings, within
from posegrasp.perception.crop import backproject, padded_box


@settings
class SplitConfig:
    """Splitting a mask into the blocks it holds, and dropping duplicate detections."""

    #: An observed point this close (m) to the fitted model's surface is explained by it.
    tol: float = field(default=0.004, metadata=within(0, 1))
    #: An unexplained part must cover at least this many pixels to be split off ...
    min_pixels: int = field(default=150, metadata=within(0, 100000000))
    #: ... and this share of the mask.
    min_share: float = field(default=0.1, metadata=within(0, 1))
    #: A part fitted this close (m) to the rest's model is the same block; the split is undone.
    same_block: float = field(default=0.005, metadata=within(0, 1))
    #: Split passes; 0 turns splitting and duplicate dropping off.
    rounds: int = field(default=2, metadata=within(0, 100))
    #: Surface points per model for the distance test.
    model_points: int = field(default=20000, metadata=within(1, 100000000))
    #: Two detections of one type closer than this share of the block's smallest side are one; 0: never.
    duplicate: float = field(default=0.5, metadata=within(0, 100))


class ModelSurface:
    """Distance from an object's surface, from dense surface points (object frame, m).

    ``explained`` first looks each point up in a voxel grid (side ``cell``) of the distance d(c) from every cell
    centre c to the surface: a point p in the cell lies within half the cell diagonal h of c, so
    |d(p) - d(c)| <= h, and the test d(p) < tol is settled without a search when d(c) + h < tol or d(c) - h >= tol.
    Only points in the cells between (and none outside the grid, which covers the model's bounding box widened by
    tol: all farther) are searched in a k-d tree. The result is exactly the k-d tree's on every point."""

    def __init__(self, points: np.ndarray, cell: float = 0.002):
        if cell <= 0:
            raise ValueError(f"ModelSurface needs cell > 0, got {cell}")
        self.points = np.asarray(points, dtype=np.float64)
        self.tree = cKDTree(self.points)
        self.cell = cell
        self._grids: dict[float, tuple[np.ndarray, np.ndarray]] = {}  # tol -> (grid origin (3,), cell states)

    def _grid(self, tol: float) -> tuple[np.ndarray, np.ndarray]:
        """Origin (3,) and states (I, J, K) int8 of the grid for ``tol``: 1 every point of the cell is within tol,
        0 none is, -1 search."""
        if tol not in self._grids:
            lo = self.points.min(axis=0) - tol
            shape = np.ceil((self.points.max(axis=0) + tol - lo) / self.cell).astype(int)
            centres = lo + (np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1) + 0.5) * self.cell
            d = self.tree.query(centres.reshape(-1, 3))[0].reshape(shape)
            h, eps = self.cell * np.sqrt(3) / 2, 1e-9  # eps: float rounding never settles a point wrongly
            self._grids[tol] = lo, np.where(d + h < tol - eps, 1, np.where(d - h >= tol + eps, 0, -1)).astype(np.int8)
        return self._grids[tol]

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
        local = (P - T_cam_obj[:3, 3]) @ T_cam_obj[:3, :3]  # object frame
        lo, states = self._grid(tol)
        ijk = np.floor((local - lo) / self.cell).astype(np.int64)
        i, j, k = ijk.T
        n0, n1, n2 = states.shape
        u = ijk.view(np.uint64)  # a negative index wraps to above any grid size
        inside = (u[:, 0] < n0) & (u[:, 1] < n1) & (u[:, 2] < n2)
        state = np.zeros(len(idx), dtype=np.int8)  # outside the grid: farther than tol
        state[inside] = states.ravel()[((i * n1 + j) * n2 + k)[inside]]
        search = np.flatnonzero(state < 0)
        state[search] = self.tree.query(local[search], distance_upper_bound=tol)[0] < tol
        out[box].flat[idx[state > 0]] = True
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
    least = max(cfg.min_pixels, cfg.min_share * int(mask[box].sum()))
    parts = []
    for i in range(1, n):
        if stats[i, cv2.CC_STAT_AREA] >= least:
            parts.append(np.zeros_like(mask))
            parts[-1][box] = comp == i
    return parts


def same_place(points: np.ndarray, T_a: np.ndarray, surface: ModelSurface, T_b: np.ndarray, tol: float) -> bool:
    """Whether a model's points (M, 3) (object frame) placed at T_a (4x4, camera frame) lie, in the median, within
    ``tol`` (m) of the block's ``surface`` placed at T_b: the two poses put one block in one place."""
    placed = points @ T_a[:3, :3].T + T_a[:3, 3]  # camera frame
    # distances of tol or more come back as inf: the median is below tol exactly when it was, and far points cost less
    dist, _ = surface.tree.query((placed - T_b[:3, 3]) @ T_b[:3, :3], distance_upper_bound=tol)
    return float(np.median(dist)) < tol


def drop_duplicates(dets: list, sides: dict[int, float], duplicate: float) -> list:
    """``dets`` (each with ``obj_id``, ``T_cam_obj`` (4x4, camera frame, m) and ``mask``) without those fitted where a
    detection of the same type with a larger mask sits: their centres closer than ``duplicate`` x the block's smallest
    side (``sides``, m, by obj_id), which two blocks cannot be (one block seen as two segments, or split in two);
    ``duplicate`` 0 drops none. The order is kept."""
    if duplicate <= 0:
        return dets
    kept: list = []
    for d in sorted(dets, key=lambda d: -int(d.mask.sum())):
        if all(k.obj_id != d.obj_id or np.linalg.norm(k.T_cam_obj[:3, 3] - d.T_cam_obj[:3, 3]) >=
               duplicate * sides[d.obj_id] for k in kept):
            kept.append(d)
    return [d for d in dets if any(d is k for k in kept)]
