"""A run's instance classifiers as one ensemble: ``cls/`` and the further members ``cls_<name>/``, whose class
probabilities are averaged (``perception.classifier`` builds each member)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from posegrasp.errors import WeightsError
from posegrasp.perception import checkpoint as ckpt_mod
from posegrasp.perception.classifier import ClassifierConfig
from posegrasp.perception.inputs import normalize_cls_input, prepare_cls_input
from posegrasp.perception.int8 import inference_form


class ClassifierEnsemble:
    """Members (in inference form) and the crop settings they share (``cfg``: objects, crop geometry, the height
    channel's range; members without the height channel read a crop's first 6 channels)."""

    def __init__(self, models: list[torch.nn.Module], cfg: ClassifierConfig, names: list[str] | None = None):
        self.models, self.cfg = models, cfg
        self.names = names or [f"cls {i + 1}" for i in range(len(models))]  #: each member's (its folder's) name

    @staticmethod
    def members(weights: Path) -> list[Path]:
        """The checkpoint folders of the run ``weights``'s classifiers: ``cls/``, then ``cls_<name>/`` by name."""
        return [weights / "cls"] + sorted(p for p in weights.glob("cls_*") if p.is_dir())

    @classmethod
    def load(cls, weights: Path, int8: bool = True) -> "ClassifierEnsemble":
        """The run ``weights``'s classifiers (``members``), each in int8 when ``int8`` and its folder holds its
        measured ranges (``perception.int8``); WeightsError when they differ in their objects, crop settings or height
        ranges."""
        dirs = cls.members(weights)
        models, cfgs = [], []
        for d in dirs:
            model, cfg, _ = ckpt_mod.load_model(d, "cls")
            models.append(inference_form(model, d, int8))
            cfgs.append(cfg)
        key = [(list(c.obj_ids), c.crop_size, c.crop_side, c.depth_range) for c in cfgs]
        for d, k in zip(dirs[1:], key[1:]):
            if k != key[0]:
                raise WeightsError(f"classifier {d} differs from {dirs[0]} in its objects or crop settings ({k} vs "
                                   f"{key[0]}): an ensemble's members must share them")
        heights = sorted({c.height_range for c in cfgs if c.height_range > 0})
        if len(heights) > 1:
            raise WeightsError(f"the classifiers in {weights} use height ranges {heights}: an ensemble's members share "
                               "one")
        shared = dataclasses.replace(cfgs[0], height_range=heights[0] if heights else 0.0)
        return cls(models, shared, [d.name for d in dirs])

    def __call__(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, masks: list[np.ndarray],
                 plane: np.ndarray | None) -> list[tuple[int, float] | None]:
        """(obj_id, probability) of each mask's most probable class (``probabilities``)."""
        return [None if p is None else (self.cfg.obj_ids[int(p.argmax())], float(p.max()))
                for p in self.probabilities(rgb, depth, K, masks, plane)]

    @torch.no_grad()
    def probabilities(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, masks: list[np.ndarray],
                      plane: np.ndarray | None) -> list[np.ndarray | None]:
        """The members' mean class probabilities (n,) (order ``cfg.obj_ids``) of each mask (H, W) bool, all crops as
        one batch; None where the mask lacks the valid depth for a crop. plane: the supporting plane for the height
        channel (None: heights 0)."""
        cfg = self.cfg
        crops = [prepare_cls_input(rgb, depth, K, m, cfg, plane) for m in masks]
        ok = [i for i, x in enumerate(crops) if x is not None]
        out: list[np.ndarray | None] = [None] * len(masks)
        if ok:
            x = torch.from_numpy(np.stack([normalize_cls_input(crops[i]) for i in ok]))  # (S, C, size, size)
            prob = torch.stack([torch.softmax(m(x[:, :m.cfg.in_channels]), dim=1) for m in self.models])  # (M, S, n)
            for i, p in zip(ok, prob.mean(dim=0).numpy()):
                out[i] = p
        return out
