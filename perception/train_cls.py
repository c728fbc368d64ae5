"""Training of the instance classifier (``perception.classifier``) on metric crops of the annotated instances and of
the run's seg net's segments: ``train_cls`` writes ``RUN/cls/``."""

from __future__ import annotations

import dataclasses
import hashlib
import math
from dataclasses import field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from posegrasp.config import settings, within
from posegrasp.errors import WeightsError
from posegrasp.perception import checkpoint as ckpt_mod
from posegrasp.perception.classifier import ClassifierConfig, build_classifier
from posegrasp.perception.data import ClsDataset, CropSource, DataConfig, collate
from posegrasp.perception.segmenter import Segmenter
from posegrasp.perception.training import (StageConfig, StageTraining, batch_keys, build_model, dataset_objects,
                                           init_checkpoint, set_lr, split_exists, train_split)


@settings
class ClsTrainConfig(StageConfig):
    """Instance classifier training (``perception.classifier``)."""

    #: The classifier net.
    model: ClassifierConfig = field(default_factory=ClassifierConfig)
    #: Samples and augmentation.
    data: DataConfig = field(default_factory=DataConfig)
    #: Objects trained; empty: every object of `models_info.json`.
    obj_ids: list[int] = field(default_factory=list)
    #: Training steps (batches).
    steps: int = field(default=3000, metadata=within(1, 100000000))
    #: Crops per batch.
    batch_size: int = field(default=64, metadata=within(1, 4096))
    #: Peak learning rate.
    lr: float = field(default=2e-3, metadata=within(0, 10))
    #: AdamW weight decay.
    weight_decay: float = field(default=1e-4, metadata=within(0, 10))
    #: Share of the steps over which the learning rate rises linearly; then a cosine to 0.
    warmup: float = field(default=0.1, metadata=within(0, 1))
    #: Also learn on the run's `seg/` net's segments of the training images, labelled by the ground truth.
    use_seg: bool = True
    #: Also learn a class 0, "not a block", from segments mostly on background (needs `use_seg`).
    background: bool = False
    #: A classifier checkpoint (or a run holding `cls/`) to fine-tune; its `[cls.model]` settings come with it.
    init: str = ""


def cls_lr(cfg: ClsTrainConfig, step: int) -> float:
    """Learning rate at ``step``: linear warm-up over ``warmup x steps``, then cosine to 0."""
    w = max(1, int(cfg.warmup * cfg.steps))
    if step < w:
        return cfg.lr * (step + 1) / w
    return 0.5 * cfg.lr * (1.0 + math.cos(math.pi * min(1.0, (step - w) / max(1, cfg.steps - w))))


class ClsTraining(StageTraining):
    """Cross-entropy on augmented crops (classes: ``obj_ids``, with 0 "not a block" first when ``background``);
    accuracy on ``val_split``. The crops are cached in ``RUN/cache/`` (a resumed run starts at once)."""

    name, config, fine_tunes = "cls", ClsTrainConfig, True
    columns = ["step", "time_s", "loss", "acc", "lr", "val_acc"]

    def build(self) -> None:
        cfg, run = self.cfg, self.run
        _, obj_ids = dataset_objects(self.data, cfg.obj_ids)
        self.has_seg = cfg.use_seg and ckpt_mod.exists(run.out / "seg")
        if cfg.background and not self.has_seg:
            raise WeightsError(f"[cls] background = true learns from the seg net's segments: train seg into {run.out} "
                               "first (and keep use_seg = true), or set background = false")
        obj_ids = ([0] if cfg.background else []) + obj_ids  # 0: "not a block"
        model = cfg.model
        if cfg.init:  # fine-tuning: the crop settings and channels come with the weights
            model = ckpt_mod.load_model(init_checkpoint(Path(cfg.init), "cls"), "cls")[1]
        self.model_cfg = dataclasses.replace(model, obj_ids=obj_ids)
        self.cfg = cfg = dataclasses.replace(cfg, model=self.model_cfg)
        self.model = build_model("cls", build_classifier, self.model_cfg)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.state = {"step": 0, "lr": cfg.lr}

    def prepare(self, progress: bool) -> None:
        cfg, m, run, data = self.cfg, self.model_cfg, self.run, self.data
        segmenter: Callable[[np.ndarray], list[tuple[int, np.ndarray]]] | None = None
        seg_id = ""
        if self.has_seg:
            segmenter = Segmenter.load(run.out / "seg").parts
            seg_id = hashlib.sha256((run.out / "seg" / "model.safetensors").read_bytes()).hexdigest()

        def dataset(split: str, augment: bool) -> ClsDataset:  # crops cached in the run: a resume starts at once
            source = CropSource(segmenter, seg_id, run.out / "cache" / f"cls_crops_{split}.npy", progress)
            return ClsDataset(data, split, m, cfg.data, augment, cfg.seed, source)

        self.ds = dataset(train_split(data, cfg.train_split), True)
        self.val = dataset(cfg.val_split, False) if split_exists(data, cfg.val_split) else None

    def step(self, step: int) -> dict[str, float]:
        cfg = self.cfg
        self.model.train()
        set_lr(self.opt, cls_lr(cfg, step))
        b = collate([self.ds.get(i, key) for i, key in batch_keys(len(self.ds), step, cfg.batch_size, cfg.seed)])
        logits = self.model(b["image"])  # (B, classes)
        loss = torch.nn.functional.cross_entropy(logits, b["label"])
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return {"loss": float(loss.detach()), "acc": float((logits.argmax(1) == b["label"]).float().mean())}

    def after_step(self, step: int, values: dict[str, float]) -> dict[str, Any]:
        cfg, state = self.cfg, self.state
        state.update(step=step, lr=cls_lr(cfg, step))
        if self.val is not None and cfg.eval_every and step % cfg.eval_every == 0:
            state["val_acc"] = evaluate_cls(self.model, self.val)
            return {"lr": state["lr"], "val_acc": state["val_acc"]}
        return {"lr": state["lr"]}

    def summary(self) -> dict[str, Any]:
        return {"samples": len(self.ds)}


def train_cls(data: str | Path, out: str | Path, cfg: ClsTrainConfig | None = None, steps: int | None = None,
              seed: int | None = None, resume: bool = False, progress: bool = True) -> dict[str, float]:
    """Train the instance classifier on ``data`` (with the segments of ``out/seg`` when present and
    ``cfg.use_seg``); checkpoints in ``out/cls``."""
    return ClsTraining.train(data, out, cfg, steps, seed, resume, progress)


@torch.no_grad()
def evaluate_cls(model: torch.nn.Module, ds: ClsDataset, batch_size: int = 256) -> float:
    """Accuracy (fraction) of the classifier on every sample of ``ds`` (no augmentation)."""
    model.eval()
    right = 0
    for s in range(0, len(ds), batch_size):
        b = collate([ds.get(i) for i in range(s, min(len(ds), s + batch_size))])
        right += int((model(b["image"]).argmax(1) == b["label"]).sum())
    return right / len(ds)
