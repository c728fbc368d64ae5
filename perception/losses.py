"""Pose losses (DenseFusion's, batched): ADD for asymmetric objects, ADD-S for symmetric ones, or
optionally the minimum ADD over an object's discrete symmetries.

All points are in metres. ``model_points`` (B, M, 3) are in the object frame; ``target`` (B, M, 3)
are the same points under the ground-truth pose, in the camera frame (or, for the refiner, in the
frame of the current estimate). Nearest neighbours are found with ``torch.cdist`` under no_grad, then
the distances to the matched points are recomputed with gradients.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from posegrasp.perception.torch_geometry import make_transform, quat_to_rotmat


def point_distances(pred: torch.Tensor, target: torch.Tensor, symmetric: torch.Tensor,
                    max_elems: int = 1 << 24) -> torch.Tensor:
    """Mean distance per proposal between predicted and target model points.

    pred (B, P, M, 3): model points under each of P proposals; target (B, M, 3); symmetric (B,) bool.
    Asymmetric samples: ADD (point i to point i). Symmetric samples: each predicted point to its
    nearest target point (DenseFusion's ADD-S). Returns (B, P).
    """
    B, P, M, _ = pred.shape
    tgt = target[:, None].expand(B, P, M, 3)
    sym_idx = torch.nonzero(symmetric.bool(), as_tuple=False).flatten().tolist()
    if sym_idx:
        tgt = tgt.clone()
        chunk = max(1, max_elems // max(M * target.shape[1], 1))
        with torch.no_grad():
            for b in sym_idx:
                for s in range(0, P, chunk):
                    d = torch.cdist(pred[b, s:s + chunk].detach(), target[b][None])  # (p, M, M)
                    nn_idx = d.argmin(dim=-1)  # (p, M)
                    tgt[b, s:s + chunk] = target[b][nn_idx]
    return (pred - tgt).norm(dim=-1).mean(dim=-1)  # (B, P)


def min_symmetry_targets(pred: torch.Tensor, sym_targets: torch.Tensor, max_elems: int = 1 << 24) -> torch.Tensor:
    """For each proposal, the copy of the target under the object's discrete symmetries closest to it.

    pred (B, P, M, 3); sym_targets (B, S, M, 3): the model points under T_gt S_k for the identity and each
    discrete symmetry S_k (padded with repeats). Returns (B, P, M, 3), chosen under no_grad: the ADD to it
    is min_k ADD(pred, T_gt S_k), which unlike ADD-S pins the rotation down to the true symmetries.
    """
    B, P, M, _ = pred.shape
    S = sym_targets.shape[1]
    out = torch.empty_like(pred)
    chunk = max(1, max_elems // max(S * M * 3, 1))
    with torch.no_grad():
        for b in range(B):
            for s in range(0, P, chunk):
                p = pred[b, s:s + chunk].detach()  # (p, M, 3)
                d = (p[:, None] - sym_targets[b][None]).norm(dim=-1).mean(dim=-1)  # (p, S)
                out[b, s:s + chunk] = sym_targets[b][d.argmin(dim=1)]
    return out


@dataclass(frozen=True)
class PoseTargets:
    """What the pose loss compares the net's proposals with: the depth points (B, N, 3) (camera frame, m), the model
    points (B, M, 3) (object frame, m), the target (B, M, 3) (the model points under the ground truth, camera frame)
    and whether each object is symmetric (B,) bool (its loss ADD-S); with ``sym_targets`` (B, S, M, 3) (see
    ``min_symmetry_targets``) and ``continuous`` (B,) bool, the least ADD over the discrete symmetries instead, and
    ADD-S only for samples with a continuous symmetry."""

    points: torch.Tensor
    model_points: torch.Tensor
    target: torch.Tensor
    symmetric: torch.Tensor
    sym_targets: torch.Tensor | None = None
    continuous: torch.Tensor | None = None

    @classmethod
    def of(cls, batch: dict[str, torch.Tensor], min_sym: bool = False) -> PoseTargets:
        """The targets of a ``perception.data.PoseDataset`` batch; ``min_sym``: with its symmetry targets."""
        sym = (batch["sym_targets"], batch["continuous"]) if min_sym else (None, None)
        return cls(batch["points"], batch["model_points"], batch["target"], batch["symmetric"], *sym)


@dataclass
class PoseLossOutput:
    """Loss of the pose net and the best proposal per sample (detached).

    dis: (B,) distance (m) of the most confident proposal; T: (B, 4, 4) its pose T_cam_obj;
    conf: (B,) its confidence; new_points / new_target: (B, N, 3) / (B, M, 3) mapped into the frame
    of that pose (R^T (p - t)), the refiner's inputs.
    """

    loss: torch.Tensor
    dis: torch.Tensor
    T: torch.Tensor
    conf: torch.Tensor
    new_points: torch.Tensor
    new_target: torch.Tensor


def pose_loss(pred_q: torch.Tensor, pred_t: torch.Tensor, pred_c: torch.Tensor, truth: PoseTargets,
              w: float = 0.015) -> PoseLossOutput:
    """DenseFusion loss mean_i(dis_i * c_i - w log c_i) over points i and the batch.

    pred_q (B, N, 4) quaternions (w, x, y, z), pred_t (B, N, 3) translation offsets (the proposal
    of point i has t = points_i + pred_t_i), pred_c (B, N) confidences in (0, 1). dis_i is ADD / ADD-S against
    ``truth`` by ``truth.symmetric``, or, with ``truth.sym_targets``, the minimum ADD over the discrete symmetries,
    and ADD-S only for samples with a continuous symmetry (``PoseTargets``).
    """
    points, model_points, target, symmetric = truth.points, truth.model_points, truth.target, truth.symmetric
    sym_targets, continuous = truth.sym_targets, truth.continuous
    B, N, _ = pred_q.shape
    R = quat_to_rotmat(pred_q)  # (B, N, 3, 3)
    t = points + pred_t  # (B, N, 3)
    pred = torch.einsum("bmk,bnjk->bnmj", model_points, R) + t[:, :, None, :]  # (B, N, M, 3)
    if sym_targets is None:
        dis = point_distances(pred, target, symmetric)  # (B, N)
    else:
        cont = continuous.bool() if continuous is not None else torch.zeros(B, dtype=torch.bool)
        dis = point_distances(pred, target, cont)  # ADD-S where continuous, else overwritten below
        disc = torch.nonzero(~cont, as_tuple=False).flatten()
        if disc.numel():
            tgt = min_symmetry_targets(pred[disc], sym_targets[disc])  # (b, N, M, 3)
            dis = dis.index_put((disc,), (pred[disc] - tgt).norm(dim=-1).mean(dim=-1))
    c = pred_c.clamp(1e-6, 1.0)
    loss = (dis * c - w * torch.log(c)).mean()
    with torch.no_grad():
        best = pred_c.argmax(dim=1)  # (B,)
        ar = torch.arange(B, device=pred_q.device)
        Rb, tb = R[ar, best], t[ar, best]  # (B, 3, 3), (B, 3)
        new_points = torch.bmm(points - tb[:, None], Rb)  # R^T (p - t) as rows
        new_target = torch.bmm(target - tb[:, None], Rb)
        out = PoseLossOutput(loss, dis[ar, best].detach(), make_transform(Rb, tb), pred_c[ar, best].detach(),
                             new_points, new_target)
    return out


@dataclass
class RefinerLossOutput:
    """Refiner loss; dis (B,) per sample (m); new_points / new_target in the refined frame."""

    loss: torch.Tensor
    dis: torch.Tensor
    dT: torch.Tensor
    new_points: torch.Tensor
    new_target: torch.Tensor


def refiner_loss(pred_q: torch.Tensor, pred_t: torch.Tensor, points: torch.Tensor, model_points: torch.Tensor,
                 target: torch.Tensor, symmetric: torch.Tensor) -> RefinerLossOutput:
    """Mean ADD / ADD-S of the refined pose dT (pred_q (B, 4), pred_t (B, 3)), both expressed in the
    frame of the current estimate, where ``points`` (B, N, 3) and ``target`` (B, M, 3) live."""
    R = quat_to_rotmat(pred_q)  # (B, 3, 3)
    pred = torch.bmm(model_points, R.transpose(1, 2)) + pred_t[:, None]  # (B, M, 3)
    dis = point_distances(pred[:, None], target, symmetric)[:, 0]  # (B,)
    with torch.no_grad():
        new_points = torch.bmm(points - pred_t[:, None], R)
        new_target = torch.bmm(target - pred_t[:, None], R)
        dT = make_transform(R, pred_t)
    return RefinerLossOutput(dis.mean(), dis.detach(), dT, new_points, new_target)
