"""The context of one frame's depth fit: its objects' models and observed points as batched tensors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from posegrasp.perception.depth_fit.grids import Grids
from posegrasp.perception.depth_fit.model import ObjectModel
from posegrasp.perception.depth_fit.starts import Symmetries, stacked_rests


@dataclass(frozen=True)
class FitContext:
    """What every stage of one frame's depth fit reads, for O objects (a fit's row names its object o): their model
    points (O, M, 3) (object frame, m; padded far off) valid where ``model_ok`` (O, M); their observed points
    (O, N, 3) (camera frame, m) with ``weights`` (O, N) (0: padding); the depth image (H, W) (m, 0: no depth) and
    intrinsics K (3, 3); the supporting plane (4,: n . x + d = 0, n unit, camera frame) or None; the models' ``grids``
    and stacked point columns (3, O M) (row o M + j: point j of model o); their rests' ups (O, U, 3) and classes
    (O, U) (``stacked_rests``) and their symmetries; given the plane, ``supports`` (O, S): heights (m) above it on
    which each object may rest besides the plane (``supports``; 0 where none)."""

    models: torch.Tensor
    model_ok: torch.Tensor
    points: torch.Tensor
    weights: torch.Tensor
    depth: torch.Tensor
    K: np.ndarray
    plane: torch.Tensor | None
    grids: Grids
    columns: torch.Tensor
    ups: torch.Tensor
    rest_labels: torch.Tensor
    symmetries: list[Symmetries]
    supports: torch.Tensor | None = None

    @classmethod
    def of(cls, models: list[ObjectModel], observed: list[np.ndarray], depth: np.ndarray, K: np.ndarray,
           plane: np.ndarray | None) -> FitContext:
        """The context of objects ``models`` observed as points (N_o, 3) each (camera frame, m) in ``depth`` (H, W)."""
        m, m_ok = _padded([x.points for x in models], 1e3)  # padding far off, never a nearest point
        p, p_ok = _padded(observed)
        ups, labels = stacked_rests([x.rests for x in models])
        return cls(m, m_ok, p, p_ok.float(), torch.from_numpy(np.asarray(depth, dtype=np.float32)), K,
                   None if plane is None else torch.from_numpy(np.asarray(plane, dtype=np.float32)),
                   Grids([x.grid for x in models], m.shape[1]), m.reshape(-1, 3).T.contiguous(), ups, labels,
                   [x.symmetries for x in models],
                   None if plane is None else supports(models, observed, np.asarray(plane, dtype=np.float64)))

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
    for o, (x, p) in enumerate(zip(models, observed)):
        others = [q for q in observed if q is not p and len(q)]  # (one array given twice: one part, two types)
        if not others or not len(p):
            continue
        q = np.concatenate(others) - np.mean(p, axis=0)
        along = q - (q @ n)[:, None] * n  # the offsets along the plane
        near = np.einsum("ij,ij->i", along, along) < float(np.max(np.einsum("ij,ij->i", x.points, x.points)))
        if near.any():
            out[o, 1:] = np.quantile(q[near] @ n + np.mean(p, axis=0) @ n + d, np.linspace(0.0, 1.0, SUPPORT_HEIGHTS))
    return torch.from_numpy(out)


def _padded(arrays: list[np.ndarray], fill: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Point sets (n_i, 3) as one float32 tensor (O, max n_i, 3), padded with ``fill``, and its validity mask
    (O, max n_i)."""
    n = max(len(a) for a in arrays)
    out, valid = torch.full((len(arrays), n, 3), fill), torch.zeros(len(arrays), n, dtype=torch.bool)
    for i, a in enumerate(arrays):
        out[i, :len(a)], valid[i, :len(a)] = torch.from_numpy(np.asarray(a, dtype=np.float32)), True
    return out, valid
