"""Training of the pose net (``perception.pose_net``) on a BOP dataset: ``train_pose`` writes ``RUN/pose/``; also the
pose samples, forward pass and evaluation the refiner's training shares (``perception.train_refiner``).

Defaults follow the paper (Liang et al. 2021): Adam lr 1e-4, batch 8, lr x0.3 and confidence weight w x0.3 once the
evaluation mean distance drops under 0.016 m, ready for the refiner's training under 0.013 m.
"""

from __future__ import annotations

import dataclasses
from dataclasses import field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from posegrasp.config import settings, within
from posegrasp.errors import ConfigError
from posegrasp.perception.data import DataConfig, ObjectModels, PoseDataset, collate
from posegrasp.perception.losses import PoseTargets, pose_loss, refiner_loss
from posegrasp.perception.pose_net import PoseNetConfig, build_pose_net
from posegrasp.perception.training import (StageConfig, StageTraining, batch_keys, build_model, dataset_objects,
                                           set_lr, split_exists, train_split)


#: ``PoseTrainConfig.sym_loss``'s values.
SYM_LOSSES = ("adds", "min_sym")


@settings
class PoseTrainConfig(StageConfig):
    """Pose net training; ``model.obj_ids`` and ``model.symmetric`` are set from the dataset.

    The evaluation that drives the lr / w decay uses ``val_split``, or a fixed subset of the training instances (no
    augmentation) when that split does not exist.
    """

    #: The net.
    model: PoseNetConfig = field(default_factory=PoseNetConfig)
    #: Samples and augmentation.
    data: DataConfig = field(default_factory=DataConfig)
    #: Objects trained; empty: every object of `models_info.json`.
    obj_ids: list[int] = field(default_factory=list)
    #: Weight of the confidence regulariser in the loss (DenseFusion's w).
    w: float = field(default=0.015, metadata=within(0, 10))
    #: Once the validation mean distance (m) falls below this, lr and w decay (once).
    decay_margin: float = field(default=0.016, metadata=within(0, 10))
    #: Factor of that learning-rate decay.
    lr_decay: float = field(default=0.3, metadata=within(0, 1))
    #: Factor of that w decay.
    w_decay: float = field(default=0.3, metadata=within(0, 1))
    #: Below this validation mean distance (m) the checkpoint is marked ready for refiner training.
    refine_margin: float = field(default=0.013, metadata=within(0, 10))
    #: Validation samples per evaluation.
    eval_samples: int = field(default=200, metadata=within(1, 100000000))
    #: `adds` (ADD-S for symmetric objects, as the paper) or `min_sym` (least ADD over discrete symmetries).
    sym_loss: str = "adds"
    #: A pose checkpoint (or a run holding `pose/`) to fine-tune; empty: from scratch.
    init: str = ""

    def __post_init__(self) -> None:
        if self.sym_loss not in SYM_LOSSES:
            raise ConfigError(f"sym_loss = {self.sym_loss!r}: use 'adds' or 'min_sym'")


class PoseTraining(StageTraining):
    """The pose loss (ADD / ADD-S weighted by the confidences) on per-object samples; the evaluation's mean distance
    drives the lr and w decay."""

    name, config, fine_tunes = "pose", PoseTrainConfig, True
    columns = ["step", "time_s", "loss", "dis", "lr", "w", "val_dis"]

    def build(self) -> None:
        cfg = self.cfg
        infos, obj_ids = dataset_objects(self.data, cfg.obj_ids)
        self.model_cfg = dataclasses.replace(cfg.model, obj_ids=obj_ids,
                                             symmetric=[infos[o].symmetric for o in obj_ids])
        self.cfg = cfg = dataclasses.replace(cfg, model=self.model_cfg)
        self.model = build_model("pose", build_pose_net, self.model_cfg)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.state = {"step": 0, "lr": cfg.lr, "w": cfg.w, "decayed": False, "refine_ready": False,
                      "best_val_dis": None}

    def prepare(self, progress: bool) -> None:
        self.ds, self.val, self.val_idx = pose_datasets(self.data, self.cfg, self.model_cfg)

    def step(self, step: int) -> dict[str, float]:
        cfg, state = self.cfg, self.state
        self.model.train()
        b = to_batch(self.ds, batch_keys(len(self.ds), step, cfg.batch_size, cfg.seed))
        out, _ = pose_forward(self.model, b, state["w"], cfg.sym_loss)
        self.opt.zero_grad(set_to_none=True)
        out.loss.backward()
        self.opt.step()
        return {"loss": float(out.loss.detach()), "dis": float(out.dis.mean())}

    def after_step(self, step: int, values: dict[str, float]) -> dict[str, Any]:
        cfg, state = self.cfg, self.state
        state["step"] = step
        if not (cfg.eval_every and step % cfg.eval_every == 0):
            return {"lr": state["lr"], "w": state["w"]}
        d = evaluate_pose(self.model, self.val, self.val_idx, cfg.batch_size)
        if state["best_val_dis"] is None or d < state["best_val_dis"]:
            state["best_val_dis"] = d
        if d < cfg.decay_margin and not state["decayed"]:
            state.update(decayed=True, lr=state["lr"] * cfg.lr_decay, w=state["w"] * cfg.w_decay)
            set_lr(self.opt, state["lr"])
        if d < cfg.refine_margin:
            state["refine_ready"] = True
        return {"lr": state["lr"], "w": state["w"], "val_dis": d}

    def summary(self) -> dict[str, Any]:
        return {"best_val_dis": self.state["best_val_dis"]}


def train_pose(data: str | Path, out: str | Path, cfg: PoseTrainConfig | None = None, steps: int | None = None,
               seed: int | None = None, resume: bool = False, progress: bool = True) -> dict[str, float]:
    """Train the pose net on ``data`` (BOP root); checkpoints in ``out/pose``."""
    return PoseTraining.train(data, out, cfg, steps, seed, resume, progress)


def pose_datasets(data: Path, cfg: Any, model: PoseNetConfig) -> tuple[PoseDataset, PoseDataset, list[int]]:
    """The augmented training samples of the pose net ``model``'s objects, the evaluation samples (``val_split``,
    else the training instances without augmentation) and the indices of the ``cfg.eval_samples`` evaluated, spread
    over them (``cfg``: a ``PoseTrainConfig`` or ``RefinerTrainConfig``)."""
    models = ObjectModels(data, cfg.data.model_pool)
    split = train_split(data, cfg.train_split)
    train = PoseDataset(data, split, model, cfg.data, augment=True, seed=cfg.seed, models=models)
    if split_exists(data, cfg.val_split):
        val = PoseDataset(data, cfg.val_split, model, cfg.data, models=models)
    else:  # no validation split: a fixed subset of the training instances, without augmentation
        val = PoseDataset(data, split, model, cfg.data, models=models)
    n = min(cfg.eval_samples, len(val))
    idx = sorted({int(i) for i in np.linspace(0, len(val) - 1, n)})
    return train, val, idx


def to_batch(ds: PoseDataset, keys: list[tuple[int, int | None]]) -> dict[str, torch.Tensor]:
    """The samples (index, augmentation key or None) of ``ds`` as one batch."""
    return collate([ds.get(i, k) for i, k in keys])


def pose_forward(model: torch.nn.Module, b: dict[str, torch.Tensor], w: float, sym_loss: str = "adds"):
    """The pose net on batch ``b`` and its loss (confidence weight ``w``, ``sym_loss`` as in ``PoseTrainConfig``);
    (the loss's output, the per-point embeddings)."""
    q, t, c, emb = model(b["image"], b["points"], b["choose"], b["obj"])
    return pose_loss(q, t, c, PoseTargets.of(b, min_sym=sym_loss == "min_sym"), w), emb


@torch.no_grad()
def evaluate_pose(model: torch.nn.Module, ds: PoseDataset, indices: list[int], batch_size: int = 8,
                  refiner: torch.nn.Module | None = None, iterations: int = 0) -> float:
    """Mean distance (m, ADD or ADD-S per object) of the most confident proposal, optionally after
    ``iterations`` steps of the refiner, over dataset samples ``indices`` (no augmentation)."""
    model.eval()
    if refiner is not None:
        refiner.eval()
    dis = []
    for s in range(0, len(indices), batch_size):
        b = to_batch(ds, [(i, None) for i in indices[s:s + batch_size]])
        out, emb = pose_forward(model, b, 0.015)
        d = out.dis
        if refiner is not None and iterations > 0:
            d = refiner_steps(refiner, b, out, emb, iterations, train=False)[-1]
        dis.append(d)
    return float(torch.cat(dis).mean())


def refiner_steps(refiner: torch.nn.Module, b: dict[str, torch.Tensor], out, emb: torch.Tensor,
                  iterations: int, train: bool) -> list[torch.Tensor]:
    """DenseFusion's refiner training / evaluation: per iteration, refine in the current frame,
    (backpropagate), and move points and target into the refined frame. Returns dis per iteration."""
    points, target = out.new_points, out.new_target
    dis = []
    for _ in range(iterations):
        dq, dt = refiner(points, emb, b["obj"])
        r = refiner_loss(dq, dt, points, b["model_points"], target, b["symmetric"])
        if train:
            r.loss.backward()
        dis.append(r.dis)
        points, target = r.new_points, r.new_target
    return dis
