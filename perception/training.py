"""The skeleton every network's training shares (``StageTraining``): the run folder and resume, the seeded set-up,
the loop with its metrics log, progress bar and checkpoints. Each stage fills it in its own module:
``perception.train_seg``, ``perception.train_pose``, ``perception.train_refiner`` and ``perception.train_cls``.

A stage writes the ``RUN/<stage>/`` checkpoint (see ``perception.checkpoint``) and ``RUN/<stage>_metrics.csv``. Runs
are seeded and resumable: batch composition and augmentation are functions of (seed, step), and the checkpoint holds
the weights, the optimizer state, the schedule state and the torch RNG, so a killed run resumed with ``resume=True``
continues exactly where its last checkpoint was written.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
import signal
import threading
import time
from abc import ABC, abstractmethod
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterator

import numpy as np
import torch

from posegrasp import bop, inputs
from posegrasp import io as pio
from posegrasp.config import settings, within
from posegrasp.errors import ConfigError, UserError, WeightsError
from posegrasp.lock import folder_lock
from posegrasp.outputs import Record
from posegrasp.perception import checkpoint as ckpt_mod
from posegrasp.perception.runtime import flush_subnormals

#: What marks a training run's folder (``posegrasp.outputs``): a stage's checkpoint settings or metrics log.
RUN_RECORDS = (Record("*/config.json", ("format", "stage", "model")), Record("*_metrics.csv", head=b"step,"))


@settings
class StageConfig:
    """What every stage's training has: splits, steps, intervals, seed and CPU threads."""

    #: Training split; empty: `train_pbr` if the dataset has it, else `train`.
    train_split: str = ""
    #: Validation split, evaluated every `eval_every` steps when the dataset has it.
    val_split: str = "val"
    #: Training steps (batches).
    steps: int = field(default=20000, metadata=within(1, 100000000))
    #: Samples per batch.
    batch_size: int = field(default=8, metadata=within(1, 4096))
    #: Initial learning rate.
    lr: float = field(default=1e-4, metadata=within(0, 10))
    #: Steps between rows of the metrics CSV.
    log_every: int = field(default=20, metadata=within(1, 100000000))
    #: Steps between checkpoints (a killed run resumes from the last).
    checkpoint_every: int = field(default=500, metadata=within(1, 100000000))
    #: Steps between evaluations on the validation split.
    eval_every: int = field(default=1000, metadata=within(0, 100000000))
    #: Seed of the batches and augmentations.
    seed: int = field(default=0, metadata=within(0, 9223372036854775807))
    #: Torch CPU threads.
    threads: int = field(default=2, metadata=within(1, 256))


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


class _Batches(torch.utils.data.Dataset):
    """Batch ``start + i`` as item i: ``collate`` of ``get(index, key)`` over ``batch_keys``."""

    def __init__(self, get: Callable[[int, int], dict], collate: Callable[[list[dict]], dict], n: int,
                 batch_size: int, seed: int, start: int, total: int):
        self.get, self.collate, self.n, self.batch_size, self.seed = get, collate, n, batch_size, seed
        self.start, self.total = start, total

    def __len__(self) -> int:
        return max(0, self.total - self.start)

    def __getitem__(self, i: int) -> dict:
        keys = batch_keys(self.n, self.start + i, self.batch_size, self.seed)
        return self.collate([self.get(j, key) for j, key in keys])


def batch_stream(get: Callable[[int, int], dict], collate: Callable[[list[dict]], dict], n: int, batch_size: int,
                 seed: int, start: int, total: int, workers: int = 0) -> Iterator[dict]:
    """Batches ``start``..``total - 1`` in order, each a function of (seed, step) as ``batch_keys`` says, prepared by
    ``workers`` processes ahead of the training (0: in this process, when asked for). The same batches either way."""
    src = _Batches(get, collate, n, batch_size, seed, start, total)
    if workers <= 0:
        return (src[i] for i in range(len(src)))
    return iter(torch.utils.data.DataLoader(src, batch_size=None, shuffle=False, num_workers=workers,
                                            prefetch_factor=4, pin_memory=torch.cuda.is_available()))


def training_device(name: str) -> torch.device:
    """The torch device ``name`` ("cpu", "cuda", "cuda:N"); ConfigError when torch cannot use it."""
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"device {name!r} is not a torch device: use 'cpu' or 'cuda'") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {name!r}: this torch sees no CUDA GPU; set device = 'cpu'")
    if dev.type not in ("cpu", "cuda"):
        raise ConfigError(f"device {name!r}: only 'cpu' and 'cuda' are supported")
    return dev


class MetricsLog:
    """Append-only CSV of training metrics; rows after the resumed step are dropped on resume."""

    def __init__(self, path: Path, columns: list[str], resume_step: int | None):
        self.path, self.columns = path, columns
        rows: list[dict[str, str]] = []
        if resume_step is not None and os.path.lexists(path):
            raw = inputs.read_bytes(path, "csv")
            try:
                for r in csv.DictReader(io.StringIO(raw.decode("utf-8"), newline="")):
                    try:
                        if int(r["step"]) <= resume_step and None not in r.values():
                            rows.append(r)
                    except (KeyError, TypeError, ValueError):
                        continue
            except (UnicodeDecodeError, csv.Error) as e:
                raise UserError(f"{path} is not a metrics CSV ({str(e).splitlines()[0][:80]}); move it away to "
                                "resume") from None
        buf = [",".join(columns)] + [",".join(r.get(c, "") or "" for c in columns) for r in rows]
        pio.write_bytes(path, ("\n".join(buf) + "\n").encode())

    def write(self, **values: Any) -> None:
        """Append one row (floats with 6 significant digits, missing values empty)."""
        def fmt(v: Any) -> str:
            return f"{v:.6g}" if isinstance(v, float) else ("" if v is None else str(v))

        with open(self.path, "a") as f:
            f.write(",".join(fmt(values.get(c)) for c in self.columns) + "\n")
            f.flush()


@dataclass
class RunFolder:
    """Where a stage writes (``out/<stage>/``, ``out/<stage>_metrics.csv``; a run holding the stage under its old
    folder name goes on there: ``checkpoint.stage_dir``), and whether it resumes."""

    out: Path
    stage: str
    resume: bool
    ckpt: Path = field(init=False)

    def __post_init__(self) -> None:
        self.ckpt = ckpt_mod.stage_dir(self.out, self.stage)

    @property
    def metrics(self) -> Path:
        return self.out / f"{self.ckpt.name}_metrics.csv"

    def prepare(self) -> dict[str, Any] | None:
        """The checkpoint's config+state when resuming, None for a fresh run; UserError on misuse."""
        have = ckpt_mod.exists(self.ckpt)
        if have and not self.resume:
            raise UserError(f"{self.ckpt} already holds a checkpoint: pass --resume to continue it or choose "
                            f"another --out")
        if not have:
            return None
        return {"config": ckpt_mod.read_config(self.ckpt), "state": ckpt_mod.read_state(self.ckpt)}


class StageTraining(ABC):
    """One network's training on a BOP dataset, as a template: ``train`` resolves the config (the checkpoint's when
    resuming), seeds torch, calls ``build`` (the net, its config, the optimizer and a fresh ``state``), restores the
    checkpoint or loads ``cfg.init`` weights, calls ``prepare`` (the datasets), then runs ``step`` and ``after_step``
    until ``cfg.steps``, logging and checkpointing (``loop``). Subclasses set the class attributes and the hooks."""

    name: ClassVar[str]  # RUN/<name>/ and the checkpoint's stage
    config: ClassVar[type]  # the training config dataclass (a ``StageConfig``)
    columns: ClassVar[list[str]]  # of RUN/<name>_metrics.csv
    needs: ClassVar[str] = ""  # a stage whose checkpoint the run must hold first
    fine_tunes: ClassVar[bool] = False  # whether ``cfg.init`` may name weights to start from

    model: torch.nn.Module
    model_cfg: Any
    opt: torch.optim.Optimizer
    state: dict[str, Any]  # the schedule's state, saved with the checkpoint ("step" first)

    def __init__(self, data: Path, run: RunFolder, cfg: Any):
        self.data, self.run, self.cfg = data, run, cfg

    @abstractmethod
    def build(self) -> None:
        """Set ``model``, ``model_cfg``, ``cfg`` (with ``model_cfg`` in it), ``opt`` and a fresh ``state``."""

    @abstractmethod
    def prepare(self, progress: bool) -> None:
        """Load the datasets (once the weights are restored or initialised)."""

    @abstractmethod
    def step(self, step: int) -> dict[str, float]:
        """Optimise on batch ``step`` (0-based); the batch's losses and metrics."""

    @abstractmethod
    def after_step(self, step: int, values: dict[str, float]) -> dict[str, Any]:
        """Schedules and evaluation once ``step`` steps are done; the values to log (evaluations as ``val_*``)."""

    def summary(self) -> dict[str, Any]:
        """Entries of ``train``'s result after the last metrics and the step."""
        return {}

    def save(self, step: int) -> None:
        """Write the checkpoint at ``step``."""
        self.state["step"] = step
        ckpt_mod.save(self.run.ckpt, self.name, self.model, self.model_cfg, self.cfg, self.state, self.opt)

    @classmethod
    def train(cls, data: str | Path, out: str | Path, cfg: Any = None, steps: int | None = None,
              seed: int | None = None, resume: bool = False, progress: bool = True) -> dict[str, Any]:
        """Train on ``data`` (BOP root) into run ``out``; ``steps`` and ``seed`` override the config. Returns the last
        logged metrics, the step and ``summary()``."""
        data = Path(data)
        check_splits(data, cfg or cls.config(), progress)
        run = RunFolder(Path(out), cls.name, resume)
        if cls.needs and not ckpt_mod.exists(run.out / cls.needs):
            raise WeightsError(f"{run.out / cls.needs} holds no {cls.needs} net: run 'train {cls.needs}' with --out "
                               f"{run.out} first")
        with folder_lock(run.out, owns=RUN_RECORDS):  # one process writes a run folder at a time
            prior = run.prepare()
            t = cls(data, run, resumed_cfg(cls.config, prior, cfg or cls.config(), {"steps": steps, "seed": seed}))
            torch.set_num_threads(max(1, int(t.cfg.threads)))
            torch.manual_seed(t.cfg.seed)
            t.build()
            if prior is not None:
                t.state = restore(run, prior, t.model, t.opt, t.state)
            elif cls.fine_tunes and t.cfg.init:
                init_from(t.model, t.model_cfg, Path(t.cfg.init), cls.name)
            t.prepare(progress)
            log = MetricsLog(run.metrics, cls.columns, t.state["step"] if prior else None)
            last = loop(t, log, progress)
            return {**last, "step": t.state["step"], **t.summary()}


def _progress(enabled: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from posegrasp.progress import progress

    return progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("loss {task.fields[loss]}"), TextColumn("{task.fields[extra]}"),
                    TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), enabled=enabled)


def set_lr(opt: torch.optim.Optimizer, lr: float) -> None:
    """Every parameter group of ``opt`` at learning rate ``lr``."""
    for g in opt.param_groups:
        g["lr"] = lr


#: Steps between the zeroing of a training net's subnormal weights (``loop``); one takes ~7 ms on the shipped nets.
FLUSH_EVERY = 10


def loop(t: StageTraining, log: MetricsLog, progress: bool) -> dict[str, float]:
    """Run the training ``t``'s steps from its state's step to ``cfg.steps`` - 1 (``t.step``, then ``t.after_step``),
    log every ``cfg.log_every`` (and after evaluations: keys of ``after_step``'s dict starting with ``val_``),
    checkpoint (``t.save``) every ``cfg.checkpoint_every`` and at the end. Every ``FLUSH_EVERY`` steps, from step 0, the
    net's subnormal weights are zeroed first (``flush_subnormals``): the shipped bin seg net held 117k, and fine-tuning
    it ran 1.5x slower with them.

    Ctrl-C lets the current step finish, checkpoints it and raises ``KeyboardInterrupt`` (a second Ctrl-C stops at
    once, keeping the last checkpoint). A checkpoint holds the values not yet logged (``state["pending"]``), so a
    resumed run logs the rows, and ends with the files, of an uninterrupted one."""
    run, cfg, state, total = t.run, t.cfg, t.state, t.cfg.steps
    acc: dict[str, list[float]] = state.pop("pending", {})
    last: dict[str, float] = {}
    t0 = time.perf_counter() - float(state.get("elapsed_s", 0.0))
    step = start = int(state["step"])

    def checkpoint(step: int) -> None:
        state["elapsed_s"] = round(time.perf_counter() - t0, 3)
        if acc:
            state["pending"] = acc
        try:
            t.save(step)
        finally:
            state.pop("pending", None)

    with _progress(progress) as bar, stop_at_step_end() as stop:
        task = bar.add_task(run.stage, total=total, completed=start, loss="-", extra="")
        while step < total:
            if step % FLUSH_EVERY == 0:  # by step number: a resumed run flushes where an uninterrupted one does
                flush_subnormals(t.model)
            values = t.step(step)
            if not all(math.isfinite(v) for v in values.values()):
                raise UserError(f"{run.stage} training diverged at step {step}: {values}")
            step += 1
            for k, v in values.items():
                acc.setdefault(k, []).append(v)
            extra = t.after_step(step, values)
            evaluated = any(k.startswith("val_") for k in extra)
            if step % cfg.log_every == 0 or step == total or evaluated:
                last = {k: float(np.mean(v)) for k, v in acc.items()}
                acc = {}
                log.write(step=step, time_s=round(time.perf_counter() - t0, 3), **last, **extra)
                shown = " ".join(f"{k} {v:.4g}" for k, v in extra.items() if isinstance(v, float))
                bar.update(task, loss=f"{last.get('loss', float('nan')):.4f}", extra=shown)
            if step % cfg.checkpoint_every == 0 or step == total or stop.requested:
                checkpoint(step)
            bar.update(task, completed=step)
            if stop.requested and step < total:
                raise KeyboardInterrupt
    return last


class _StopRequest:
    requested = False


@contextmanager
def stop_at_step_end() -> Iterator[_StopRequest]:
    """Inside the block, a first SIGINT (Ctrl-C) only sets ``requested``, for the loop to stop at a step's end; a
    second one raises ``KeyboardInterrupt`` at once. Outside the main thread nothing is caught."""
    stop = _StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def on_sigint(signum: int, frame: Any) -> None:
        if stop.requested:
            raise KeyboardInterrupt
        stop.requested = True

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)


def build_model(stage: str, build: Callable[[Any], torch.nn.Module], model_cfg: Any) -> torch.nn.Module:
    """``build(model_cfg)``, with a model the settings cannot build as a one-line ConfigError naming
    ``[stage.model]``."""
    try:
        return build(model_cfg)
    except ValueError as e:
        raise ConfigError(f"[{stage}.model] {e}") from None


def split_exists(root: Path, split: str) -> bool:
    """Whether the BOP dataset ``root`` has the split ``split`` (False for an empty name)."""
    return bool(split) and bop.split_dir(root, split).is_dir()


def train_split(root: Path, split: str) -> str:
    """The training split: ``split`` if given, else ``train_pbr`` (BOP's synthetic training data)
    when present, else ``train``."""
    if split:
        return split
    return "train_pbr" if split_exists(root, "train_pbr") else "train"


def check_splits(data: Path, cfg: Any, progress: bool) -> None:
    """Refuse (DatasetError) a training or validation split that ``dataset check`` would flag, before anything
    is written or trained (``bop.check.require_valid``)."""
    from posegrasp.bop.check import require_valid

    for split in dict.fromkeys((train_split(data, cfg.train_split), cfg.val_split)):
        if split == cfg.val_split and not split_exists(data, split):
            continue
        require_valid(data, split, progress=progress)


def resumed_cfg(cls: type, prior: dict[str, Any] | None, cfg: Any, overrides: dict[str, Any]) -> Any:
    """Training config: the checkpoint's when resuming (CLI overrides like steps still apply)."""
    from posegrasp.config import from_dict

    if prior is not None and prior["config"].get("train"):
        cfg = from_dict(cls, prior["config"]["train"], where="resumed config.json")
    return dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})


def dataset_objects(data: Path, wanted: list[int]) -> tuple[dict[int, bop.ObjectInfo], list[int]]:
    """The dataset's model infos and the objects to train for (``wanted``, or all when empty)."""
    infos = bop.load_models_info(data)
    obj_ids = list(wanted) or sorted(infos)
    unknown = [o for o in obj_ids if o not in infos]
    if unknown:
        raise ConfigError(f"obj_ids {unknown} are not in {bop.models_info_path(data)}")
    return infos, obj_ids


def restore(run: RunFolder, prior: dict[str, Any], model: torch.nn.Module, opt: torch.optim.Optimizer,
            fresh: dict[str, Any]) -> dict[str, Any]:
    """Load the checkpoint's weights and optimizer state for a resumed run; its training state, checked against
    ``fresh`` (the state a new run starts with: same keys, values of the same kinds, finite, step >= 0)."""
    state = checked_state(prior["state"], fresh, run.ckpt / "state.json")
    ckpt_mod.load_weights(run.ckpt, model)
    ckpt_mod.load_optimizer(run.ckpt, opt)
    return state


def checked_state(state: Any, fresh: dict[str, Any], where: Path) -> dict[str, Any]:
    """``state`` (a checkpoint's ``state.json``) if it has ``fresh``'s keys with values of the same kind (a
    number where ``fresh`` has one or None, finite; a bool for a bool; ...), ``step`` an integer >= 0 and any
    ``elapsed_s`` a finite number >= 0; else a one-line WeightsError naming the key."""
    def kind(v: Any) -> str:
        return "bool" if isinstance(v, bool) else "number" if isinstance(v, (int, float)) else type(v).__name__

    def bad(key: str, want: str, v: Any) -> WeightsError:
        return WeightsError(f"{where}: {key} = {json.dumps(v)[:40]} is not {want}; the checkpoint is corrupt: train "
                            "into a new --out")

    if not isinstance(state, dict):
        raise WeightsError(f"{where}: expected a JSON object, got {type(state).__name__}; the checkpoint is corrupt")
    for key, like in {**fresh, "step": 0, "elapsed_s": 0.0}.items():
        if key not in state:
            if key == "elapsed_s":
                continue
            raise WeightsError(f"{where}: the key {key!r} is missing; the checkpoint is corrupt: train into a new --out")
        v = state[key]
        if key == "step" and (kind(v) != "number" or v != int(v) or v < 0):
            raise bad(key, "an integer >= 0", v)
        if kind(v) == "number" and not math.isfinite(v) or key == "elapsed_s" and kind(v) == "number" and v < 0:
            raise bad(key, "a finite number" + (" >= 0" if key == "elapsed_s" else ""), v)
        if like is not None and kind(v) != kind(like) and not (v is None and kind(like) == "number"):
            raise bad(key, f"a {kind(like)}", v)
        if like is None and v is not None and kind(v) != "number":
            raise bad(key, "a number or null", v)
    return state


def init_checkpoint(src: Path, stage: str) -> Path:
    """The ``stage`` checkpoint folder that ``init`` names: a run's ``src/stage``, or ``src`` itself."""
    return src / stage if (src / stage).is_dir() else src


def init_from(model: torch.nn.Module, model_cfg: Any, src: Path, stage: str) -> None:
    """Load the weights of the ``stage`` checkpoint at ``src`` (or ``src/stage``) into ``model``. A seg net may have
    been trained at another input size (it is fully convolutional: fine-tuning adapts it to the new one), and may lack
the seam head the run's net has (that head then starts from its random initialisation)."""
    ckpt = init_checkpoint(src, stage)
    if not ckpt_mod.exists(ckpt):
        raise WeightsError(f"init weights {src} hold no {stage} checkpoint: name a run or its {stage}/ folder")
    src_model, src_cfg, _ = ckpt_mod.load_model(ckpt, stage)
    state = src_model.state_dict()
    if stage == "seg":
        if src_cfg.seams and not model_cfg.seams:
            raise WeightsError(f"init weights {ckpt} have a seam head this run's seg net lacks: set [seg.model] "
                               "seams = true")
        if model_cfg.seams and not src_cfg.seams:  # a seam head added to a net without one starts fresh
            state.update({k: v for k, v in model.state_dict().items() if k.startswith("seam.")})
        src_cfg = dataclasses.replace(src_cfg, input_size=model_cfg.input_size, seams=model_cfg.seams)
    if src_cfg != model_cfg:
        raise WeightsError(f"init weights {ckpt} were trained with another {stage} model config than this run's: "
                           f"use the same [{stage}.model] settings and dataset objects")
    model.load_state_dict(state)
