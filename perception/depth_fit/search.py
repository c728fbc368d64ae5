"""The final searches on the fine score: each object's best fits turned about the plane's normal, and moved along it.

Seen from above, a flat face's points pin neither its turn about the normal nor its shift along the plane, and ICP
stops where the squared distances balance, while a model a degree off sticks out of the seen silhouette, which the
score's free-space term sees. So the fits are moved on the score itself:

- ``yaw_search``: each object's best fit turned about the normal n through its centre by +-s, +-2 s, ... within
  +-``yaw_deg`` (s = 3 ``yaw_step_deg``), then by one ``yaw_step_deg`` each side of the best; every turn is kept as a
  candidate.
- ``pattern_search``: each object's best fits on ``pattern_fits`` different rests moved, ``pattern_rounds`` rounds
  per scale (shift, turn) of ``PATTERN_SCALES``, to the best of the six moves t +- shift e1, t +- shift e2 (e1, e2
  spanning the plane) and R -> G(+-turn) R (G a turn about n through the centre), where that scores lower. A block
  resting on the plane keeps resting.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from posegrasp.perception.depth_fit.config import SearchConfig
from posegrasp.perception.depth_fit.score import Scored, best_rows
from posegrasp.perception.depth_fit.starts import up_face
from posegrasp.perception.torch_geometry import turns_about

#: The pattern search's scales, in turn: (shift along the plane (m), turn about its normal (deg)).
PATTERN_SCALES = ((0.002, 2.0), (0.001, 1.0), (0.0005, 0.5))

#: Scores (H,) of poses R (H, 3, 3), t (H, 3) of objects obj (H,).
ScoreOf = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def yaw_search(poses: Scored, normal: torch.Tensor, cfg: SearchConfig, score_of: ScoreOf) -> Scored:
    """``poses`` and, appended, each object's best turned about ``normal`` (3,, camera frame) (module doc)."""
    for span, by in ((cfg.yaw_deg, 3 * cfg.yaw_step_deg), (cfg.yaw_step_deg,) * 2) if cfg.yaw_deg > 0 else ():
        R, t, obj = poses.R, poses.t, poses.obj
        best = poses.argbest()
        angles = np.arange(by, span + 1e-9, by)
        G = turns_about(normal, torch.from_numpy(np.radians(np.concatenate([-angles, angles]))).float())  # (S, 3, 3)
        Rs = (G[None] @ R[best][:, None]).reshape(-1, 3, 3)
        ts, os_ = t[best].repeat_interleave(len(G), 0), obj[best].repeat_interleave(len(G), 0)
        poses = poses + Scored(Rs, ts, os_, score_of(Rs, ts, os_))
    return poses


def pattern_search(poses: Scored, normal: torch.Tensor, ups: torch.Tensor, cfg: SearchConfig,
                   score_of: ScoreOf) -> Scored:
    """``poses`` and, appended, each object's best ``cfg.pattern_fits`` on different rests (ups (O, U, 3), each
    object's) moved by the pattern search on ``score_of`` along the plane with unit normal ``normal`` (3,)
    (module doc)."""
    R, t, obj, score = poses.R, poses.t, poses.obj, poses.score
    sel = best_rows(score, obj, cfg.pattern_fits, face=up_face(R, normal, ups[obj]))
    Rc, tc, oc, sc = R[sel].clone(), t[sel].clone(), obj[sel], score[sel].clone()
    n = normal.to(R.dtype)
    e1 = torch.linalg.cross(n, torch.eye(3, dtype=n.dtype)[int(n.abs().argmin())])
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(n, e1)
    C = len(Rc)
    for shift, turn in PATTERN_SCALES:
        moves = torch.stack([shift * e1, -shift * e1, shift * e2, -shift * e2])  # (4, 3)
        G = turns_about(n, torch.tensor(np.radians([turn, -turn]), dtype=n.dtype))  # (2, 3, 3)
        for _ in range(cfg.pattern_rounds):
            Rm = torch.cat([Rc[:, None].expand(C, 4, 3, 3), G[None] @ Rc[:, None]], 1)  # (C, 6, 3, 3)
            tm = torch.cat([tc[:, None] + moves[None], tc[:, None].expand(C, 2, 3)], 1)  # (C, 6, 3)
            low, k = score_of(Rm.reshape(-1, 3, 3), tm.reshape(-1, 3), oc.repeat_interleave(6)).view(C, 6).min(dim=1)
            better = torch.nonzero(low < sc)[:, 0]
            Rc[better], tc[better], sc[better] = Rm[better, k[better]], tm[better, k[better]], low[better]
    return poses + Scored(Rc, tc, oc, sc)
