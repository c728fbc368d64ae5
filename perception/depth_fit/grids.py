"""Nearest model points looked up in a voxel grid, and the exact ones searched from there in buckets.

A ``NearestGrid`` stores, for every cell centre c of a voxel grid of side ``cell`` over the model's bounding box
widened by ``margin``, the index of the model point nearest c. A point p in that cell lies within half a cell
diagonal h of c, so the stored point is at most 2 h farther from p than p's true nearest point; points beyond the
grid take the nearest point of its closest cell. An ICP step then costs O(H N) lookups instead of the O(H N M)
distances of an exhaustive search. The exact nearest point lies no farther from p than the stored one, at distance
r: it is found among the model points in the ``Buckets`` (the cubes of a coarser grid, each listing its points)
that the cube p +- r meets. ``Grids`` stacks several objects' grids into one batched lookup. Object frame, metres.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
import torch
from scipy.spatial import cKDTree

from posegrasp.perception.depth_fit.distance_field import DistanceField, Fields, distinct, gather


class NearestGrid:
    """The nearest of the model points (M, 3) (object frame, m) to every cell centre of a voxel grid of side
    ``cell`` (m) over the model's bounding box widened by ``margin`` (m): ``grid(points)`` gives the index of an
    (approximately, within half a cell diagonal) nearest model point of each point (N, 3), object frame. ``field``:
    the model's ``DistanceField``, for the scores' fit term (None: that of the model points, unsigned)."""

    def __init__(self, model: np.ndarray, cell: float = 0.002, margin: float = 0.02,
                 field: DistanceField | None = None):
        if cell <= 0 or margin < 0:
            raise ValueError(f"NearestGrid needs cell > 0 and margin >= 0, got cell={cell}, margin={margin}")
        model = np.asarray(model, dtype=np.float64)
        self.lo = model.min(axis=0) - margin
        self.shape = np.ceil((model.max(axis=0) + margin - self.lo) / cell).astype(int) + 1
        self.cell = cell
        centres = self.lo + np.stack(np.meshgrid(*[np.arange(n) for n in self.shape], indexing="ij"), -1) * cell
        self.index = torch.from_numpy(cKDTree(model).query(centres.reshape(-1, 3))[1].astype(np.int64))  # C order
        self.field = field or DistanceField(model)
        self.buckets = Buckets(model)

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        return Grids([self], 0)(points[None], torch.zeros(1, dtype=torch.long))[0]


class Buckets:
    """The model points (M, 3) (object frame, m) sorted into the cubes of side ``size`` (m) of a grid over their
    bounding box (``shape`` cubes, the first at ``lo``): the points of flat cube k (C order) are ``rows[first[k]:
    first[k + 1]]``. Cubes of at least 4 mm, at most 48 along the longest side."""

    def __init__(self, model: np.ndarray):
        self.lo = model.min(axis=0)
        extent = model.max(axis=0) - self.lo
        self.size = max(0.004, float(extent.max()) / 47.0)
        self.shape = np.floor(extent / self.size).astype(int) + 1
        ijk = np.minimum(np.floor((model - self.lo) / self.size).astype(int), self.shape - 1)
        flat = np.ravel_multi_index(ijk.T, self.shape)
        self.rows = torch.from_numpy(np.argsort(flat, kind="stable").astype(np.int32))
        self.first = torch.from_numpy(np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=int(np.prod(
            self.shape))))]).astype(np.int32))


#: How many stacks of grids ``Grids.of`` keeps.
KEPT = 4
_KEPT: OrderedDict[tuple[tuple[int, ...], int], tuple[list[NearestGrid], Grids]] = OrderedDict()
_KEPT_LOCK = threading.Lock()


class Grids:
    """Several objects' ``NearestGrid``s as one lookup, each distinct grid once (objects of one model share one):
    the u-th distinct grid's points (those of object ``first[u]``'s model) start at row u x ``stride`` of the stacked
    models, and ``grids(points, obj)`` maps points (H, N, 3), row h in the frame of object obj[h], to rows of them
    (the ICP steps, ``icp``, look them up in compiled code). ``fields``: their distance fields."""

    def __init__(self, grids: list[NearestGrid], stride: int):
        self.fields = Fields([g.field for g in grids])
        #: The first object of each distinct grid (objects of one model share one): its model's points are the rows.
        self.first, which = distinct(grids)
        shared = [grids[o] for o in self.first]
        # int32 rows and indices (``gather``)
        self.index = torch.cat([g.index + u * stride for u, g in enumerate(shared)]).int()
        self.start = torch.tensor([0] + [len(g.index) for g in shared[:-1]]).cumsum(0)[which].int()  # (O,)
        self.lo = torch.tensor(np.stack([g.lo for g in grids]), dtype=torch.float32)  # (O, 3)
        self.cell = torch.tensor([g.cell for g in grids], dtype=torch.float32)  # (O,)
        self.max = torch.tensor(np.stack([g.shape - 1 for g in grids]), dtype=torch.float32)  # (O, 3)
        # (O, 3, 1); float32 holds the flat cell indices exactly (fewer than 2^24 cells)
        self.strides = torch.tensor(np.stack([[g.shape[1] * g.shape[2], g.shape[2], 1] for g in grids]),
                                    dtype=torch.float32)[..., None]
        # the buckets of the exact matches: their rows as those of the stacked models, their lists one after another
        b = [g.buckets for g in shared]
        self.bucket_rows = torch.cat([x.rows + u * stride for u, x in enumerate(b)]).int()
        self.bucket_first = torch.cat([x.first + sum(len(y.rows) for y in b[:u]) for u, x in enumerate(b)]).int()
        self.bucket_start = torch.tensor([0] + [len(x.first) for x in b[:-1]]).cumsum(0)[which].int()  # (O,)
        b = [g.buckets for g in grids]
        self.bucket_lo = torch.tensor(np.stack([x.lo for x in b]), dtype=torch.float32)  # (O, 3)
        self.bucket_size = torch.tensor([x.size for x in b], dtype=torch.float32)  # (O,)
        self.bucket_shape = torch.tensor(np.stack([x.shape for x in b]), dtype=torch.int32)  # (O, 3)

    @classmethod
    def of(cls, grids: list[NearestGrid], stride: int) -> Grids:
        """``Grids(grids, stride)``, kept for the last ``KEPT`` lists of grids (the same grid objects, in order): a
        frame's objects are mostly those of the frame before, and stacking their grids and fields, ~10^5 values per
        model, costs ~1 ms. The grids are read only, so a list's stack stays valid; each entry holds its grids, whose
        ids so stay theirs."""
        key = (tuple(map(id, grids)), stride)
        with _KEPT_LOCK:
            hit = _KEPT.get(key)
            if hit is None:
                hit = _KEPT[key] = (list(grids), cls(grids, stride))
                while len(_KEPT) > KEPT:
                    _KEPT.popitem(last=False)
            _KEPT.move_to_end(key)
            return hit[1]

    def __call__(self, points: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        return self.local(points.transpose(1, 2), obj)

    def local(self, points: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        """Rows (H, N) int32 of the nearest model points of points (H, 3, N) in their objects' frames."""
        return self._lookup((points - self.lo[obj, :, None]) / self.cell[obj, None, None], obj)

    def _lookup(self, cells: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        """Rows (H, N) for cell coordinates (H, 3, N)."""
        ijk = torch.minimum(cells.round_().clamp_(min=0), self.max[obj, :, None])  # (H, 3, N), whole numbers
        flat = torch.bmm(self.strides[obj].transpose(1, 2), ijk)[:, 0]  # (H, N): strides . ijk, exact in float32
        return gather(self.index, flat.int() + self.start[obj, None])

