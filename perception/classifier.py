"""Instance classifier: which block is this segment? (an addition to the paper's pipeline).

The segmentation net finds the blocks well (foreground IoU ~86 on the test split) but often confuses
their types: the blocks differ by shape, not colour (datagen draws colours at random), and at the
CPU input size a block is a few dozen pixels. This net re-labels every connected segment of the
class map from a crop of fixed metric size (``crop_side`` metres at the segment's median depth, so
pixels have the same size in metres at any distance) with RGB, the segment's mask and the depth
relative to the segment (``perception.inputs.prepare_cls_input``).

    x (B, 6 or 7, S, S) -> [conv-BN-ReLU x2, max-pool] per width -> global average -> linear -> (B, K) logits

With ``height_range`` > 0 the crop has a 7th channel: the height above the supporting plane (table), which tells
apart blocks that look alike from above but not from the side (an arch and a 2x4 brick, a lying prism and an
L-block, a 2x2 brick and a cube) whatever the camera's tilt; the relative depth alone mixes heights with the
tilt's ramp.

K = len(obj_ids); logit k is object ``obj_ids[k]``. Id 0 among them is "not a block" (the seg net's background
id): segments it wins are dropped, which removes distractors the seg net took for blocks.
``EstimatorConfig(classify=False)`` and ``posegrasp eval --no-cls`` give the paper's pipeline without it.
"""

from __future__ import annotations

from dataclasses import field

import torch
from torch import nn

from posegrasp.config import settings, within
from posegrasp.errors import ConfigError
from posegrasp.perception.seg_net import ConvBNReLU

IN_CHANNELS = 6  # RGB (normalised), mask, relative depth, valid depth (+ height above the plane, optional)


@settings
class ClassifierConfig:
    """The instance classifier: a small CNN on a crop of fixed metric size around each segment."""

    #: Classes (BOP ids; 0: not a block); set from the dataset.
    obj_ids: list[int] = field(default_factory=lambda: [1, 2, 3])
    #: Channels of the conv stages, a 2x max-pool between stages.
    widths: tuple[int, ...] = field(default=(16, 32, 64, 128), metadata=within(1, 4096))
    #: Input side (px).
    crop_size: int = field(default=64, metadata=within(8, 1024))
    #: The crop's side (m) at the segment's median depth.
    crop_side: float = field(default=0.16, metadata=within(0.001, 10))
    #: Depths relative to the segment's are clipped to +-this (m), scaled to [-1, 1].
    depth_range: float = field(default=0.05, metadata=within(0.0001, 10))
    #: Above 0: a channel of the height (m) above the supporting plane, clipped to [0, this].
    height_range: float = field(default=0.0, metadata=within(0, 10))

    @property
    def in_channels(self) -> int:
        """Channels of the crop (``perception.inputs.prepare_cls_input``)."""
        return IN_CHANNELS + (self.height_range > 0)

    def __post_init__(self) -> None:
        if not self.obj_ids:
            raise ConfigError("obj_ids = []: name at least one object")
        if not self.widths:
            raise ConfigError("widths = []: give the channels of at least one conv stage")
        if self.crop_size < 2 ** (len(self.widths) - 1):
            raise ConfigError(f"crop_size = {self.crop_size} is too small for {len(self.widths)} pooled stages: use at "
                              f"least {2 ** (len(self.widths) - 1)}")


class CropClassifier(nn.Module):
    """A small VGG-style CNN over metric crops: (B, C, S, S) -> (B, K) logits."""

    def __init__(self, cfg: ClassifierConfig):
        super().__init__()
        self.cfg = cfg
        layers: list[nn.Module] = []
        cin = cfg.in_channels
        for i, w in enumerate(cfg.widths):
            if i:
                layers.append(nn.MaxPool2d(2))  # (B, C, S / 2^i, S / 2^i)
            layers += [ConvBNReLU(cin, w), ConvBNReLU(w, w)]
            cin = w
        self.features = nn.Sequential(*layers)
        self.fc = nn.Linear(cin, len(cfg.obj_ids))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.features(x).mean(dim=(2, 3)))  # (B, C) -> (B, K)


def build_classifier(cfg: ClassifierConfig) -> CropClassifier:
    """The instance classifier for ``cfg`` (random init)."""
    return CropClassifier(cfg)
