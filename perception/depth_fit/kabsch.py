"""The ICP step's rigid fit: batched weighted Kabsch, and its held form, a turn about a normal and a shift.

Free rows: the rotation R and translation t minimising sum_i w_i |R s_i + t - d_i|^2 (weights normalised to sum to
1) are R = argmax tr(R C), C = sum_i w_i (s_i - c_s)(d_i - c_d)^T, from the SVD of C with no reflection, and
t = c_d - R c_s (c_s, c_d the weighted centroids).

Held rows (a fit resting on the plane, unit normal n): R = G(a) R0, G(a) the turn by a about n. With q_i = R0 s_i,
the fit term is maximised by a = atan2(B, A) where sum_i w_i G(a) q_i . (d_i - c_d) = cos(a) A + sin(a) B,
C = sum_i w_i q_i (d_i - c_d)^T, A = tr C - n^T C n and B = n . (C_yz - C_zy, C_zx - C_xz, C_xy - C_yx).
"""

from __future__ import annotations

import torch

from posegrasp.perception.torch_geometry import turns_about


class Kabsch:
    """Batched weighted least-squares rigid fits dst ~ R src + t to fixed targets dst (H, N, 3) with weights w (H, N)
    >= 0 (0: a padding point); ``fit(src)`` (H, 3, N) (any strides) -> R (H, 3, 3), t (H, 3). The centred targets'
    weighted sum is 0, so C = S^T (w (D - c_d)), whose right factor is computed once (module doc)."""

    def __init__(self, dst: torch.Tensor, w: torch.Tensor):
        self.w = (w / w.sum(dim=1, keepdim=True))[:, None, :]  # (H, 1, N)
        self.cd = (self.w @ dst)[:, 0]  # (H, 3)
        self.wd = self.w.transpose(1, 2) * (dst - self.cd[:, None])  # (H, N, 3)

    def fit(self, src: torch.Tensor, held: torch.Tensor | None = None, R0: torch.Tensor | None = None,
            n: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The fits of every row; the rows ``held`` (H,) as turns of R0 (H, 3, 3) about n (3,) (module doc)."""
        cs = (src * self.w).sum(dim=2)  # (H, 3)
        C = torch.bmm(src, self.wd)  # (H, 3, 3) cross-covariance
        if held is None or not bool(held.any()):
            R = svd_rotation(C)
        else:
            R = torch.empty_like(C)
            free = ~held
            if bool(free.any()):
                R[free] = svd_rotation(C[free])
            Rh = R0[held]
            Ch = Rh @ C[held]
            A = Ch.diagonal(dim1=1, dim2=2).sum(dim=1) - (Ch @ n) @ n
            B = torch.stack([Ch[:, 1, 2] - Ch[:, 2, 1], Ch[:, 2, 0] - Ch[:, 0, 2], Ch[:, 0, 1] - Ch[:, 1, 0]], 1) @ n
            R[held] = turns_about(n, torch.atan2(B, A)) @ Rh
        return R, self.cd - (R @ cs[:, :, None])[:, :, 0]


def svd_rotation(C: torch.Tensor) -> torch.Tensor:
    """The rotations (H, 3, 3) that maximise tr(R C) for cross-covariances C (H, 3, 3) (Kabsch, no reflection)."""
    U, _, Vt = torch.linalg.svd(C)
    d = torch.sign(torch.linalg.det(Vt.transpose(1, 2) @ U.transpose(1, 2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=1))
    return Vt.transpose(1, 2) @ D @ U.transpose(1, 2)
