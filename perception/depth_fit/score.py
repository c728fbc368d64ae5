"""The score of a fit against the depth image (lower is better, m), and the choice of each object's best fits.

For a pose (R, t) of an object with observed points p_i (weights w_i) and model points m_j:

    score = sum_i w_i min(d_i, truncation) / sum_i w_i + violation_weight v + float_weight f

d_i: the distance of p_i to the model, from the model's surface (its distance field) in the ``fine`` scores, else to
the grid's match among the model points (within a cell diagonal of the nearest). v: the share of model points that
project onto valid depth pixels and lie more than ``violation_margin`` in front of the seen surface (the model would
fill space the camera sees through), plus, given the supporting plane, the share more than ``violation_margin``
beneath it (sunk into the table). f, given the plane: the height of the lowest model point above the highest support
not above it (the plane, or the seen surface of a neighbouring object: ``FitContext.supports``) less
``float_margin``, in cm, clipped to [0, 1] (a block resting on nothing). The ranking scores take the first
``rank_points`` model points for v and f, the fine ones all of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from posegrasp.perception.depth_fit.config import ScoreConfig
from posegrasp.perception.depth_fit.context import FitContext
from posegrasp.perception.depth_fit.distance_field import gather
from posegrasp.perception.depth_fit.grids import columns


def score(frame: FitContext, cfg: ScoreConfig, R: torch.Tensor, t: torch.Tensor, obj: torch.Tensor,
          fine: bool = False) -> torch.Tensor:
    """Scores (H,) in m of the poses R (H, 3, 3), t (H, 3) (object to camera) of the frame's objects ``obj`` (H,)
    (module doc); ``fine``: the distances from the models' surfaces and all the model points."""
    m, m_ok, p, w = frame.models, frame.model_ok, frame.points, frame.weights
    k = m.shape[1] if fine else cfg.rank_points
    ok, wo = m_ok[obj, :k], w[obj]
    # coordinates first, (H, 3, k) and (H, 3, N): batched products with 3-long rows are ~8x slower on a CPU
    mc = torch.baddbmm(t[:, :, None], R, m[:, :k].transpose(1, 2)[obj])  # (H, 3, k), camera frame
    Rt = R.transpose(1, 2)
    local = torch.baddbmm(-(Rt @ t[:, :, None]), Rt, p.transpose(1, 2)[obj])  # (H, 3, N), object frame
    if fine:
        dist = frame.grids.fields(local, obj)
    else:  # (the sum of squares: torch's norm along a 3-long dim of a (H, 3, N) tensor is ~20x slower)
        dist = ((local - columns(frame.columns, frame.grids.local(local, obj))) ** 2).sum(dim=1).sqrt()
    fit = (dist.clamp(max=cfg.truncation) * wo).sum(dim=1) / wo.sum(dim=1)
    K, depth, plane = frame.K, frame.depth, frame.plane
    z = mc[:, 2].clamp(min=1e-6)
    u = torch.round(mc[:, 0] * float(K[0, 0]) / z + float(K[0, 2]))  # (H, k) whole pixel numbers, float32
    v = torch.round(mc[:, 1] * float(K[1, 1]) / z + float(K[1, 2]))
    h, w_img = depth.shape  # (pixel indices below 2^24: exact in float32)
    inside = ok & (u >= 0) & (u < w_img) & (v >= 0) & (v < h)
    dz = gather(depth.reshape(-1), (v.clamp_(0, h - 1).mul_(w_img) + u.clamp_(0, w_img - 1)).int())
    viol = (inside & (dz > 0) & (z < dz - cfg.violation_margin)).sum(dim=1) / inside.sum(dim=1).clamp(min=1)
    total = fit
    if plane is not None:
        height = (mc * plane[:3, None]).sum(dim=1) + plane[3]  # (H, k)
        viol = viol + (ok & (height < -cfg.violation_margin)).sum(dim=1) / ok.sum(dim=1)
        lowest = height.masked_fill(~ok, torch.inf).min(dim=1).values  # (H,)
        if frame.supports is not None:  # the highest support not above the lowest point (the plane, 0, at least)
            sup = frame.supports[obj]
            lowest = lowest - sup.masked_fill(sup > lowest[:, None] + cfg.float_margin, 0.0).max(dim=1).values
        total = total + cfg.float_weight * ((lowest - cfg.float_margin) / 0.01).clamp(0, 1)
    return total + cfg.violation_weight * viol


@dataclass(frozen=True)
class Scored:
    """Scored poses: rotations R (H, 3, 3) and translations t (H, 3) (object to camera, m) of objects obj (H,), and
    their scores (H,) (m)."""

    R: torch.Tensor
    t: torch.Tensor
    obj: torch.Tensor
    score: torch.Tensor

    def __add__(self, other: Scored) -> Scored:
        """These poses and then ``other``'s."""
        return Scored(torch.cat([self.R, other.R]), torch.cat([self.t, other.t]), torch.cat([self.obj, other.obj]),
                      torch.cat([self.score, other.score]))

    def best(self, o: int) -> tuple[np.ndarray, float]:
        """Object o's best-scoring pose T_cam_obj (4, 4) (float64) and its score (m)."""
        i = torch.nonzero(self.obj == o)[:, 0]
        b = int(i[self.score[i].argmin()])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R[b].double().numpy(), self.t[b].double().numpy()
        return T, float(self.score[b])


def best_rows(score: torch.Tensor, obj: torch.Tensor, n: int, R: torch.Tensor | None = None, apart_deg: float = 10.0,
              face: torch.Tensor | None = None) -> torch.Tensor:
    """Rows of the ``n`` lowest scores (H,) of each object ``obj`` (H,), object by object; given the rotations R
    (H, 3, 3), each kept row turned at least ``apart_deg`` from those kept before it (fits that converged to one
    pose count once); given ``face`` (H,), each kept row with a face label of its own."""
    keep = []
    cos_apart = float(np.cos(np.radians(apart_deg)))
    for o in obj.unique():
        rows = torch.nonzero(obj == o)[:, 0]
        rows = rows[score[rows].argsort()]
        kept = [int(rows[0])]
        for r in rows[1:].tolist():
            if len(kept) == n:
                break
            if face is not None:
                if int(face[r]) not in face[kept].tolist():
                    kept.append(r)
            elif R is None or float(((torch.einsum("kij,ij->k", R[kept], R[r]) - 1) / 2).max()) < cos_apart:
                kept.append(r)  # (the cosines of the angles between R_r and the kept rotations)
        keep.append(torch.tensor(kept))
    return torch.cat(keep)
