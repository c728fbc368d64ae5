"""Checkpoints of the perception nets: safetensors + JSON, never pickles, written all-or-nothing.

A checkpoint is a directory (``RUN/seg``, ``RUN/pose``, ``RUN/refiner``, ``RUN/cls``) holding

- ``model.safetensors``: the model's state dict,
- ``config.json``: ``{"format", "version", "stage", "model": {...}, "train": {...}}`` (``stage``: the stage's tag,
  ``FILE_TAGS``),
- ``state.json``: training progress (step, learning rate, loss weight, flags, timings),
- ``optimizer.safetensors``: optimizer tensors and the torch RNG state, with the optimizer's
  hyper-parameters as JSON metadata (present only while training).

Saving writes every file (atomically) into a sibling temporary directory, then swaps it in with two
renames; a kill at any moment leaves either the old or the new checkpoint, which ``resolve`` finds. A run folder
holding the refiner under its old folder name, ``RUN/refine``, is read as it is (``stage_dir``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys
from pathlib import Path
from typing import Any, Callable

import torch
from safetensors import SafetensorError
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save
from torch import nn

from posegrasp import inputs
from posegrasp import io as pio
from posegrasp.config import from_dict
from posegrasp.errors import UserError, WeightsError
from posegrasp.perception import int8
from posegrasp.perception.classifier import ClassifierConfig, build_classifier
from posegrasp.perception.pose_net import PoseNetConfig, build_pose_net
from posegrasp.perception.refiner import RefinerConfig, build_refiner
from posegrasp.perception.seg_net import SegNetConfig, build_seg_net

FORMAT = "posegrasp-perception"
VERSION = 1
STAGES: dict[str, tuple[type, Callable[[Any], nn.Module]]] = {
    "seg": (SegNetConfig, build_seg_net),
    "pose": (PoseNetConfig, build_pose_net),
    "refiner": (RefinerConfig, build_refiner),
    "cls": (ClassifierConfig, build_classifier),
}
#: The stage tag a checkpoint's files carry where it is not the stage's name (the format's first version: the
#: refiner's files say "refine"; same bytes from the same training).
FILE_TAGS = {"refiner": "refine"}
#: A stage's checkpoint folder under its old name, still read (``stage_dir``).
OLD_FOLDERS = {"refiner": "refine"}
_noticed: set[Path] = set()  # the old folders this process has named in a notice


def stage_dir(run: Path, stage: str) -> Path:
    """The folder of the run ``run``'s ``stage`` checkpoint: ``run/<stage>``, or its old name (``OLD_FOLDERS``)
    when only that holds one, with a notice on stderr naming the new name (once per folder and process)."""
    new, old = Path(run) / stage, Path(run) / OLD_FOLDERS.get(stage, stage)
    if old == new or _present(new) or not _present(old):
        return new
    if old not in _noticed:
        _noticed.add(old)
        print(f"posegrasp: note: {old} is read as the {stage} checkpoint: its folder is now named {stage}/",
              file=sys.stderr)
    return old


def _present(ckpt: Path) -> bool:
    """Whether a checkpoint folder, or the one a killed save left (``resolve``), is there."""
    return ckpt.exists() or ckpt.with_name(f".{ckpt.name}.old").exists()


def stage_of(tag: Any) -> Any:
    """The stage whose checkpoints carry the tag ``tag`` (``FILE_TAGS``); ``tag`` itself otherwise."""
    return next((s for s, t in FILE_TAGS.items() if t == tag), tag)


def _one_line(msg: str, limit: int = 300) -> str:
    msg = " ".join(str(msg).split())
    return msg if len(msg) <= limit else msg[: limit - 3] + "..."


def resolve(ckpt: Path) -> Path:
    """The checkpoint directory, recovering the previous one if a save was killed mid-swap."""
    old = ckpt.with_name(f".{ckpt.name}.old")
    if not ckpt.exists() and old.exists():
        os.replace(old, ckpt)
    return ckpt


def exists(ckpt: Path) -> bool:
    """Whether a complete checkpoint is at ``ckpt``."""
    ckpt = resolve(Path(ckpt))
    return (ckpt / "state.json").exists() and (ckpt / "model.safetensors").exists()


def save(ckpt: Path, stage: str, model: nn.Module, model_cfg: Any, train_cfg: Any, state: dict[str, Any],
         optimizer: torch.optim.Optimizer | None = None) -> Path:
    """Write a checkpoint all-or-nothing (see module docstring)."""
    ckpt = Path(ckpt)
    tmp = ckpt.with_name(f".{ckpt.name}.tmp")
    old = ckpt.with_name(f".{ckpt.name}.old")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    step = str(int(state.get("step", 0)))
    sd = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
    tag = FILE_TAGS.get(stage, stage)
    pio.write_bytes(tmp / "model.safetensors", safetensors_bytes(sd, {"format": FORMAT, "stage": tag, "step": step}))
    if optimizer is not None:
        pio.write_bytes(tmp / "optimizer.safetensors", _optimizer_bytes(optimizer, step))
    pio.write_json(tmp / "config.json", {"format": FORMAT, "version": VERSION, "stage": tag,
                                         "model": dataclasses.asdict(model_cfg),
                                         "train": dataclasses.asdict(train_cfg) if train_cfg is not None else None})
    pio.write_json(tmp / "state.json", state)
    resolve(ckpt)
    shutil.rmtree(old, ignore_errors=True)
    if ckpt.exists():
        os.replace(ckpt, old)
    os.replace(tmp, ckpt)
    shutil.rmtree(old, ignore_errors=True)
    return ckpt


def _optimizer_bytes(opt: torch.optim.Optimizer, step: str) -> bytes:
    sd = opt.state_dict()
    tensors: dict[str, torch.Tensor] = {"rng.torch": torch.get_rng_state()}
    scalars: dict[str, dict[str, Any]] = {}
    for pid, st in sd["state"].items():
        for k, v in st.items():
            if torch.is_tensor(v):
                tensors[f"state.{pid}.{k}"] = v.detach().contiguous().cpu()
            elif v is not None:
                scalars.setdefault(str(pid), {})[k] = v
    meta = {"format": FORMAT, "step": step, "param_groups": json.dumps(sd["param_groups"]),
            "scalars": json.dumps(scalars)}
    return safetensors_bytes(tensors, meta)


def safetensors_bytes(tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> bytes:
    """The safetensors file of ``tensors`` and ``metadata``, the same bytes for the same content: the header's
    metadata keys sorted (safetensors writes them in a per-process hash order; the tensors it already orders by
    dtype and name)."""
    data = st_save(tensors, metadata=metadata)
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8:8 + n])
    header["__metadata__"] = dict(sorted(header.get("__metadata__", {}).items()))
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # the tensor data stays 8-byte aligned
    return len(text).to_bytes(8, "little") + text + data[8 + n:]


def _read_safetensors(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    if not os.path.lexists(path):
        raise WeightsError(f"weights file {path} does not exist")
    data = inputs.read_bytes(path, "weights", WeightsError)
    try:
        tensors = st_load(data)
        n = int.from_bytes(data[:8], "little")
        meta = json.loads(data[8:8 + n]).get("__metadata__", {}) or {}
    except (SafetensorError, ValueError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise WeightsError(_one_line(f"weights file {path} is corrupt or not safetensors: {e}")) from None
    for name, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            bad = int((~torch.isfinite(t)).sum())
            raise WeightsError(f"weights file {path}: tensor {name!r} has {bad} of {t.numel()} values NaN or "
                               "infinite; the weights are unusable: retrain or use another checkpoint")
    return tensors, meta


def read_config(ckpt: Path) -> dict[str, Any]:
    """``config.json`` of a checkpoint, checked for format and stage (``stage``: the stage's name, not its file tag)."""
    p = resolve(Path(ckpt)) / "config.json"
    cfg = _read_json(p, f"{p} does not exist: {ckpt} is not a trained checkpoint")
    if not isinstance(cfg, dict) or cfg.get("format") != FORMAT or not isinstance(cfg.get("stage"), str) \
            or stage_of(cfg["stage"]) not in STAGES:
        raise WeightsError(f"{p} is not a {FORMAT} config")
    cfg = {**cfg, "stage": stage_of(cfg["stage"])}
    if cfg.get("version") != VERSION or isinstance(cfg.get("version"), bool):
        raise WeightsError(f"{p}: version = {json.dumps(cfg.get('version'))[:40]}; expected {VERSION}")
    for key, optional in (("model", False), ("train", True)):  # weights made by no training (perturb): train null
        v = cfg.get(key, {})
        if not isinstance(v, dict) and not (optional and v is None):
            raise WeightsError(f"{p}: {key} = {json.dumps(v)[:40]}; expected a JSON object{' or null' * optional}")
    return cfg


def _read_json(p: Path, missing: str) -> Any:
    """The JSON of a checkpoint file ``p`` (UTF-8, no NaN or Infinity); a WeightsError (``missing`` if absent)."""
    from posegrasp.bop.schema import read_json
    from posegrasp.errors import DatasetError

    if not os.path.lexists(p):
        raise WeightsError(missing)
    try:
        return read_json(p)
    except DatasetError as e:
        raise WeightsError(f"{e}; the checkpoint is corrupt") from None


def read_state(ckpt: Path) -> dict[str, Any]:
    """``state.json`` of a checkpoint."""
    return _read_json(resolve(Path(ckpt)) / "state.json", f"{resolve(Path(ckpt)) / 'state.json'} does not exist")


def load_model(ckpt: Path, stage: str | None = None) -> tuple[nn.Module, Any, dict[str, Any]]:
    """Build the model described by ``config.json`` and load ``model.safetensors`` into it.

    Returns (model in eval mode, model config dataclass, the whole config dict). Missing, corrupt
    or mismatched files raise WeightsError with a one-line message.
    """
    ckpt = resolve(Path(ckpt))
    cfg = read_config(ckpt)
    if stage is not None and cfg["stage"] != stage:
        raise WeightsError(f"{ckpt} holds a {cfg['stage']} model, expected {stage}")
    cls, builder = STAGES[cfg["stage"]]
    where = ckpt / "config.json"
    try:
        model_cfg = from_dict(cls, cfg["model"], where=str(where))  # an unknown key or bad type: its ConfigError
    except (TypeError, KeyError) as e:
        raise WeightsError(_one_line(f"{where} describes an invalid model: {e}")) from None
    try:
        model = builder(model_cfg)
    except (ValueError, TypeError, KeyError) as e:
        raise WeightsError(_one_line(f"{where} describes an invalid model: {e}")) from None
    load_weights(ckpt, model)
    return model.eval(), model_cfg, cfg


def load_weights(ckpt: Path, model: nn.Module) -> None:
    """Load the checkpoint's ``model.safetensors`` into ``model`` (one-line WeightsError when missing, corrupt or not
    matching)."""
    path = resolve(Path(ckpt)) / "model.safetensors"
    load_state(model, _read_safetensors(path)[0], path)


def load_state(model: nn.Module, tensors: dict[str, torch.Tensor], where: Path) -> None:
    """``load_state_dict`` with a one-line WeightsError on any mismatch of names or shapes."""
    own = model.state_dict()
    missing = sorted(set(own) - set(tensors))
    unexpected = sorted(set(tensors) - set(own))
    shapes = [k for k in own if k in tensors and tuple(own[k].shape) != tuple(tensors[k].shape)]
    if missing or unexpected or shapes:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing (e.g. {missing[0]})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected (e.g. {unexpected[0]})")
        if shapes:
            k = shapes[0]
            parts.append(f"{len(shapes)} with wrong shape (e.g. {k}: {tuple(tensors[k].shape)} vs "
                         f"{tuple(own[k].shape)})")
        raise WeightsError(_one_line(f"weights {where} do not match the model in config.json: " + ", ".join(parts)))
    model.load_state_dict(tensors, strict=True)


def load_optimizer(ckpt: Path, optimizer: torch.optim.Optimizer) -> None:
    """Restore optimizer state and the torch RNG from ``optimizer.safetensors``."""
    path = resolve(Path(ckpt)) / "optimizer.safetensors"
    tensors, meta = _read_safetensors(path)
    try:
        groups = json.loads(meta["param_groups"])
        scalars = json.loads(meta.get("scalars", "{}"))
    except (KeyError, json.JSONDecodeError):
        raise WeightsError(f"{path} lacks the optimizer metadata") from None
    state: dict[int, dict[str, Any]] = {}
    for key, v in tensors.items():
        if key.startswith("state."):
            _, pid, name = key.split(".", 2)
            state.setdefault(int(pid), {})[name] = v
    for pid, st in scalars.items():
        state.setdefault(int(pid), {}).update(st)
    try:
        optimizer.load_state_dict({"state": state, "param_groups": groups})
    except (ValueError, KeyError, RuntimeError) as e:
        raise WeightsError(_one_line(f"{path} does not match the optimizer: {e}")) from None
    if "rng.torch" in tensors:
        torch.set_rng_state(tensors["rng.torch"])


def perturb_run(src: Path, dst: Path, rel_sigma: float, stages: tuple[str, ...] = ("pose",), seed: int = 0) -> Path:
    """A deliberately degraded copy of the run ``src`` in ``dst``: every learned parameter tensor W of the
    given stages (not scalars such as the attention gammas, not batch-norm statistics) gets Gaussian
    noise of standard deviation ``rel_sigma * std(W)`` (seeded); other stages are copied as they are.
    For sensitivity studies: how much worse does grasping get with a worse model? ``dst`` appears complete or not
    at all."""
    if rel_sigma < 0:
        raise UserError(f"rel_sigma (--rel-sigma) must be >= 0, got {rel_sigma}")
    src, dst = Path(src), Path(dst)
    tmp = dst.with_name(f".{dst.name}.tmp")  # built beside dst, renamed to it when complete
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        _perturb_into(src, tmp, rel_sigma, stages, seed)
        if dst.is_dir() and not any(dst.iterdir()):
            dst.rmdir()
        os.replace(tmp, dst)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dst


def _perturb_into(src: Path, dst: Path, rel_sigma: float, stages: tuple[str, ...], seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    for stage in STAGES:
        ckpt = resolve(stage_dir(src, stage))
        if not exists(ckpt):
            continue
        model, model_cfg, cfg = load_model(ckpt, stage)
        if stage in stages:
            with torch.no_grad():
                for _, p in sorted(model.named_parameters()):
                    if p.numel() > 1:
                        p += rel_sigma * p.std() * torch.randn(p.shape, generator=gen)
        state = {**read_state(ckpt), "perturbed": {"from": str(src), "rel_sigma": rel_sigma, "seed": seed}}
        train_cfg = cfg["train"]
        save(dst / stage, stage, model, model_cfg, None, state)
        if stage not in stages:  # the same weights: the same int8 net
            int8.copy_ranges(ckpt, dst / stage)
        if train_cfg is not None:  # keep the training settings the weights came from
            written = {**read_config(dst / stage), "stage": FILE_TAGS.get(stage, stage), "train": train_cfg}
            pio.write_json(dst / stage / "config.json", written)
