"""Segmentation network of the paper: a VGG16-style encoder and a decoder of three Multi-scale
Feature Fusion Modules (MFFM), two upsampling layers and a final conv giving per-pixel logits.

Encoder: 16 convs and 5 max-pools; the first 13 convs are VGG16's (64, 64, M, 128, 128, M,
256 x3, M, 512 x3, M, 512 x3, M), then 3 more 3x3 convs (512) at 1/32 resolution form the
bottleneck. Stage k (k = 1..5) outputs the features before its pool, at 1/2^(k-1) resolution.
Decoder (the bottleneck is the first "previous decoder layer"):

- MFFM1 at 1/16: stage 5 and the bottleneck (upsampled x2),
- MFFM2 at 1/8: stages 4, 5 and MFFM1,
- MFFM3 at 1/4: stages 3, 4, 5 and MFFM2,

every encoder input through its own conv to 64 channels, the previous decoder input through a conv
keeping its channels, all concatenated and fused by a 3x3 conv. Then two x2 upsampling layers
(bilinear + conv) back to full resolution and a 1x1 conv to ``num_classes`` logits (class 0 is
background, class k the object with BOP obj_id k). Every channel count is scaled by ``width``.

With ``seams``, a second 1x1 conv on the same features gives a seam logit per pixel: whether the pixel belongs to a
part and touches (8-connected) a pixel of another part. The foreground cut along the seams falls apart into one
component per part, also where touching parts are of one type (``inputs.seam_components``): the contour-aware
instance segmentation of DCAN (Chen et al. 2016) on the paper's decoder.
"""

from __future__ import annotations

from dataclasses import field

import torch
import torch.nn.functional as F
from torch import nn

from posegrasp.config import settings, within

#: VGG16's 13 convs, then this model's 3 extra bottleneck convs; "M" = 2x2 max-pool.
VGG16_PLAN: tuple[int | str, ...] = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M",
                                     512, 512, 512, "M", 512, 512, 512, "M")
EXTRA_CONVS: tuple[int, ...] = (512, 512, 512)


@settings
class SegNetConfig:
    """Segmentation net hyper-parameters; every channel count is scaled by ``width``."""

    #: Classes: background + objects (class = BOP obj_id); set from the dataset.
    num_classes: int = field(default=4, metadata=within(2, 100000))
    #: Channel multiplier (1.0 is the paper's net; 0.25 runs on a CPU).
    width: float = field(default=0.25, metadata=within(0.01, 4.0))
    #: (height, width) (px) the image is resized to; at least 32, multiples of 32 avoid rounding.
    input_size: tuple[int, int] = field(default=(240, 320), metadata=within(32, 2048))
    #: Output channels of MFFM1..3 at width 1.0.
    mffm_channels: tuple[int, int, int] = field(default=(256, 128, 64), metadata=within(1, 4096))
    #: Conv width of every encoder input of an MFFM (64 in the paper).
    encoder_skip_channels: int = field(default=64, metadata=within(1, 4096))
    #: Channels of the two upsampling convs.
    up_channels: tuple[int, int] = field(default=(64, 32), metadata=within(1, 4096))
    #: Batch normalisation after the convs.
    batch_norm: bool = True
    #: Also predict seams between touching parts (one more 1x1 conv), which split the foreground into parts.
    seams: bool = False

    def scaled(self, c: int) -> int:
        """Channel count ``c`` at this width (at least 4)."""
        return max(4, int(round(c * self.width)))



class ConvBNReLU(nn.Sequential):
    """k x k conv (same padding) + optional BatchNorm + ReLU."""

    def __init__(self, cin: int, cout: int, k: int = 3, bn: bool = True):
        layers: list[nn.Module] = [nn.Conv2d(cin, cout, k, padding=k // 2, bias=not bn)]
        if bn:
            layers.append(nn.BatchNorm2d(cout))
        layers.append(nn.ReLU(inplace=True))
        super().__init__(*layers)


class VGGEncoder(nn.Module):
    """VGG16 convs in 5 stages + 3 bottleneck convs; returns the 5 pre-pool stage outputs and the
    bottleneck (1/32 resolution)."""

    def __init__(self, cfg: SegNetConfig):
        super().__init__()
        self.stages = nn.ModuleList()
        cin, layers = 3, []
        for v in VGG16_PLAN:
            if v == "M":
                self.stages.append(nn.Sequential(*layers))
                layers = []
            else:
                c = cfg.scaled(int(v))
                layers.append(ConvBNReLU(cin, c, bn=cfg.batch_norm))
                cin = c
        self.pool = nn.MaxPool2d(2, 2)
        extra = []
        for v in EXTRA_CONVS:
            c = cfg.scaled(v)
            extra.append(ConvBNReLU(cin, c, bn=cfg.batch_norm))
            cin = c
        self.bottleneck = nn.Sequential(*extra)
        self.stage_channels = [cfg.scaled(c) for c in (64, 128, 256, 512, 512)]
        self.out_channels = cin

    def forward(self, x: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
        feats = []
        for stage in self.stages:
            x = stage(x)  # stage k: (B, C_k, H / 2^(k-1), W / 2^(k-1))
            feats.append(x)
            x = self.pool(x)
        return feats, self.bottleneck(x)  # bottleneck: (B, C, H / 32, W / 32)


class MFFM(nn.Module):
    """Multi-scale feature fusion at one resolution: each encoder input -> its own conv (skip
    channels), the previous decoder input -> a conv keeping its channels; inputs at lower resolution
    are upsampled (bilinear) first; all concatenated and fused by a 3x3 conv to ``out_channels``."""

    def __init__(self, enc_channels: list[int], prev_channels: int, skip_channels: int, out_channels: int,
                 bn: bool = True):
        super().__init__()
        self.enc_convs = nn.ModuleList(ConvBNReLU(c, skip_channels, bn=bn) for c in enc_channels)
        self.prev_conv = ConvBNReLU(prev_channels, prev_channels, bn=bn)
        self.fuse = ConvBNReLU(skip_channels * len(enc_channels) + prev_channels, out_channels, bn=bn)

    def forward(self, enc: list[torch.Tensor], prev: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        def up(x: torch.Tensor) -> torch.Tensor:
            return x if x.shape[-2:] == size else F.interpolate(x, size=size, mode="bilinear", align_corners=False)

        parts = [conv(up(e)) for conv, e in zip(self.enc_convs, enc)]
        parts.append(self.prev_conv(up(prev)))
        return self.fuse(torch.cat(parts, dim=1))  # (B, out_channels, *size)


class UpBlock(nn.Module):
    """Bilinear upsampling (x2, to the given size) + 3x3 conv."""

    def __init__(self, cin: int, cout: int, bn: bool = True):
        super().__init__()
        self.conv = ConvBNReLU(cin, cout, bn=bn)

    def forward(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        return self.conv(F.interpolate(x, size=size, mode="bilinear", align_corners=False))


class SegNet(nn.Module):
    """VGG16 encoder + 3 MFFMs + 2 upsamplings + 1x1 classifier: (B, 3, H, W) -> (B, classes, H, W)."""

    def __init__(self, cfg: SegNetConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = VGGEncoder(cfg)
        sc = self.encoder.stage_channels
        skip = cfg.scaled(cfg.encoder_skip_channels)
        m1, m2, m3 = (cfg.scaled(c) for c in cfg.mffm_channels)
        bn = cfg.batch_norm
        self.mffm1 = MFFM([sc[4]], self.encoder.out_channels, skip, m1, bn)  # 1/16
        self.mffm2 = MFFM([sc[3], sc[4]], m1, skip, m2, bn)  # 1/8
        self.mffm3 = MFFM([sc[2], sc[3], sc[4]], m2, skip, m3, bn)  # 1/4
        u1, u2 = (cfg.scaled(c) for c in cfg.up_channels)
        self.up1 = UpBlock(m3, u1, bn)  # 1/2
        self.up2 = UpBlock(u1, u2, bn)  # 1/1
        self.classifier = nn.Conv2d(u2, cfg.num_classes, 1)
        self.seam = nn.Conv2d(u2, 1, 1) if cfg.seams else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Logits (B, num_classes, H, W); apply softmax for probabilities."""
        return self.classifier(self.features(x))

    def forward_seams(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Class logits (B, num_classes, H, W) and seam logits (B, H, W) (None without ``cfg.seams``)."""
        d = self.features(x)
        return self.classifier(d), None if self.seam is None else self.seam(d)[:, 0]

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """The decoder's full-resolution features (B, u2, H, W) of images (B, 3, H, W)."""
        s, b = self.encoder(x)
        d = self.mffm1([s[4]], b, tuple(s[4].shape[-2:]))  # (B, m1, H/16, W/16)
        d = self.mffm2([s[3], s[4]], d, tuple(s[3].shape[-2:]))  # (B, m2, H/8, W/8)
        d = self.mffm3([s[2], s[3], s[4]], d, tuple(s[2].shape[-2:]))  # (B, m3, H/4, W/4)
        d = self.up1(d, tuple(s[1].shape[-2:]))  # (B, u1, H/2, W/2)
        return self.up2(d, tuple(s[0].shape[-2:]))  # (B, u2, H, W)


def seg_loss(logits: torch.Tensor, labels: torch.Tensor, background_weight: float = 1.0) -> torch.Tensor:
    """Pixel-wise cross-entropy; logits (B, C, H, W), labels (B, H, W) int64.

    ``background_weight`` < 1 down-weights class 0: small objects in wide views cover a few percent of
    the pixels, and plain cross-entropy (weight 1, the paper's loss) then first settles on all-background.
    """
    weight = None
    if background_weight != 1.0:
        weight = torch.ones(logits.shape[1], dtype=logits.dtype, device=logits.device)
        weight[0] = background_weight
    return F.cross_entropy(logits, labels, weight=weight)


def seam_loss(logits: torch.Tensor, seams: torch.Tensor, labels: torch.Tensor, pos_weight: float) -> torch.Tensor:
    """Binary cross-entropy of the seam logits (B, H, W) against the seam targets (B, H, W) bool on the parts' pixels
    (labels (B, H, W) > 0) only: off the parts the class map already says there is no part. Seams are a few per cent
    of those pixels: ``pos_weight`` scales their terms."""
    on = labels > 0
    if not bool(on.any()):
        return logits.sum() * 0.0
    w = torch.tensor(pos_weight, dtype=logits.dtype, device=logits.device)
    return F.binary_cross_entropy_with_logits(logits[on], seams[on].to(logits.dtype), pos_weight=w)


def build_seg_net(cfg: SegNetConfig) -> SegNet:
    """The segmentation net for ``cfg`` (random init; no pretrained weights)."""
    return SegNet(cfg)
