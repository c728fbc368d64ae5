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

from posegrasp.errors import PosegraspError
from posegrasp.perception.depth_fit import kernels
from posegrasp.perception.depth_fit.config import ScoreConfig
from posegrasp.perception.depth_fit.context import FitContext


def score(frame: FitContext, cfg: ScoreConfig, R: torch.Tensor, t: torch.Tensor, obj: torch.Tensor,
          fine: bool = False) -> torch.Tensor:
    """Scores (H,) in m of the poses R (H, 3, 3), t (H, 3) (object to camera) of the frame's objects ``obj`` (H,)
    (module doc), in compiled code (``_score.c``); ``fine``: the distances from the models' surfaces and all the
    model points."""
    k = frame.kernels
    R, t = R.float().contiguous(), t.float().contiguous()
    obs, keep = k.observed(obj)
    out = torch.empty(len(keep))
    config = kernels.CScoreConfig(cfg.truncation, cfg.violation_margin, cfg.violation_weight, cfg.float_margin,
                                 cfg.float_weight)
    points = k.models.shape[1] if fine else min(cfg.rank_points, k.models.shape[1])
    if kernels.LIB.posegrasp_scores(obs, k.grids, k.fields if fine else None, k.scene, config, points, R.data_ptr(),
                                    t.data_ptr(), out.data_ptr(), torch.get_num_threads()) != 0:
        raise PosegraspError("depth fit score: out of memory")
    return out


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

    def argbest(self) -> torch.Tensor:
        """The row of each object's lowest score (the first on ties), objects in increasing order."""
        obj, score = self.obj.numpy(), self.score.numpy()
        rows = [i[np.argmin(score[i])] for i in (np.flatnonzero(obj == o) for o in np.unique(obj))]
        return torch.from_numpy(np.array(rows, dtype=np.int64))

    def bests(self) -> dict[int, tuple[np.ndarray, float]]:
        """Each object's best-scoring pose T_cam_obj (4, 4) (float64) and its score (m), by object."""
        out = {}
        R, t, obj, score = (x.numpy() for x in (self.R, self.t, self.obj, self.score))
        for b in self.argbest().tolist():
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R[b], t[b]
            out[int(obj[b])] = T, float(score[b])
        return out


def best_rows(score: torch.Tensor, obj: torch.Tensor, n: int, R: torch.Tensor | None = None, apart_deg: float = 10.0,
              face: torch.Tensor | None = None) -> torch.Tensor:
    """Rows of the ``n`` lowest scores (H,) of each object ``obj`` (H,), object by object; given the rotations R
    (H, 3, 3), each kept row turned at least ``apart_deg`` from those kept before it (fits that converged to one
    pose count once); given ``face`` (H,), each kept row with a face label of its own."""
    cos_apart = float(np.cos(np.radians(apart_deg)))
    labels = None if face is None else face.tolist()
    obj_ = obj.numpy()
    turns = None if R is None else R.reshape(-1, 9).numpy()  # row k: R_k flat; R_k . R_r = trace(R_k^T R_r)
    keep: list[int] = []
    for o in np.unique(obj_):
        rows = torch.from_numpy(np.flatnonzero(obj_ == o))
        rows = rows[score[rows].argsort()].tolist()
        if labels is not None:  # each face label's first row, in score order
            first = {}
            for r in rows:
                first.setdefault(labels[r], r)
            kept = list(first.values())[:n]
        elif turns is None:
            kept = rows[:n]
        else:
            kept = [rows[0]]
            for r in rows[1:]:
                if len(kept) == n:
                    break
                if float(((turns[kept] @ turns[r] - 1) / 2).max()) < cos_apart:
                    kept.append(r)  # (the cosines of the angles between R_r and the kept rotations)
        keep += kept
    return torch.tensor(keep, dtype=torch.long)
