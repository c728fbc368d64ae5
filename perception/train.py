"""Training of the segmentation net, the pose net and the refiner on a BOP dataset.

``train_seg``, ``train_pose``, ``train_refine`` and ``train_cls`` write ``RUN/<stage>/`` checkpoints (see
``perception.checkpoint``) and ``RUN/<stage>_metrics.csv``. Runs are seeded and resumable: batch
composition and augmentation are functions of (seed, step), and the checkpoint holds the weights,
the optimizer state, the schedule state and the torch RNG, so a killed run resumed with
``resume=True`` continues exactly where its last checkpoint was written.

Defaults follow the paper (REFERENCE §1): segmentation SGD, momentum 0.9, batch 4, lr x0.8 every
5000 steps; pose Adam lr 1e-4, batch 8, lr x0.3 and confidence weight w x0.3 once the evaluation
mean distance drops under 0.016 m, refinement ready under 0.013 m. The segmentation lr default is
1e-2 rather than the paper's 1e-4 because the net trains from scratch (no ImageNet weights).
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from posegrasp import bop
from posegrasp import io as pio
from posegrasp.errors import UserError
from posegrasp.perception import checkpoint as ckpt_mod
from posegrasp.perception.classifier import ClassifierConfig, build_classifier
from posegrasp.perception.data import ClsDataset, DataConfig, ObjectModels, PoseDataset, SegDataset, collate
from posegrasp.perception.losses import pose_loss, refine_loss
from posegrasp.perception.metrics import confusion_matrix, segmentation_scores
from posegrasp.perception.pose_net import PoseNetConfig, build_pose_net
from posegrasp.perception.refiner import RefinerConfig, build_refiner
from posegrasp.perception.seg_net import SegNetConfig, build_seg_net, seg_loss


@dataclass
class StageConfig:
    """What every stage's training has: splits (``train_split`` empty = ``train_pbr`` if present,
    else ``train``), logging, checkpoint and evaluation intervals (steps), seed and CPU threads."""

    train_split: str = ""
    val_split: str = "val"
    steps: int = 20000
    batch_size: int = 8
    lr: float = 1e-4
    log_every: int = 20
    checkpoint_every: int = 500
    eval_every: int = 1000
    seed: int = 0
    threads: int = 2


@dataclass
class SegTrainConfig(StageConfig):
    """Segmentation training. ``model.num_classes`` is set from the dataset (max obj_id + 1).
    ``val_split`` is evaluated (on ``eval_images``) every ``eval_every`` steps when it exists.
    ``init`` names a seg checkpoint (or a run holding ``seg/``) whose weights the net starts from
    (fine-tuning, fresh optimizer); empty = from scratch."""

    model: SegNetConfig = field(default_factory=SegNetConfig)
    data: DataConfig = field(default_factory=DataConfig)
    batch_size: int = 4
    lr: float = 1e-2
    momentum: float = 0.9
    weight_decay: float = 1e-4
    lr_decay: float = 0.8
    lr_decay_every: int = 5000
    optimizer: str = "sgd"
    background_weight: float = 1.0
    eval_every: int = 2000
    eval_images: int = 50
    init: str = ""


@dataclass
class PoseTrainConfig(StageConfig):
    """Pose net training. ``obj_ids`` empty = every object of models_info; ``model.obj_ids`` and
    ``model.symmetric`` are set from the dataset. The evaluation that drives the lr / w decay uses
    ``val_split``, or a fixed subset of the training instances (no augmentation) when that split
    does not exist. ``sym_loss``: "adds" (the paper: ADD-S for every symmetric object) or "min_sym"
    (the minimum ADD over each object's discrete symmetries, ADD-S only for continuous ones; it pins
    the rotation down where ADD-S lets near-symmetric shapes settle on a wrong one). ``init``: a pose
    checkpoint (or a run holding ``pose/``) to start from (fine-tuning), as for segmentation."""

    model: PoseNetConfig = field(default_factory=PoseNetConfig)
    data: DataConfig = field(default_factory=DataConfig)
    obj_ids: list[int] = field(default_factory=list)
    w: float = 0.015
    decay_margin: float = 0.016
    lr_decay: float = 0.3
    w_decay: float = 0.3
    refine_margin: float = 0.013
    eval_samples: int = 200
    sym_loss: str = "adds"
    init: str = ""


@dataclass
class RefineTrainConfig(StageConfig):
    """Refiner training on top of the frozen pose net in ``RUN/pose`` (its objects and embedding
    width are copied into ``model``). lr defaults to DenseFusion's decayed lr (1e-4 x 0.3)."""

    model: RefinerConfig = field(default_factory=RefinerConfig)
    data: DataConfig = field(default_factory=DataConfig)
    steps: int = 10000
    lr: float = 3e-5
    iterations: int = 2
    eval_samples: int = 200


@dataclass
class ClsTrainConfig(StageConfig):
    """Instance classifier training (``perception.classifier``). ``obj_ids`` empty = every object of
    models_info. ``use_seg``: also learn on the segments that the run's ``seg/`` net predicts on the
    training images (when the run has one), labelled by the ground truth. ``background``: also learn a
    class 0, "not a block", from those segments that lie mostly on background (needs ``use_seg`` and the
    run's ``seg/``); the estimator drops the segments it wins. The learning rate rises
    linearly over the first ``warmup`` of the steps, then follows a cosine to 0."""

    model: ClassifierConfig = field(default_factory=ClassifierConfig)
    data: DataConfig = field(default_factory=DataConfig)
    obj_ids: list[int] = field(default_factory=list)
    steps: int = 3000
    batch_size: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup: float = 0.1
    use_seg: bool = True
    background: bool = False


# ---------------------------------------------------------------------------- shared machinery

def batch_keys(n: int, step: int, batch_size: int, seed: int) -> list[tuple[int, int]]:
    """(dataset index, augmentation key) of each sample of batch ``step``: epochs are seeded
    permutations of the n samples, the key is the global sample counter."""
    out = []
    perms: dict[int, np.ndarray] = {}
    for g in range(step * batch_size, (step + 1) * batch_size):
        e, k = divmod(g, n)
        if e not in perms:
            perms[e] = np.random.default_rng([seed, e]).permutation(n)
        out.append((int(perms[e][k]), g))
    return out


class MetricsLog:
    """Append-only CSV of training metrics; rows after the resumed step are dropped on resume."""

    def __init__(self, path: Path, columns: list[str], resume_step: int | None):
        self.path, self.columns = path, columns
        rows: list[dict[str, str]] = []
        if resume_step is not None and path.exists():
            with open(path, newline="") as f:
                for r in csv.DictReader(f):
                    try:
                        if int(r["step"]) <= resume_step and None not in r.values():
                            rows.append(r)
                    except (KeyError, TypeError, ValueError):
                        continue
        buf = [",".join(columns)] + [",".join(r.get(c, "") or "" for c in columns) for r in rows]
        pio.write_bytes(path, ("\n".join(buf) + "\n").encode())

    def write(self, **values: Any) -> None:
        def fmt(v: Any) -> str:
            return f"{v:.6g}" if isinstance(v, float) else ("" if v is None else str(v))

        with open(self.path, "a") as f:
            f.write(",".join(fmt(values.get(c)) for c in self.columns) + "\n")
            f.flush()


def _progress(enabled: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from posegrasp.progress import progress

    return progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("loss {task.fields[loss]}"), TextColumn("{task.fields[extra]}"),
                    TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), enabled=enabled)


@dataclass
class _Run:
    """Where a stage writes, and whether it resumes."""

    out: Path
    stage: str
    resume: bool

    @property
    def ckpt(self) -> Path:
        return self.out / self.stage

    @property
    def metrics(self) -> Path:
        return self.out / f"{self.stage}_metrics.csv"

    def prepare(self) -> dict[str, Any] | None:
        """The checkpoint's config+state when resuming, None for a fresh run; UserError on misuse."""
        have = ckpt_mod.exists(self.ckpt)
        if have and not self.resume:
            raise UserError(f"{self.ckpt} already holds a checkpoint: pass --resume to continue it or choose "
                            f"another --out")
        if not have:
            return None
        return {"config": ckpt_mod.read_config(self.ckpt), "state": ckpt_mod.read_state(self.ckpt)}


def _set_lr(opt: torch.optim.Optimizer, lr: float) -> None:
    for g in opt.param_groups:
        g["lr"] = lr


def _loop(run: _Run, total: int, start: int, step_fn: Callable[[int], dict[str, float]],
          after_step: Callable[[int, dict[str, float]], dict[str, Any]],
          save: Callable[[int], None], cfg: Any, log: MetricsLog, progress: bool, state: dict[str, Any]
          ) -> dict[str, float]:
    """Run steps start..total-1, log every ``cfg.log_every`` (and after evaluations: keys of
    ``after_step``'s dict starting with ``val_``), checkpoint every ``cfg.checkpoint_every``, at the
    end and on Ctrl-C."""
    acc: dict[str, list[float]] = {}
    last: dict[str, float] = {}
    t0 = time.perf_counter() - float(state.get("elapsed_s", 0.0))
    step = start

    def checkpoint(step: int) -> None:
        state["elapsed_s"] = round(time.perf_counter() - t0, 3)
        save(step)

    with _progress(progress) as bar:
        task = bar.add_task(run.stage, total=total, completed=start, loss="-", extra="")
        try:
            while step < total:
                values = step_fn(step)
                if not all(math.isfinite(v) for v in values.values()):
                    raise UserError(f"{run.stage} training diverged at step {step}: {values}")
                step += 1
                for k, v in values.items():
                    acc.setdefault(k, []).append(v)
                extra = after_step(step, values)
                evaluated = any(k.startswith("val_") for k in extra)
                if step % cfg.log_every == 0 or step == total or evaluated:
                    last = {k: float(np.mean(v)) for k, v in acc.items()}
                    acc = {}
                    log.write(step=step, time_s=round(time.perf_counter() - t0, 3), **last, **extra)
                    shown = " ".join(f"{k} {v:.4g}" for k, v in extra.items() if isinstance(v, float))
                    bar.update(task, loss=f"{last.get('loss', float('nan')):.4f}", extra=shown)
                if step % cfg.checkpoint_every == 0 or step == total:
                    checkpoint(step)
                bar.update(task, completed=step)
        except KeyboardInterrupt:
            checkpoint(step)
            raise
    return last


def _build(stage: str, build: Callable[[Any], torch.nn.Module], model_cfg: Any) -> torch.nn.Module:
    """``build(model_cfg)``, with an unusable ``[stage.model]`` setting (its ``validate()``) as a one-line UserError."""
    try:
        return build(model_cfg)
    except ValueError as e:
        raise UserError(f"[{stage}.model] {e}") from None


def _setup(cfg: Any) -> None:
    torch.set_num_threads(max(1, int(cfg.threads)))
    torch.manual_seed(cfg.seed)


def _split_exists(root: Path, split: str) -> bool:
    return bool(split) and bop.split_dir(root, split).is_dir()


def train_split(root: Path, split: str) -> str:
    """The training split: ``split`` if given, else ``train_pbr`` (BOP's synthetic training data)
    when present, else ``train``."""
    if split:
        return split
    return "train_pbr" if _split_exists(root, "train_pbr") else "train"


def _resumed_cfg(cls: type, prior: dict[str, Any] | None, cfg: Any, overrides: dict[str, Any]) -> Any:
    """Training config: the checkpoint's when resuming (CLI overrides like steps still apply)."""
    from posegrasp.config import from_dict

    if prior is not None and prior["config"].get("train"):
        cfg = from_dict(cls, prior["config"]["train"], where="resumed config.json")
    return dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})


def _objects(data: Path, wanted: list[int]) -> tuple[dict[int, bop.ObjectInfo], list[int]]:
    """The dataset's model infos and the objects to train for (``wanted``, or all when empty)."""
    infos = bop.load_models_info(data)
    obj_ids = list(wanted) or sorted(infos)
    unknown = [o for o in obj_ids if o not in infos]
    if unknown:
        raise UserError(f"obj_ids {unknown} are not in {bop.models_info_path(data)}")
    return infos, obj_ids


def _restore(run: _Run, prior: dict[str, Any], model: torch.nn.Module, opt: torch.optim.Optimizer
             ) -> dict[str, Any]:
    """Load the checkpoint's weights and optimizer state for a resumed run; its training state."""
    tensors, _ = ckpt_mod._read_safetensors(run.ckpt / "model.safetensors")
    ckpt_mod.load_state(model, tensors, run.ckpt / "model.safetensors")
    ckpt_mod.load_optimizer(run.ckpt, opt)
    return prior["state"]


def _init_from(model: torch.nn.Module, model_cfg: Any, src: Path, stage: str) -> None:
    """Load the weights of the ``stage`` checkpoint at ``src`` (or ``src/stage``) into ``model``. A seg net may have been
    trained at another input size (it is fully convolutional: fine-tuning adapts it to the new one)."""
    ckpt = src / stage if (src / stage).is_dir() else src
    if not ckpt_mod.exists(ckpt):
        raise UserError(f"init weights {src} hold no {stage} checkpoint: name a run or its {stage}/ folder")
    src_model, src_cfg, _ = ckpt_mod.load_model(ckpt, stage)
    if stage == "seg":
        src_cfg = dataclasses.replace(src_cfg, input_size=model_cfg.input_size)
    if src_cfg != model_cfg:
        raise UserError(f"init weights {ckpt} were trained with another {stage} model config than this run's: "
                        f"use the same [{stage}.model] settings and dataset objects")
    model.load_state_dict(src_model.state_dict())


# ---------------------------------------------------------------------------- segmentation

def train_seg(data: str | Path, out: str | Path, cfg: SegTrainConfig | None = None, steps: int | None = None,
              seed: int | None = None, resume: bool = False, progress: bool = True) -> dict[str, float]:
    """Train the segmentation net on ``data`` (BOP root); checkpoints in ``out/seg``."""
    data, run = Path(data), _Run(Path(out), "seg", resume)
    prior = run.prepare()
    cfg = _resumed_cfg(SegTrainConfig, prior, cfg or SegTrainConfig(), {"steps": steps, "seed": seed})
    _setup(cfg)
    infos = bop.load_models_info(data)
    model_cfg = dataclasses.replace(cfg.model, num_classes=max(infos) + 1)
    cfg = dataclasses.replace(cfg, model=model_cfg)
    model = _build("seg", build_seg_net, model_cfg)
    if cfg.optimizer not in ("sgd", "adam"):
        raise UserError(f"seg optimizer {cfg.optimizer!r} is not 'sgd' or 'adam'")
    opt = (torch.optim.SGD(model.parameters(), lr=cfg.lr, momentum=cfg.momentum, weight_decay=cfg.weight_decay)
           if cfg.optimizer == "sgd" else torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay))
    state: dict[str, Any] = {"step": 0, "lr": cfg.lr}
    if prior is not None:
        state = _restore(run, prior, model, opt)
    elif cfg.init:
        _init_from(model, model_cfg, Path(cfg.init), "seg")
    ds = SegDataset(data, train_split(data, cfg.train_split), model_cfg.input_size, model_cfg.num_classes, cfg.data,
                    augment=True, seed=cfg.seed)
    val = (SegDataset(data, cfg.val_split, model_cfg.input_size, model_cfg.num_classes, cfg.data)
           if _split_exists(data, cfg.val_split) else None)
    log = MetricsLog(run.metrics, ["step", "time_s", "loss", "pixel_acc", "lr", "val_mPA", "val_mIoU"],
                     state["step"] if prior else None)

    def step_fn(step: int) -> dict[str, float]:
        model.train()
        batch = collate([ds.get(i, key) for i, key in batch_keys(len(ds), step, cfg.batch_size, cfg.seed)])
        logits = model(batch["image"])
        loss = seg_loss(logits, batch["label"], cfg.background_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        acc = (logits.argmax(1) == batch["label"]).float().mean()
        return {"loss": float(loss.detach()), "pixel_acc": float(acc)}

    def after_step(step: int, values: dict[str, float]) -> dict[str, Any]:
        lr = cfg.lr * cfg.lr_decay ** (step // cfg.lr_decay_every)
        _set_lr(opt, lr)
        state.update(step=step, lr=lr)
        if val is not None and cfg.eval_every and step % cfg.eval_every == 0:
            s = evaluate_seg(model, val, cfg.eval_images)
            state.update(val_mIoU=s["mIoU"])
            return {"lr": lr, "val_mPA": s["mPA"], "val_mIoU": s["mIoU"]}
        return {"lr": lr}

    def save(step: int) -> None:
        state["step"] = step
        ckpt_mod.save(run.ckpt, "seg", model, model_cfg, cfg, state, opt)

    last = _loop(run, cfg.steps, int(state["step"]), step_fn, after_step, save, cfg, log, progress, state)
    return {**last, "step": state["step"]}


@torch.no_grad()
def evaluate_seg(model: torch.nn.Module, ds: SegDataset, max_images: int = 0) -> dict[str, Any]:
    """mPA / mIoU (%) of the net on (up to ``max_images`` of) a dataset at the net's input size."""
    model.eval()
    n = len(ds) if not max_images else min(max_images, len(ds))
    conf = np.zeros((ds.num_classes, ds.num_classes), dtype=np.int64)
    for i in range(n):
        s = ds.get(i)
        pred = model(s["image"][None]).argmax(1)[0]
        conf += confusion_matrix(pred.numpy(), s["label"].numpy(), ds.num_classes)
    return segmentation_scores(conf)


# ---------------------------------------------------------------------------- pose

def _pose_datasets(data: Path, cfg: Any, obj_ids: list[int], num_points: int, crop_size: int
                   ) -> tuple[PoseDataset, PoseDataset, list[int]]:
    models = ObjectModels(data, cfg.data.model_pool)
    split = train_split(data, cfg.train_split)
    train = PoseDataset(data, split, obj_ids, num_points, crop_size, cfg.data, augment=True,
                        seed=cfg.seed, models=models)
    if _split_exists(data, cfg.val_split):
        val = PoseDataset(data, cfg.val_split, obj_ids, num_points, crop_size, cfg.data, models=models)
    else:  # no validation split: a fixed subset of the training instances, without augmentation
        val = PoseDataset(data, split, obj_ids, num_points, crop_size, cfg.data, models=models)
    n = min(cfg.eval_samples, len(val))
    idx = sorted({int(i) for i in np.linspace(0, len(val) - 1, n)})
    return train, val, idx


def _to_batch(ds: PoseDataset, keys: list[tuple[int, int | None]]) -> dict[str, torch.Tensor]:
    return collate([ds.get(i, k) for i, k in keys])


def _pose_forward(model, b: dict[str, torch.Tensor], w: float, sym_loss: str = "adds"):
    q, t, c, emb = model(b["image"], b["points"], b["choose"], b["obj"])
    sym = {"sym_targets": b["sym_targets"], "continuous": b["continuous"]} if sym_loss == "min_sym" else {}
    return pose_loss(q, t, c, b["points"], b["model_points"], b["target"], b["symmetric"], w, **sym), emb


@torch.no_grad()
def evaluate_pose(model, ds: PoseDataset, indices: list[int], batch_size: int = 8, refiner=None,
                  iterations: int = 0) -> float:
    """Mean distance (m, ADD or ADD-S per object) of the most confident proposal, optionally after
    ``iterations`` refinement steps, over dataset samples ``indices`` (no augmentation)."""
    model.eval()
    if refiner is not None:
        refiner.eval()
    dis = []
    for s in range(0, len(indices), batch_size):
        b = _to_batch(ds, [(i, None) for i in indices[s:s + batch_size]])
        out, emb = _pose_forward(model, b, 0.015)
        d = out.dis
        if refiner is not None and iterations > 0:
            d = _refine_iterations(refiner, b, out, emb, iterations, train=False)[-1]
        dis.append(d)
    return float(torch.cat(dis).mean())


def _refine_iterations(refiner, b: dict[str, torch.Tensor], out, emb: torch.Tensor, iterations: int,
                       train: bool, opt: torch.optim.Optimizer | None = None) -> list[torch.Tensor]:
    """DenseFusion's refinement training / evaluation: per iteration, refine in the current frame,
    (backpropagate), and move points and target into the refined frame. Returns dis per iteration."""
    points, target = out.new_points, out.new_target
    dis = []
    for _ in range(iterations):
        dq, dt = refiner(points, emb, b["obj"])
        r = refine_loss(dq, dt, points, b["model_points"], target, b["symmetric"])
        if train:
            r.loss.backward()
        dis.append(r.dis)
        points, target = r.new_points, r.new_target
    return dis


def train_pose(data: str | Path, out: str | Path, cfg: PoseTrainConfig | None = None, steps: int | None = None,
               seed: int | None = None, resume: bool = False, progress: bool = True) -> dict[str, float]:
    """Train the pose net on ``data`` (BOP root); checkpoints in ``out/pose``."""
    data, run = Path(data), _Run(Path(out), "pose", resume)
    prior = run.prepare()
    cfg = _resumed_cfg(PoseTrainConfig, prior, cfg or PoseTrainConfig(), {"steps": steps, "seed": seed})
    _setup(cfg)
    infos, obj_ids = _objects(data, cfg.obj_ids)
    model_cfg = dataclasses.replace(cfg.model, obj_ids=obj_ids, symmetric=[infos[o].symmetric for o in obj_ids])
    cfg = dataclasses.replace(cfg, model=model_cfg)
    model = _build("pose", build_pose_net, model_cfg)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    state: dict[str, Any] = {"step": 0, "lr": cfg.lr, "w": cfg.w, "decayed": False, "refine_ready": False,
                             "best_val_dis": None}
    if cfg.sym_loss not in ("adds", "min_sym"):
        raise UserError(f"pose sym_loss {cfg.sym_loss!r} is not 'adds' or 'min_sym'")
    if prior is not None:
        state = _restore(run, prior, model, opt)
    elif cfg.init:
        _init_from(model, model_cfg, Path(cfg.init), "pose")
    train_ds, val_ds, val_idx = _pose_datasets(data, cfg, obj_ids, model_cfg.num_points, model_cfg.crop_size)
    log = MetricsLog(run.metrics, ["step", "time_s", "loss", "dis", "lr", "w", "val_dis"],
                     state["step"] if prior else None)

    def step_fn(step: int) -> dict[str, float]:
        model.train()
        b = _to_batch(train_ds, batch_keys(len(train_ds), step, cfg.batch_size, cfg.seed))
        out, _ = _pose_forward(model, b, state["w"], cfg.sym_loss)
        opt.zero_grad(set_to_none=True)
        out.loss.backward()
        opt.step()
        return {"loss": float(out.loss.detach()), "dis": float(out.dis.mean())}

    def after_step(step: int, values: dict[str, float]) -> dict[str, Any]:
        state["step"] = step
        if not (cfg.eval_every and step % cfg.eval_every == 0):
            return {"lr": state["lr"], "w": state["w"]}
        d = evaluate_pose(model, val_ds, val_idx, cfg.batch_size)
        if state["best_val_dis"] is None or d < state["best_val_dis"]:
            state["best_val_dis"] = d
        if d < cfg.decay_margin and not state["decayed"]:
            state.update(decayed=True, lr=state["lr"] * cfg.lr_decay, w=state["w"] * cfg.w_decay)
            _set_lr(opt, state["lr"])
        if d < cfg.refine_margin:
            state["refine_ready"] = True
        return {"lr": state["lr"], "w": state["w"], "val_dis": d}

    def save(step: int) -> None:
        state["step"] = step
        ckpt_mod.save(run.ckpt, "pose", model, model_cfg, cfg, state, opt)

    last = _loop(run, cfg.steps, int(state["step"]), step_fn, after_step, save, cfg, log, progress, state)
    return {**last, "step": state["step"], "best_val_dis": state["best_val_dis"]}


# ---------------------------------------------------------------------------- refiner

def train_refine(data: str | Path, out: str | Path, cfg: RefineTrainConfig | None = None, steps: int | None = None,
                 seed: int | None = None, resume: bool = False, progress: bool = True) -> dict[str, float]:
    """Train the refiner on ``data`` with the frozen pose net of ``out/pose``; checkpoints in
    ``out/refine``."""
    data, run = Path(data), _Run(Path(out), "refine", resume)
    if not ckpt_mod.exists(run.out / "pose"):
        raise UserError(f"{run.out / 'pose'} holds no pose net: run 'train pose' with --out {run.out} first")
    prior = run.prepare()
    cfg = _resumed_cfg(RefineTrainConfig, prior, cfg or RefineTrainConfig(), {"steps": steps, "seed": seed})
    _setup(cfg)
    pose_net, pose_cfg, _ = ckpt_mod.load_model(run.out / "pose", "pose")
    for p in pose_net.parameters():
        p.requires_grad_(False)
    model_cfg = dataclasses.replace(cfg.model, obj_ids=list(pose_cfg.obj_ids), symmetric=list(pose_cfg.symmetric),
                                    emb_dim=pose_cfg.emb_dim)
    cfg = dataclasses.replace(cfg, model=model_cfg)
    model = _build("refine", build_refiner, model_cfg)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    state: dict[str, Any] = {"step": 0, "lr": cfg.lr, "best_val_dis": None}
    if prior is not None:
        state = _restore(run, prior, model, opt)
    train_ds, val_ds, val_idx = _pose_datasets(data, cfg, list(pose_cfg.obj_ids), pose_cfg.num_points,
                                               pose_cfg.crop_size)
    log = MetricsLog(run.metrics, ["step", "time_s", "loss", "dis_pose", "dis", "lr", "val_dis"],
                     state["step"] if prior else None)

    def step_fn(step: int) -> dict[str, float]:
        model.train()
        b = _to_batch(train_ds, batch_keys(len(train_ds), step, cfg.batch_size, cfg.seed))
        with torch.no_grad():
            out, emb = _pose_forward(pose_net, b, 0.015)
        opt.zero_grad(set_to_none=True)
        dis = _refine_iterations(model, b, out, emb, cfg.iterations, train=True)
        opt.step()
        return {"loss": float(sum(float(d.mean()) for d in dis)), "dis_pose": float(out.dis.mean()),
                "dis": float(dis[-1].mean())}

    def after_step(step: int, values: dict[str, float]) -> dict[str, Any]:
        state["step"] = step
        if not (cfg.eval_every and step % cfg.eval_every == 0):
            return {"lr": state["lr"]}
        d = evaluate_pose(pose_net, val_ds, val_idx, cfg.batch_size, refiner=model, iterations=cfg.iterations)
        if state["best_val_dis"] is None or d < state["best_val_dis"]:
            state["best_val_dis"] = d
        return {"lr": state["lr"], "val_dis": d}

    def save(step: int) -> None:
        state["step"] = step
        ckpt_mod.save(run.ckpt, "refine", model, model_cfg, cfg, state, opt)

    last = _loop(run, cfg.steps, int(state["step"]), step_fn, after_step, save, cfg, log, progress, state)
    return {**last, "step": state["step"], "best_val_dis": state["best_val_dis"]}


# ---------------------------------------------------------------------------- instance classifier

def cls_lr(cfg: ClsTrainConfig, step: int) -> float:
    """Learning rate at ``step``: linear warm-up over ``warmup x steps``, then cosine to 0."""
    w = max(1, int(cfg.warmup * cfg.steps))
    if step < w:
        return cfg.lr * (step + 1) / w
    return 0.5 * cfg.lr * (1.0 + math.cos(math.pi * min(1.0, (step - w) / max(1, cfg.steps - w))))


def train_cls(data: str | Path, out: str | Path, cfg: ClsTrainConfig | None = None, steps: int | None = None,
              seed: int | None = None, resume: bool = False, progress: bool = True) -> dict[str, float]:
    """Train the instance classifier on ``data`` (with the segments of ``out/seg`` when present and
    ``cfg.use_seg``); checkpoints in ``out/cls``."""
    from posegrasp.perception.inference import Segmenter

    data, run = Path(data), _Run(Path(out), "cls", resume)
    prior = run.prepare()
    cfg = _resumed_cfg(ClsTrainConfig, prior, cfg or ClsTrainConfig(), {"steps": steps, "seed": seed})
    _setup(cfg)
    infos, obj_ids = _objects(data, cfg.obj_ids)
    has_seg = cfg.use_seg and ckpt_mod.exists(run.out / "seg")
    if cfg.background and not has_seg:
        raise UserError(f"[cls] background = true learns from the seg net's segments: train seg into {run.out} "
                        "first (and keep use_seg = true), or set background = false")
    obj_ids = ([0] if cfg.background else []) + obj_ids  # 0: "not a block"
    model_cfg = dataclasses.replace(cfg.model, obj_ids=obj_ids)
    cfg = dataclasses.replace(cfg, model=model_cfg)
    model = _build("cls", build_classifier, model_cfg)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    state: dict[str, Any] = {"step": 0, "lr": cfg.lr}
    if prior is not None:
        state = _restore(run, prior, model, opt)
    segmenter, seg_id = None, ""
    if has_seg:
        seg = Segmenter.load(run.out / "seg")
        seg_id = hashlib.sha256((run.out / "seg" / "model.safetensors").read_bytes()).hexdigest()

        def segmenter(rgb: np.ndarray) -> np.ndarray:
            return seg(rgb)[0]
    crop = (model_cfg.crop_size, model_cfg.crop_side, model_cfg.depth_range)

    def dataset(split: str, augment: bool) -> ClsDataset:  # crops cached in the run: a resume starts at once
        return ClsDataset(data, split, obj_ids, *crop, cfg.data, augment=augment, seed=cfg.seed,
                          segmenter=segmenter, progress=progress, height_range=model_cfg.height_range,
                          cache=run.out / "cache" / f"cls_crops_{split}.npy", segmenter_id=seg_id)

    ds = dataset(train_split(data, cfg.train_split), True)
    val = dataset(cfg.val_split, False) if _split_exists(data, cfg.val_split) else None
    log = MetricsLog(run.metrics, ["step", "time_s", "loss", "acc", "lr", "val_acc"],
                     state["step"] if prior else None)

    def step_fn(step: int) -> dict[str, float]:
        model.train()
        _set_lr(opt, cls_lr(cfg, step))
        b = collate([ds.get(i, key) for i, key in batch_keys(len(ds), step, cfg.batch_size, cfg.seed)])
        logits = model(b["image"])
        loss = torch.nn.functional.cross_entropy(logits, b["label"])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"loss": float(loss.detach()), "acc": float((logits.argmax(1) == b["label"]).float().mean())}

    def after_step(step: int, values: dict[str, float]) -> dict[str, Any]:
        state.update(step=step, lr=cls_lr(cfg, step))
        if val is not None and cfg.eval_every and step % cfg.eval_every == 0:
            state["val_acc"] = evaluate_cls(model, val)
            return {"lr": state["lr"], "val_acc": state["val_acc"]}
        return {"lr": state["lr"]}

    def save(step: int) -> None:
        state["step"] = step
        ckpt_mod.save(run.ckpt, "cls", model, model_cfg, cfg, state, opt)

    last = _loop(run, cfg.steps, int(state["step"]), step_fn, after_step, save, cfg, log, progress, state)
    return {**last, "step": state["step"], "samples": len(ds)}


@torch.no_grad()
def evaluate_cls(model: torch.nn.Module, ds: ClsDataset, batch_size: int = 256) -> float:
    """Accuracy (fraction) of the classifier on every sample of ``ds`` (no augmentation)."""
    model.eval()
    right = 0
    for s in range(0, len(ds), batch_size):
        b = collate([ds.get(i) for i in range(s, min(len(ds), s + batch_size))])
        right += int((model(b["image"]).argmax(1) == b["label"]).sum())
    return right / len(ds)


__all__ = ["SegTrainConfig", "PoseTrainConfig", "RefineTrainConfig", "ClsTrainConfig", "train_seg", "train_pose",
           "train_refine", "train_cls", "evaluate_seg", "evaluate_pose", "evaluate_cls", "batch_keys"]
