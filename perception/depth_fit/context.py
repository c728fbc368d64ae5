"""The context of one frame's depth fit: its objects' models and observed points as batched tensors."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import torch

from posegrasp.perception.depth_fit.grids import Grids
from posegrasp.perception.depth_fit.model import ObjectModel
from posegrasp.perception.depth_fit.starts import Symmetries, stacked_rests

if TYPE_CHECKING:
    from posegrasp.perception.depth_fit.kernels import KernelFrame


@dataclass(frozen=True)
class FitContext:
    """What every stage of one frame's depth fit reads, for O objects (a fit's row names its object o): their model
    points (O, M, 3) (object frame, m; padded far off) valid where ``model_ok`` (O, M); their observed points
    (O, N, 3) (camera frame, m) with ``weights`` (O, N) (0: padding); the depth image (H, W) (m, 0: no depth) and
    intrinsics K (3, 3); the supporting plane (4,: n . x + d = 0, n unit, camera frame) or None; the models' ``grids``
    and their stacked points ``table`` (G M, 3) (row u M + j: point j of the u-th distinct grid's model); their
    rests' ups (O, U, 3) and classes (O, U) (``stacked_rests``), their symmetries and their convex hulls' vertices
    ``hulls`` (O, V, 3) (``ObjectModel.hull``, padded by repeating the first); given the plane, ``supports`` (O, S):
    heights (m) above it on which each object may rest besides the plane (``supports``; 0 where none); ``kernels``,
    all this as the compiled kernels read it."""

    models: torch.Tensor
    model_ok: torch.Tensor
    points: torch.Tensor
    weights: torch.Tensor
    depth: torch.Tensor
    K: np.ndarray
    plane: torch.Tensor | None
    grids: Grids
    table: torch.Tensor
    ups: torch.Tensor
    rest_labels: torch.Tensor
    symmetries: list[Symmetries]
    hulls: torch.Tensor
    supports: torch.Tensor | None = None

    @classmethod
    def of(cls, models: list[ObjectModel], observed: list[np.ndarray], depth: np.ndarray, K: np.ndarray,
           plane: np.ndarray | None) -> FitContext:
        """The context of objects ``models`` observed as points (N_o, 3) each (camera frame, m) in ``depth`` (H, W)."""
        m, m_ok = _padded([x.points for x in models], 1e3)  # padding far off, never a nearest point
        p, p_ok = _padded(observed)
        ups, labels = stacked_rests([x.rests for x in models])
        grids = Grids.of([x.grid for x in models], m.shape[1])
        return cls(m, m_ok, p, p_ok.float(), torch.from_numpy(np.asarray(depth, dtype=np.float32)), K,
                   None if plane is None else torch.from_numpy(np.asarray(plane, dtype=np.float32)),
                   grids, m[grids.first].reshape(-1, 3).contiguous(), ups, labels,
                   [x.symmetries for x in models], _repeated([x.hull for x in models]),
                   None if plane is None else supports(models, observed, np.asarray(plane, dtype=np.float64)))

    @cached_property
    def kernels(self) -> KernelFrame:
        """This context as the compiled kernels' structures (``kernels.KernelFrame``), built once."""
        from posegrasp.perception.depth_fit.kernels import KernelFrame

        return KernelFrame(self)

    @property
    def normal(self) -> torch.Tensor:
        """The turns' axis (3,), camera frame: the plane's normal, or the optical axis without a plane."""
        return torch.tensor([0.0, 0.0, 1.0]) if self.plane is None else self.plane[:3]


#: Heights per object in ``supports`` (quantiles of its neighbours' points).
SUPPORT_HEIGHTS = 16


def supports(models: list[ObjectModel], observed: list[np.ndarray], plane: np.ndarray) -> torch.Tensor:
    """(O, 1 + SUPPORT_HEIGHTS) heights (m) above the plane (4,: n . x + d = 0, camera frame) on which each object
    may rest: 0 (the plane), then the heights of the other parts' observed points (N_o, 3 each, camera frame, m) that
    lie within the object's bounding radius of its own points' centroid along the plane, as quantiles (0 where there
    are none): a part lying on other parts rests on their seen surfaces, not on the plane."""
    out = np.zeros((len(models), 1 + SUPPORT_HEIGHTS), dtype=np.float32)
    n, d = plane[:3], plane[3]
    parts = list({id(p): p for p in observed if len(p)}.values())  # (one array given twice: one part, two types)
    if len(parts) < 2:
        return torch.from_numpy(out)
    e1 = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    e1 /= np.linalg.norm(e1)
    basis = np.stack([e1, np.cross(n, e1)], axis=1)  # (3, 2): spans the plane
    q = np.concatenate(parts)  # (Q, 3)
    owner = np.repeat(np.arange(len(parts)), [len(p) for p in parts])  # (Q,)
    own = {id(p): i for i, p in enumerate(parts)}
    height = q @ n + d  # (Q,)
    rows = [o for o, p in enumerate(observed) if len(p)]
    centre = np.stack([np.mean(observed[o], axis=0) for o in rows]) @ basis  # (O', 2) along the plane
    along = q @ basis  # (Q, 2)
    dist2 = (np.einsum("ij,ij->i", centre, centre)[:, None] + np.einsum("ij,ij->i", along, along)[None]
             - 2.0 * centre @ along.T)  # (O', Q)
    radius = np.array([models[o].radius for o in rows])
    near = (dist2 < radius[:, None] ** 2) & (owner[None] != np.array([own[id(observed[o])] for o in rows])[:, None])
    levels = np.linspace(0.0, 1.0, SUPPORT_HEIGHTS)
    for o, ok in zip(rows, near):
        if ok.any():
            out[o, 1:] = np.quantile(height[ok], levels)
    return torch.from_numpy(out)


def _padded(arrays: list[np.ndarray], fill: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Point sets (n_i, 3) as one float32 tensor (O, max n_i, 3), padded with ``fill``, and its validity mask
    (O, max n_i)."""
    n = max(len(a) for a in arrays)
    out, valid = np.full((len(arrays), n, 3), fill, dtype=np.float32), np.zeros((len(arrays), n), dtype=bool)
    for i, a in enumerate(arrays):
        out[i, :len(a)], valid[i, :len(a)] = a, True
    return torch.from_numpy(out), torch.from_numpy(valid)


def _repeated(arrays: list[np.ndarray]) -> torch.Tensor:
    """Point sets (n_i, 3) as one float32 tensor (O, max n_i, 3), each padded by repeating its first point."""
    n = max(len(a) for a in arrays)
    return torch.from_numpy(np.stack([np.concatenate([a, np.repeat(a[:1], n - len(a), axis=0)])
                                      for a in arrays]).astype(np.float32))
