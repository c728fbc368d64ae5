"""The depth fit's ICP steps, batched over fits, in compiled code (``_icp.c``, built with the package).

Each step matches every observed point p_i of a fit (weight w_i) to a model point m_i, by the voxel grid's lookup
(``grids``) or its exact nearest one, and refits its rotation R and translation t (object to camera, m):

- free fits, weighted Kabsch: R = argmax tr(R C), C = sum_i m_i (w_i (p_i - c_p))^T (weights normalised to sum to
  1, c_p their weighted centroid), by Horn's unit quaternion, or R kept where every point is matched to one model
  point (C = 0: no rotation is pinned, as for a start far from its points); t = c_p - R c_m;
- held fits (resting on the plane, unit normal n): R = G(a) R0, G(a) the turn by a about n, R0 the fit's rotation;
  with C' = R0 C, sum_i w_i G(a) R0 m_i . (p_i - c_p) = cos(a) A + sin(a) B, A = tr C' - n^T C' n and
  B = n . (C'_yz - C'_zy, C'_zx - C'_xz, C'_xy - C'_yx), so a = atan2(B, A); then t is moved along n to set the fit
  back resting on the plane n . x + d = 0: its lowest model point's height, ``low`` + n . t + d, made 0.

The steps of a batch of fits run in one call, its rows on torch's number of threads. Camera-frame metres.
"""

from __future__ import annotations

import torch

from posegrasp.errors import PosegraspError
from posegrasp.perception.depth_fit.context import FitContext
from posegrasp.perception.depth_fit.kernels import LIB


def steps(frame: FitContext, R: torch.Tensor, t: torch.Tensor, obj: torch.Tensor, held: torch.Tensor,
          low: torch.Tensor, n: int, exact: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """The fits R (H, 3, 3), t (H, 3) of objects obj (H,) after ``n`` ICP steps against ``frame``'s observed points,
    each matched by its grids, or with ``exact`` to its nearest model point; rows ``held`` (H,) turned about the
    plane's normal and set back resting on it (``low`` (H,): module doc). New tensors."""
    k = frame.kernels
    R, t = R.float().contiguous().clone(), t.float().contiguous().clone()
    held, low = held.to(torch.uint8).contiguous(), low.float().contiguous()
    obs, keep = k.observed(obj)
    status = LIB.posegrasp_icp_steps(obs, k.grids, k.buckets, int(exact), n, R.data_ptr(), t.data_ptr(),
                                     held.data_ptr(), low.data_ptr(), k.plane.data_ptr(), torch.get_num_threads())
    if status != 0:
        raise PosegraspError("depth fit ICP: " + ("an object has no observed point with weight" if status == -1
                                                   else "out of memory"))
    return R, t
