"""DenseFusion's iterative pose refiner.

Each iteration maps the points into the frame of the current estimate T (R^T (p - t)), computes a
global feature from them and the pose net's per-point colour embedding, and regresses a delta pose
dT (quaternion (w, x, y, z) and translation, m) per object; the estimate becomes T x dT.
"""

from __future__ import annotations

from dataclasses import field

import torch
from torch import nn

from posegrasp.config import settings, within
from posegrasp.perception.pose_net import PointFusion
from posegrasp.perception.torch_geometry import make_transform, quat_to_rotmat


@settings
class RefinerConfig:
    """Refiner hyper-parameters (DenseFusion's values in the descriptions); objects and widths follow the pose net."""

    #: BOP ids of the objects, as the pose net's.
    obj_ids: list[int] = field(default_factory=lambda: [1, 2, 3])
    #: Per object, whether its loss is ADD-S, as the pose net's.
    symmetric: list[bool] = field(default_factory=lambda: [False, False, False])
    #: The pose net's colour embedding channels (32).
    emb_dim: int = field(default=32, metadata=within(1, 4096))
    #: Per-point conv widths (64, 128).
    point_widths: tuple[int, int] = field(default=(32, 64), metadata=within(1, 4096))
    #: Conv widths before the pool (512, 1024).
    global_widths: tuple[int, int] = field(default=(128, 256), metadata=within(1, 4096))
    #: Fully connected widths (512, 128).
    fc_widths: tuple[int, int] = field(default=(128, 64), metadata=within(1, 4096))
    #: Refinement steps at inference (2 YCB, 4 LineMOD).
    iterations: int = field(default=2, metadata=within(0, 100))

    @property
    def num_objects(self) -> int:
        return len(self.obj_ids)


class RefinerFeat(PointFusion):
    """Both fusion levels concatenated (2 p1 + 2 p2), then g1 -> g2 and average pooling:
    (B, 3, N), (B, E, N) -> (B, g2)."""

    def __init__(self, emb_dim: int, point_widths: tuple[int, int], global_widths: tuple[int, int]):
        super().__init__(emb_dim, point_widths, global_widths, 2 * sum(point_widths))

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        x = torch.cat(self.levels(x, emb), dim=1)  # (B, 2 p1 + 2 p2, N)
        return self.global_convs(x).mean(dim=2)  # (B, g2)


def _mlp(cin: int, widths: tuple[int, ...], out: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for w in widths:
        layers += [nn.Linear(cin, w), nn.ReLU(inplace=True)]
        cin = w
    layers.append(nn.Linear(cin, out))
    return nn.Sequential(*layers)


class PoseRefiner(nn.Module):
    """Global feature + two fully connected heads (delta quaternion, delta translation) per object."""

    def __init__(self, cfg: RefinerConfig):
        super().__init__()
        self.cfg = cfg
        self.feat = RefinerFeat(cfg.emb_dim, cfg.point_widths, cfg.global_widths)
        k = cfg.num_objects
        self.fc_r = _mlp(cfg.global_widths[1], cfg.fc_widths, 4 * k)
        self.fc_t = _mlp(cfg.global_widths[1], cfg.fc_widths, 3 * k)

    def forward(self, points: torch.Tensor, emb: torch.Tensor, obj: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """points (B, N, 3) in the current estimate's frame (m), emb (B, E, N), obj (B,) ->
        dq (B, 4) unit quaternion, dt (B, 3) m."""
        g = self.feat(points.transpose(1, 2), emb)  # (B, g2)
        B = g.shape[0]
        ar = torch.arange(B, device=g.device)
        dq = self.fc_r(g).view(B, -1, 4)[ar, obj]
        dq = dq / dq.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        dt = self.fc_t(g).view(B, -1, 3)[ar, obj]
        return dq, dt


def to_estimate_frame(points: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """Camera-frame points (B, N, 3) -> frame of the estimates T (B, 4, 4): R^T (p - t)."""
    return torch.bmm(points - T[:, None, :3, 3], T[:, :3, :3])


@torch.no_grad()
def refine(refiner: PoseRefiner, T: torch.Tensor, points: torch.Tensor, emb: torch.Tensor, obj: torch.Tensor,
           iterations: int) -> torch.Tensor:
    """Apply ``iterations`` refinement steps to the poses T (B, 4, 4) (T_cam_obj, m): T <- T x dT."""
    for _ in range(iterations):
        dq, dt = refiner(to_estimate_frame(points, T), emb, obj)
        T = torch.bmm(T, make_transform(quat_to_rotmat(dq), dt))
    return T


def build_refiner(cfg: RefinerConfig) -> PoseRefiner:
    """The refiner for ``cfg`` (random init)."""
    return PoseRefiner(cfg)
