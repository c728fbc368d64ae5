"""Pose network: DenseFusion's dense per-point fusion of colour and geometry, extended by the
paper's three parallel modules (PAM, CAM, GFEM), with per-point rotation, translation and
confidence heads chosen per object.

Inputs: an RGB crop (B, 3, S, S) normalised, ``choose`` (B, N) flat indices into the S x S crop of
the pixels the N points come from, the points (B, N, 3) in the camera frame (m) and the object
index (B,) (position of the object's BOP id in ``PoseNetConfig.obj_ids``). Output per point i: a
unit quaternion (w, x, y, z), a translation offset t_i (the pose proposed by point i has
t = points_i + t_i, m) and a confidence in (0, 1).
"""

from __future__ import annotations

from dataclasses import field

import torch
import torch.nn.functional as F
from torch import nn

from posegrasp.config import settings, within
from posegrasp.errors import ConfigError
from posegrasp.perception.attention import CAM, GFEM, PAM


@settings
class PoseNetConfig:
    """Pose net hyper-parameters (DenseFusion's values in the descriptions)."""

    #: BOP ids of the objects, one head each; set from the dataset.
    obj_ids: list[int] = field(default_factory=lambda: [1, 2, 3])
    #: Per object, whether its loss is ADD-S; set from the dataset.
    symmetric: list[bool] = field(default_factory=lambda: [False, False, False])
    #: Depth points sampled per object (500 LineMOD, 1000 YCB).
    num_points: int = field(default=500, metadata=within(1, 100000))
    #: Side (px) the colour crop is resized to; a multiple of 8.
    crop_size: int = field(default=80, metadata=within(8, 1024))
    #: ResNet18 base channels (64).
    backbone_width: int = field(default=16, metadata=within(1, 4096))
    #: Colour embedding channels per pixel (32).
    emb_dim: int = field(default=32, metadata=within(1, 4096))
    #: Per-point convs of geometry and colour (64, 128).
    point_widths: tuple[int, int] = field(default=(32, 64), metadata=within(1, 4096))
    #: Convs before the average pool (512, 1024).
    global_widths: tuple[int, int] = field(default=(128, 256), metadata=within(1, 4096))
    #: 1D-conv head widths (640, 256, 128).
    head_widths: tuple[int, int, int] = field(default=(128, 64, 32), metadata=within(1, 4096))
    #: The paper's position attention module (all three off: DenseFusion).
    use_pam: bool = True
    #: The paper's channel attention module.
    use_cam: bool = True
    #: The paper's global feature enhancement module.
    use_gfem: bool = True
    #: Channel reduction of the position attention's queries and keys.
    pam_reduction: int = field(default=8, metadata=within(1, 4096))
    #: GFEM output channels.
    gfem_channels: int = field(default=128, metadata=within(1, 4096))

    @property
    def num_objects(self) -> int:
        return len(self.obj_ids)

    @property
    def fused_channels(self) -> int:
        """Per-point fused width: 2 * p1 + 2 * p2 + g2 (1408 in DenseFusion)."""
        return 2 * self.point_widths[0] + 2 * self.point_widths[1] + self.global_widths[1]

    def __post_init__(self) -> None:
        if len(self.obj_ids) == 0 or len(set(self.obj_ids)) != len(self.obj_ids):
            raise ConfigError(f"obj_ids = {list(self.obj_ids)}: name at least one BOP object id, each once")
        if len(self.symmetric) != len(self.obj_ids):
            raise ConfigError(f"symmetric = {list(self.symmetric)}: give one flag per object id of obj_ids = "
                              f"{list(self.obj_ids)}")
        if self.crop_size % 8:
            raise ConfigError(f"crop_size = {self.crop_size}: use a multiple of 8 px")

    def index_of(self, obj_id: int) -> int:
        """Head index of a BOP object id."""
        return self.obj_ids.index(obj_id)


# ---------------------------------------------------------------------------- colour CNN (PSPNet)

class BasicBlock(nn.Module):
    """ResNet basic block (two 3x3 convs) with optional stride and dilation."""

    conv_bn_pairs = (("conv1", "bn1"), ("conv2", "bn2"))  # for ``perception.runtime.fold_batch_norms``

    def __init__(self, cin: int, cout: int, stride: int = 1, dilation: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, padding=dilation, dilation=dilation, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.down = None
        if stride != 1 or cin != cout:
            self.down = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)), inplace=True)
        y = self.bn2(self.conv2(y))
        return F.relu(y + (x if self.down is None else self.down(x)), inplace=True)


class DilatedResNet18(nn.Module):
    """ResNet18 with output stride 8 (layers 3 and 4 dilated instead of strided): (B, 3, S, S) ->
    (B, 8 * width, S / 8, S / 8)."""

    def __init__(self, width: int):
        super().__init__()
        w = width
        self.stem = nn.Sequential(nn.Conv2d(3, w, 7, 2, 3, bias=False), nn.BatchNorm2d(w), nn.ReLU(inplace=True),
                                  nn.MaxPool2d(3, 2, 1))
        self.layer1 = nn.Sequential(BasicBlock(w, w), BasicBlock(w, w))
        self.layer2 = nn.Sequential(BasicBlock(w, 2 * w, stride=2), BasicBlock(2 * w, 2 * w))
        self.layer3 = nn.Sequential(BasicBlock(2 * w, 4 * w, dilation=2), BasicBlock(4 * w, 4 * w, dilation=2))
        self.layer4 = nn.Sequential(BasicBlock(4 * w, 8 * w, dilation=4), BasicBlock(8 * w, 8 * w, dilation=4))
        self.out_channels = 8 * w

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.stem(x)  # (B, w, S/4, S/4)
        x = self.layer2(self.layer1(x))  # (B, 2w, S/8, S/8)
        return self.layer4(self.layer3(x))  # (B, 8w, S/8, S/8)


class PSPModule(nn.Module):
    """Pyramid pooling (bins 1, 2, 3, 6), each bin level through a 1x1 conv, upsampled and
    concatenated with the input, then a 1x1 bottleneck conv."""

    def __init__(self, cin: int, cout: int, sizes: tuple[int, ...] = (1, 2, 3, 6)):
        super().__init__()
        self.sizes = sizes
        self.convs = nn.ModuleList(nn.Conv2d(cin, cin, 1, bias=False) for _ in sizes)
        self.bottleneck = nn.Conv2d(cin * (len(sizes) + 1), cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        parts = [F.interpolate(conv(F.adaptive_avg_pool2d(x, s)), size=(h, w), mode="bilinear", align_corners=False)
                 for s, conv in zip(self.sizes, self.convs)]
        return F.relu(self.bottleneck(torch.cat(parts + [x], dim=1)))


class PSPUp(nn.Module):
    """x2 bilinear upsampling + 3x3 conv + PReLU."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, padding=1)
        self.act = nn.PReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.conv(F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)))


class ColorCNN(nn.Module):
    """PSPNet on a dilated ResNet18, upsampled back to crop size: (B, 3, S, S) -> (B, emb_dim, S, S).

    With width 64 the channels are DenseFusion's (512 -> PSP 1024 -> 256 -> 64 -> 64 -> 32). Unlike
    DenseFusion there is no dropout and no log-softmax on the embedding.
    """

    def __init__(self, width: int, emb_dim: int):
        super().__init__()
        self.backbone = DilatedResNet18(width)
        self.psp = PSPModule(8 * width, 16 * width)
        self.up1 = PSPUp(16 * width, 4 * width)
        self.up2 = PSPUp(4 * width, width)
        self.up3 = PSPUp(width, width)
        self.final = nn.Conv2d(width, emb_dim, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = self.psp(self.backbone(x))  # (B, 16w, S/8, S/8)
        f = self.up3(self.up2(self.up1(f)))  # (B, w, S, S)
        return self.final(f)


# ---------------------------------------------------------------------------- fusion and heads

class PointFusion(nn.Module):
    """DenseFusion's per-point fusion: geometry (3 -> p1 -> p2) and colour (emb -> p1 -> p2) 1x1 convs,
    concatenated at both levels, and the two global convs g_in -> g1 -> g2 its subclasses feed."""

    def __init__(self, emb_dim: int, point_widths: tuple[int, int], global_widths: tuple[int, int], g_in: int):
        super().__init__()
        p1, p2 = point_widths
        g1, g2 = global_widths
        self.conv1 = nn.Conv1d(3, p1, 1)
        self.conv2 = nn.Conv1d(p1, p2, 1)
        self.e_conv1 = nn.Conv1d(emb_dim, p1, 1)
        self.e_conv2 = nn.Conv1d(p1, p2, 1)
        self.conv5 = nn.Conv1d(g_in, g1, 1)
        self.conv6 = nn.Conv1d(g1, g2, 1)

    def levels(self, x: torch.Tensor, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 3, N), (B, emb, N) -> (B, 2 p1, N), (B, 2 p2, N)."""
        x = F.relu(self.conv1(x))
        emb = F.relu(self.e_conv1(emb))
        feat1 = torch.cat([x, emb], dim=1)
        x = F.relu(self.conv2(x))
        emb = F.relu(self.e_conv2(emb))
        return feat1, torch.cat([x, emb], dim=1)

    def global_convs(self, x: torch.Tensor) -> torch.Tensor:
        """(B, g_in, N) -> (B, g2, N)."""
        return F.relu(self.conv6(F.relu(self.conv5(x))))


class DenseFusionFeat(PointFusion):
    """Both fusion levels, plus p2*2 -> g1 -> g2 average-pooled to a global feature repeated per point.

    (B, 3, N), (B, emb, N) -> (B, 2 p1 + 2 p2 + g2, N) (1408 with DenseFusion's widths).
    """

    def __init__(self, emb_dim: int, point_widths: tuple[int, int], global_widths: tuple[int, int]):
        super().__init__(emb_dim, point_widths, global_widths, 2 * point_widths[1])

    def parts(self, x: torch.Tensor, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The per-point channels (B, 2 p1 + 2 p2, N) and the global feature (B, g2, 1)."""
        feat1, feat2 = self.levels(x, emb)
        return torch.cat([feat1, feat2], dim=1), self.global_convs(feat2).mean(dim=2, keepdim=True)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        f, g = self.parts(x, emb)
        return torch.cat([f, g.expand(-1, -1, x.shape[2])], dim=1)

    def parts_last(self, x: torch.Tensor, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``parts`` channels last, each 1x1 conv one matrix product: (B, N, 3), (B, N, emb) -> the per-point channels
        (B, N, 2 p1 + 2 p2) and the global feature (B, g2)."""
        x1, e1 = torch.relu_(pointwise(x, self.conv1)), torch.relu_(pointwise(emb, self.e_conv1))
        x2, e2 = torch.relu_(pointwise(x1, self.conv2)), torch.relu_(pointwise(e1, self.e_conv2))
        g = torch.relu_(pointwise(torch.relu_(pointwise(torch.cat([x2, e2], dim=2), self.conv5)), self.conv6))
        return torch.cat([x1, e1, x2, e2], dim=2), g.mean(dim=1)


def pointwise(x: torch.Tensor, conv: nn.Conv1d) -> torch.Tensor:
    """A 1x1 ``conv`` on features channels last: (..., cin) -> (..., cout)."""
    return F.linear(x, conv.weight[:, :, 0], conv.bias)


class PointHead(nn.Sequential):
    """1D-conv head cin -> widths... -> num_objects * out_dim (ReLU between, none at the end)."""

    def __init__(self, cin: int, widths: tuple[int, ...], out: int):
        layers: list[nn.Module] = []
        for w in widths:
            layers += [nn.Conv1d(cin, w, 1), nn.ReLU(inplace=True)]
            cin = w
        layers.append(nn.Conv1d(cin, out, 1))
        super().__init__(*layers)

    def last(self, x: torch.Tensor, start: int = 0) -> torch.Tensor:
        """The head's layers from ``start`` on, on features channels last: (..., cin) -> (..., out)."""
        for layer in list(self)[start:]:
            x = torch.relu_(x) if isinstance(layer, nn.ReLU) else pointwise(x, layer)
        return x


def select_object(x: torch.Tensor, obj: torch.Tensor, dim: int) -> torch.Tensor:
    """(B, num_obj * dim, N) -> (B, N, dim) taking each sample's object's slice."""
    B, _, N = x.shape
    x = x.view(B, -1, dim, N)
    return x[torch.arange(B, device=x.device), obj].transpose(1, 2)


def gather_embedding(emb: torch.Tensor, choose: torch.Tensor) -> torch.Tensor:
    """Per-pixel embedding (B, E, S, S) at flat indices ``choose`` (B, N) -> (B, E, N)."""
    B, E = emb.shape[:2]
    return emb.reshape(B, E, -1).gather(2, choose[:, None, :].expand(-1, E, -1))


class PoseNet(nn.Module):
    """Colour CNN + DenseFusion fusion + [PAM, CAM, GFEM] in parallel + per-object point heads."""

    def __init__(self, cfg: PoseNetConfig):
        super().__init__()
        self.cfg = cfg
        self.cnn = ColorCNN(cfg.backbone_width, cfg.emb_dim)
        self.feat = DenseFusionFeat(cfg.emb_dim, cfg.point_widths, cfg.global_widths)
        c = cfg.fused_channels
        self.pam = PAM(c, cfg.pam_reduction) if cfg.use_pam else None
        self.cam = CAM() if cfg.use_cam else None
        self.gfem = GFEM(c, cfg.gfem_channels) if cfg.use_gfem else None
        self._part_widths = (c, c * cfg.use_pam, c * cfg.use_cam, cfg.gfem_channels * cfg.use_gfem)
        cin = sum(self._part_widths)
        k = cfg.num_objects
        self.head_r = PointHead(cin, cfg.head_widths, 4 * k)
        self.head_t = PointHead(cin, cfg.head_widths, 3 * k)
        self.head_c = PointHead(cin, cfg.head_widths, 1 * k)

    def embed(self, img: torch.Tensor, choose: torch.Tensor) -> torch.Tensor:
        """Colour embedding of the chosen pixels: (B, 3, S, S), (B, N) -> (B, emb_dim, N)."""
        return gather_embedding(self.cnn(img), choose)

    def features(self, img: torch.Tensor, points: torch.Tensor, choose: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """The heads' per-point input (B, C_in, N) and the colour embedding (B, E, N)."""
        emb = self.embed(img, choose)  # (B, E, N)
        fused = self.feat(points.transpose(1, 2), emb)  # (B, C, N)
        parts = [fused]
        if self.pam is not None:
            parts.append(self.pam(fused))
        if self.cam is not None:
            parts.append(self.cam(fused))
        if self.gfem is not None:
            parts.append(self.gfem(fused))
        return torch.cat(parts, dim=1), emb  # (B, C_in, N)

    def forward(self, img: torch.Tensor, points: torch.Tensor, choose: torch.Tensor, obj: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Returns q (B, N, 4) unit, t offsets (B, N, 3) m, confidence (B, N), embedding (B, E, N)
        (detached, for the refiner)."""
        x, emb = self.features(img, points, choose)
        q = select_object(self.head_r(x), obj, 4)
        q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        t = select_object(self.head_t(x), obj, 3)
        c = torch.sigmoid(select_object(self.head_c(x), obj, 1))[..., 0]
        return q, t, c, emb.detach()

    def predict(self, img: torch.Tensor, points: torch.Tensor, choose: torch.Tensor, obj: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The most confident point's proposal (inference). Returns q (B, 4) unit, t offset (B, 3) m, confidence (B,),
        the point's index (B,) and the embedding (B, E, N): ``forward``'s numbers at that point (up to float rounding)
        for about a third of the multiply-adds.

        Only the confidence head runs on every point, and its first conv W = [W_f W_p W_c W_g] is linear in the
        features [F; PAM(F); CAM(F); GFEM(F)] (F: the fused C x N). With PAM(F) = g_p (W_v F + b_v 1^T) M^T + F, whose
        M has rows summing to 1, and CAM(F) = g_c A F + F:

            W x = (W_f + W_p + W_c + g_c W_c A) F + g_p ((W_p W_v) F) M^T + g_p W_p b_v 1^T + W_g GFEM(F)

        so PAM's and CAM's C x N outputs are never formed. F = [F_v; g 1^T] stacks the per-point channels F_v
        (2 p1 + 2 p2) on the global feature g (g2), the same at every point, so every product with F is taken as
        P F = P_v F_v + (P_g g) 1^T, and CAM's energy F F^T = [[F_v F_v^T, s g^T], [g s^T, N g g^T]] with
        s = F_v 1. The rotation and translation heads then run on the best point's features alone. Features are
        kept channels last (points x channels), so each 1x1 conv is one matrix product."""
        f = self.cnn(img)  # (B, E, S, S), channels last in memory (``runtime.for_inference``)
        B, E = f.shape[:2]
        emb = f.permute(0, 2, 3, 1).reshape(B, -1, E).gather(1, choose[..., None].expand(-1, -1, E))  # (B, N, E)
        fv, gf = self.feat.parts_last(points, emb)  # (B, N, Cv), (B, G2)
        n, cv = fv.shape[1:]

        def apply(w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # (O, C), (O,) -> [F_v; g 1^T]^T w^T + 1 b^T
            return torch.baddbmm(F.linear(gf, w[:, cv:], b)[:, None], fv, w[:, :cv].t().expand(B, -1, -1))  # (B, N, O)

        M = A = g = None
        if self.pam is not None:  # M (B, N, N), rows sum to 1
            q = apply(self.pam.query.weight[:, :, 0], self.pam.query.bias)  # (B, N, C')
            k = apply(self.pam.key.weight[:, :, 0], self.pam.key.bias)  # (B, N, C')
            M = torch.softmax(torch.bmm(q, k.transpose(1, 2)), dim=-1)
        if self.cam is not None:  # A (B, C, C) = softmax(rowmax(energy) - energy) = softmax(-energy)
            neg = fv.new_empty(B, cv + gf.shape[1], cv + gf.shape[1])  # -energy, written block by block
            ns = -fv.sum(dim=1)  # -s (B, Cv)
            neg[:, :cv, :cv] = torch.bmm(fv.transpose(1, 2), -fv)
            neg[:, :cv, cv:] = ns[:, :, None] * gf[:, None, :]
            neg[:, cv:, :cv] = gf[:, :, None] * ns[:, None, :]
            neg[:, cv:, cv:] = gf[:, :, None] * gf[:, None, :] * -n
            A = torch.softmax(neg, dim=-1)  # its subnormals zeroed: they halve the speed of the products with A
            A = F.threshold(A, torch.finfo(A.dtype).tiny, 0.0, inplace=not torch.is_grad_enabled())
        if self.gfem is not None:  # (B, G)
            g = torch.relu_(apply(self.gfem.conv.weight[:, :, 0], self.gfem.conv.bias)).mean(dim=1)
        first = self.head_c[0]
        W_f, W_p, W_c, W_g = first.weight[:, :, 0].split(self._part_widths, dim=1)  # (O, part width) each
        W = W_f + (W_p if M is not None else 0) + (W_c if A is not None else 0)  # (O, C)
        Wv, yg = W[:, :cv].expand(B, -1, -1), F.linear(gf, W[:, cv:], first.bias)  # (B, O, Cv), (B, O)
        if A is not None:  # + g_c W_c A F
            Wc, Ag = W_c.expand(B, -1, -1), torch.bmm(A[:, :, cv:], gf[:, :, None])  # (B, O, C), (B, C, 1)
            Wv = Wv + self.cam.gamma * torch.bmm(Wc, A[:, :, :cv])
            yg = yg + self.cam.gamma * torch.bmm(Wc, Ag)[..., 0]
        if g is not None:
            yg = yg + F.linear(g, W_g)
        y = torch.baddbmm(yg[:, None], fv, Wv.transpose(1, 2))  # (B, N, O): the first conv's output, PAM's term aside
        if M is not None:
            y = y + self.pam.gamma * torch.bmm(M, apply(*self._pam_value(W_p)))
        ar = torch.arange(B, device=fv.device)
        c = torch.sigmoid(self.head_c.last(y, 1)[ar, :, obj])  # (B, N)
        best = c.argmax(dim=1)
        fb = torch.cat([fv[ar, best], gf], dim=1)  # (B, C)
        xb = [fb]
        if M is not None:  # PAM at the best point b: g_p (W_v (F m_b) + b_v) + f_b, m_b = row b of M
            fm = torch.cat([torch.bmm(M[ar, best][:, None], fv)[:, 0], gf], dim=1)  # F m_b (B, C)
            xb.append(self.pam.gamma * pointwise(fm, self.pam.value) + fb)
        if A is not None:  # A f_b = A_v f_v + A_g g
            xb.append(self.cam.gamma * (torch.bmm(A[:, :, :cv], fb[:, :cv, None]) + Ag)[..., 0] + fb)
        if g is not None:
            xb.append(g)
        xb = torch.cat(xb, dim=1)  # (B, C_in)
        q = self.head_r.last(xb).view(B, -1, 4)[ar, obj]
        q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        t = self.head_t.last(xb).view(B, -1, 3)[ar, obj]
        return q, t, c[ar, best], best, emb.transpose(1, 2).detach()

    def _pam_value(self, W_p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """W_p W_v (O, C) and W_p b_v (O,): the confidence head's first conv's PAM block (W_p) times PAM's value conv,
        products of weights alone, made once per version of the weights (an optimiser step or a load bumps it); made
        anew each call where autograd records."""
        v = self.pam.value
        if torch.is_grad_enabled():
            return W_p @ v.weight[:, :, 0], W_p @ v.bias
        key = tuple((x.data_ptr(), x._version) for x in (self.head_c[0].weight, v.weight, v.bias))
        kept = self.__dict__.get("_pam_value_kept")
        if kept is None or kept[0] != key:
            kept = self.__dict__["_pam_value_kept"] = (key, (W_p @ v.weight[:, :, 0], W_p @ v.bias))
        return kept[1]


def build_pose_net(cfg: PoseNetConfig) -> PoseNet:
    """The pose net for ``cfg`` (random init; no pretrained weights)."""
    return PoseNet(cfg)
