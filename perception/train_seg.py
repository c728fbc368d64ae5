"""Training of the segmentation net (``perception.seg_net``) on a BOP dataset: ``train_seg`` writes ``RUN/seg/``.

Defaults follow the paper (Liang et al. 2021): SGD, momentum 0.9, batch 4, lr x0.8 every 5000 steps. The lr default is
1e-2 rather than the paper's 1e-4 because the net trains from scratch (no ImageNet weights).
"""

from __future__ import annotations

import dataclasses
from dataclasses import field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from posegrasp import bop
from posegrasp.config import settings, within
from posegrasp.errors import ConfigError
from posegrasp.perception.data import DataConfig, SegDataset, collate
from posegrasp.perception.metrics import confusion_matrix, segmentation_scores
from posegrasp.perception.seg_net import SegNetConfig, build_seg_net, seam_loss, seg_loss
from posegrasp.perception.training import (StageConfig, StageTraining, batch_stream, build_model, set_lr,
                                           split_exists, train_split, training_device)


#: ``SegTrainConfig.optimizer``'s values.
OPTIMIZERS = ("sgd", "adam")


@settings
class SegTrainConfig(StageConfig):
    """Segmentation training; ``model.num_classes`` is set from the dataset (max obj_id + 1)."""

    #: The net.
    model: SegNetConfig = field(default_factory=SegNetConfig)
    #: Samples and augmentation.
    data: DataConfig = field(default_factory=DataConfig)
    #: Images per batch.
    batch_size: int = field(default=4, metadata=within(1, 512))
    #: Initial learning rate.
    lr: float = field(default=1e-2, metadata=within(0, 10))
    #: SGD momentum.
    momentum: float = field(default=0.9, metadata=within(0, 1))
    #: L2 weight decay.
    weight_decay: float = field(default=1e-4, metadata=within(0, 10))
    #: Factor the learning rate is multiplied by every `lr_decay_every` steps.
    lr_decay: float = field(default=0.8, metadata=within(0, 1))
    #: Steps between learning-rate decays.
    lr_decay_every: int = field(default=5000, metadata=within(1, 100000000))
    #: `sgd` or `adam`.
    optimizer: str = "sgd"
    #: Cross-entropy weight of the background class (objects 1).
    background_weight: float = field(default=1.0, metadata=within(0, 1000))
    #: With ``model.seams``: the seam loss's weight beside the class loss ...
    seam_weight: float = field(default=1.0, metadata=within(0, 1000))
    #: ... and the weight of a seam pixel's term against a part's inner pixel's (``seg_net.seam_loss``).
    seam_pos_weight: float = field(default=3.0, metadata=within(0, 1000))
    #: Steps between evaluations on the validation split.
    eval_every: int = field(default=2000, metadata=within(0, 100000000))
    #: Validation images per evaluation.
    eval_images: int = field(default=50, metadata=within(0, 1000000))
    #: A seg checkpoint (or a run holding `seg/`) to fine-tune, with a fresh optimizer; empty: from scratch.
    init: str = ""
    #: Where the net trains: `cpu` or `cuda` (the checkpoint is the same either way).
    device: str = "cpu"
    #: Processes preparing batches ahead (0: the training process); batches do not depend on it.
    workers: int = field(default=0, metadata=within(0, 64))

    def __post_init__(self) -> None:
        """Batch normalisation needs two values per channel at the net's coarsest scale (1/32 of the input):
        ``batch_size * (height // 32) * (width // 32) >= 2``; the optimizer is one of ``OPTIMIZERS``."""
        if self.optimizer not in OPTIMIZERS:
            raise ConfigError(f"optimizer = {self.optimizer!r}: use 'sgd' or 'adam'")
        h, w = self.model.input_size
        if self.model.batch_norm and self.batch_size * (h // 32) * (w // 32) < 2:
            raise ConfigError(f"batch_size = {self.batch_size} with model.input_size = {list(self.model.input_size)} "
                              "leaves batch normalisation one value per channel at 1/32 scale; use batch_size >= 2 "
                              "or an input_size of at least 64 px on one side")


class SegTraining(StageTraining):
    """Per-pixel cross-entropy on the training images at the net's input size; mPA / mIoU on ``val_split``."""

    name, config, fine_tunes = "seg", SegTrainConfig, True
    columns = ["step", "time_s", "loss", "pixel_acc", "seam_loss", "lr", "val_mPA", "val_mIoU"]

    def build(self) -> None:
        cfg = self.cfg
        infos = bop.load_models_info(self.data)
        self.model_cfg = dataclasses.replace(cfg.model, num_classes=max(infos) + 1)
        self.cfg = cfg = dataclasses.replace(cfg, model=self.model_cfg)
        self.device = training_device(cfg.device)
        self.model = build_model("seg", build_seg_net, self.model_cfg).to(self.device)
        params = self.model.parameters()
        self.opt = (torch.optim.SGD(params, lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
                    if cfg.optimizer == "sgd" else torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay))
        self.state = {"step": 0, "lr": cfg.lr}

    def prepare(self, progress: bool) -> None:
        cfg, data, m = self.cfg, self.data, self.model_cfg
        self.ds = SegDataset(data, train_split(data, cfg.train_split), m.input_size, m.num_classes, cfg.data,
                             augment=True, seed=cfg.seed, seams=m.seams)
        self.val = (SegDataset(data, cfg.val_split, m.input_size, m.num_classes, cfg.data)
                    if split_exists(data, cfg.val_split) else None)
        self.batches = batch_stream(self.ds.get, collate, len(self.ds), cfg.batch_size, cfg.seed,
                                    int(self.state["step"]), cfg.steps, cfg.workers)

    def step(self, step: int) -> dict[str, float]:
        cfg = self.cfg
        self.model.train()
        batch = {k: v.to(self.device, non_blocking=True) for k, v in next(self.batches).items()}
        logits, seams = self.model.forward_seams(batch["image"])  # (B, C, H, W), (B, H, W) or None
        loss = seg_loss(logits, batch["label"], cfg.background_weight)
        out = {}
        if seams is not None:
            s_loss = seam_loss(seams, batch["seam"], batch["label"], cfg.seam_pos_weight)
            loss = loss + cfg.seam_weight * s_loss
            out["seam_loss"] = float(s_loss.detach())
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        acc = (logits.argmax(1) == batch["label"]).float().mean()
        return {"loss": float(loss.detach()), "pixel_acc": float(acc), **out}

    def after_step(self, step: int, values: dict[str, float]) -> dict[str, Any]:
        cfg = self.cfg
        lr = cfg.lr * cfg.lr_decay ** (step // cfg.lr_decay_every)
        set_lr(self.opt, lr)
        self.state.update(step=step, lr=lr)
        if self.val is not None and cfg.eval_every and step % cfg.eval_every == 0:
            s = evaluate_seg(self.model, self.val, cfg.eval_images)
            self.state.update(val_mIoU=s["mIoU"])
            return {"lr": lr, "val_mPA": s["mPA"], "val_mIoU": s["mIoU"]}
        return {"lr": lr}


def train_seg(data: str | Path, out: str | Path, cfg: SegTrainConfig | None = None, steps: int | None = None,
              seed: int | None = None, resume: bool = False, progress: bool = True) -> dict[str, float]:
    """Train the segmentation net on ``data`` (BOP root); checkpoints in ``out/seg``."""
    return SegTraining.train(data, out, cfg, steps, seed, resume, progress)


@torch.no_grad()
def evaluate_seg(model: torch.nn.Module, ds: SegDataset, max_images: int = 0) -> dict[str, Any]:
    """mPA / mIoU (%) of the net on (up to ``max_images`` of) a dataset at the net's input size."""
    model.eval()
    dev = next(model.parameters()).device
    n = len(ds) if not max_images else min(max_images, len(ds))
    conf = np.zeros((ds.num_classes, ds.num_classes), dtype=np.int64)
    for i in range(n):
        s = ds.get(i)
        pred = model(s["image"][None].to(dev)).argmax(1)[0].cpu()
        conf += confusion_matrix(pred.numpy(), s["label"].numpy(), ds.num_classes)
    return segmentation_scores(conf)
