"""Training of the refiner (``perception.refiner``) on top of the run's frozen pose net: ``train_refiner`` writes
``RUN/refiner/``."""

from __future__ import annotations

import dataclasses
from dataclasses import field
from pathlib import Path
from typing import Any

import torch

from posegrasp.config import settings, within
from posegrasp.perception import checkpoint as ckpt_mod
from posegrasp.perception.data import DataConfig
from posegrasp.perception.refiner import RefinerConfig, build_refiner
from posegrasp.perception.train_pose import evaluate_pose, pose_datasets, pose_forward, refiner_steps, to_batch
from posegrasp.perception.training import StageConfig, StageTraining, batch_keys, build_model


@settings
class RefinerTrainConfig(StageConfig):
    """Refiner training on top of the frozen pose net in ``RUN/pose`` (its objects and embedding
    width are copied into ``model``). lr defaults to DenseFusion's decayed lr (1e-4 x 0.3)."""

    #: The refiner net.
    model: RefinerConfig = field(default_factory=RefinerConfig)
    #: Samples and augmentation.
    data: DataConfig = field(default_factory=DataConfig)
    #: Training steps (batches).
    steps: int = field(default=10000, metadata=within(1, 100000000))
    #: Learning rate (DenseFusion's decayed 1e-4 x 0.3).
    lr: float = field(default=3e-5, metadata=within(0, 10))
    #: Refiner iterations per sample in training.
    iterations: int = field(default=2, metadata=within(1, 100))
    #: Validation samples per evaluation.
    eval_samples: int = field(default=200, metadata=within(1, 100000000))


class RefinerTraining(StageTraining):
    """``iterations`` refiner steps per batch from the frozen pose net's estimates, each step's loss
    backpropagated; the evaluation's mean distance after them is logged."""

    name, config, needs = "refiner", RefinerTrainConfig, "pose"
    columns = ["step", "time_s", "loss", "dis_pose", "dis", "lr", "val_dis"]

    def build(self) -> None:
        cfg = self.cfg
        self.pose_net, self.pose_cfg, _ = ckpt_mod.load_model(self.run.out / "pose", "pose")
        for p in self.pose_net.parameters():
            p.requires_grad_(False)
        pc = self.pose_cfg
        self.model_cfg = dataclasses.replace(cfg.model, obj_ids=list(pc.obj_ids), symmetric=list(pc.symmetric),
                                             emb_dim=pc.emb_dim)
        self.cfg = cfg = dataclasses.replace(cfg, model=self.model_cfg)
        self.model = build_model("refiner", build_refiner, self.model_cfg)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.state = {"step": 0, "lr": cfg.lr, "best_val_dis": None}

    def prepare(self, progress: bool) -> None:
        self.ds, self.val, self.val_idx = pose_datasets(self.data, self.cfg, self.pose_cfg)

    def step(self, step: int) -> dict[str, float]:
        cfg = self.cfg
        self.model.train()
        b = to_batch(self.ds, batch_keys(len(self.ds), step, cfg.batch_size, cfg.seed))
        with torch.no_grad():
            out, emb = pose_forward(self.pose_net, b, 0.015)
        self.opt.zero_grad(set_to_none=True)
        dis = refiner_steps(self.model, b, out, emb, cfg.iterations, train=True)
        self.opt.step()
        return {"loss": float(sum(float(d.mean()) for d in dis)), "dis_pose": float(out.dis.mean()),
                "dis": float(dis[-1].mean())}

    def after_step(self, step: int, values: dict[str, float]) -> dict[str, Any]:
        cfg, state = self.cfg, self.state
        state["step"] = step
        if not (cfg.eval_every and step % cfg.eval_every == 0):
            return {"lr": state["lr"]}
        d = evaluate_pose(self.pose_net, self.val, self.val_idx, cfg.batch_size, refiner=self.model,
                          iterations=cfg.iterations)
        if state["best_val_dis"] is None or d < state["best_val_dis"]:
            state["best_val_dis"] = d
        return {"lr": state["lr"], "val_dis": d}

    def summary(self) -> dict[str, Any]:
        return {"best_val_dis": self.state["best_val_dis"]}


def train_refiner(data: str | Path, out: str | Path, cfg: RefinerTrainConfig | None = None, steps: int | None = None,
                  seed: int | None = None, resume: bool = False, progress: bool = True) -> dict[str, float]:
    """Train the refiner on ``data`` with the frozen pose net of ``out/pose``; checkpoints in
    ``out/refiner``."""
    return RefinerTraining.train(data, out, cfg, steps, seed, resume, progress)
