"""Torch datasets over any BOP dataset (``posegrasp.bop``) for training: segmentation images, per-object
pose samples and instance classifier crops, with seeded colour and depth augmentation. Their inputs are
prepared as at run time (``perception.inputs``); the classifier's crops are cached (``perception.crop_cache``).

Every sample is a deterministic function of (dataset seed, index, augmentation key): the trainer
passes the global sample counter as the key, so a resumed run sees exactly the same batches.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.config import settings, within
from posegrasp.errors import DatasetError
from posegrasp.perception.classifier import ClassifierConfig
from posegrasp.perception.crop_cache import fingerprint, read_crop_cache, write_crop_cache
from posegrasp.perception.inputs import normalize_cls_input, normalize_rgb, prepare_cls_input, prepare_pose_input
from posegrasp.perception.plane import fit_support_plane
from posegrasp.perception.pose_net import PoseNetConfig


@settings
class DataConfig:
    """Sample selection and augmentation."""

    #: Skip instances less visible than this (BOP: 0.1).
    min_visib_fract: float = field(default=0.1, metadata=within(0, 1))
    #: Skip instances with fewer visible pixels with valid depth.
    min_points: int = field(default=50, metadata=within(0, 100000000))
    #: Model points per pose sample, redrawn each sample (DenseFusion 500; the symmetric loss costs N x M^2).
    num_model_points: int = field(default=128, metadata=within(1, 10000000))
    #: Surface points sampled once per model, from which each sample draws.
    model_pool: int = field(default=4000, metadata=within(1, 100000000))
    #: Augment the training samples as below.
    augment: bool = True
    #: Brightness, contrast and saturation factors drawn in [1 - j, 1 + j].
    color_jitter: float = field(default=0.2, metadata=within(0, 1))
    #: Hue shift drawn in [-h, h], a fraction of a full turn.
    hue_jitter: float = field(default=0.03, metadata=within(0, 0.5))
    #: Std (m) of Gaussian noise on each point's depth, along its ray.
    depth_noise: float = field(default=0.001, metadata=within(0, 1))
    #: Each pose sample's cloud and target shifted by U(-n, n) (m, per axis).
    translation_noise: float = field(default=0.01, metadata=within(0, 1))


def color_jitter(rgb: np.ndarray, rng: np.random.Generator, strength: float, hue: float) -> np.ndarray:
    """Random brightness, contrast, saturation (factors in [1 - s, 1 + s]) and hue shift (+-hue turns)."""
    x = rgb.astype(np.float32)
    b, c, s = rng.uniform(1 - strength, 1 + strength, 3)
    h = rng.uniform(-hue, hue)
    x = x * b
    x = (x - x.mean()) * c + x.mean()
    gray = x @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    x = (x - gray[..., None]) * s + gray[..., None]
    x = np.clip(x, 0, 255).astype(np.uint8)
    if hue > 0:
        hsv = cv2.cvtColor(x, cv2.COLOR_RGB2HSV)
        hsv[..., 0] = ((hsv[..., 0].astype(np.int32) + int(round(h * 180))) % 180).astype(np.uint8)
        x = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    return x


def _rng(seed: int, index: int, key: int | None) -> np.random.Generator:
    return np.random.default_rng([seed, index] if key is None else [seed, index, key])


def load_records(root: str | Path, split: str) -> list[bop.ImageRecord]:
    """All image records of a split; DatasetError when there is none."""
    recs = list(bop.iter_scene_images(root, split))
    if not recs:
        raise DatasetError(f"BOP split {Path(root) / split} has no images")
    return recs


def label_map(rec: bop.ImageRecord, shape: tuple[int, int], num_classes: int | None = None,
              parts: np.ndarray | None = None) -> np.ndarray:
    """(H, W) int64 class map from the visible masks: 0 background, obj_id on each object; from ``parts``
    (``part_map``'s, each mask read once) when given."""
    ids = np.zeros(len(rec.instances) + 1, dtype=np.int64)
    for inst in rec.instances:
        if num_classes is not None and inst.obj_id >= num_classes:
            raise DatasetError(f"object id {inst.obj_id} in {rec.scene_dir} does not fit a model with "
                               f"{num_classes} classes")
        ids[inst.gt_index + 1] = inst.obj_id
    return ids[part_map(rec, shape) if parts is None else parts]


def seam_map(parts: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of a part that touch (8-connected) a pixel of another part, from a part map (H, W)
    (0 background, k > 0 the k-th part)."""
    disc = np.ones((3, 3), dtype=np.uint8)
    ids = parts.astype(np.float32)  # exact for ids below 2^24
    above = cv2.dilate(ids, disc) > ids  # a neighbour of a higher id
    below = cv2.erode(np.where(parts > 0, ids, np.float32(np.inf)), disc) < ids  # of a lower id, not background
    return (parts > 0) & (above | below)


def part_map(rec: bop.ImageRecord, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) int64 map of the visible masks: 0 background, k + 1 on the part with ground-truth index k."""
    parts = np.zeros(shape, dtype=np.int64)
    for inst in rec.instances:
        parts[rec.load_mask(inst.gt_index)] = inst.gt_index + 1
    return parts


class SegDataset(Dataset):
    """Segmentation samples: ``{"image": (3, H, W) float32, "label": (H, W) int64}`` at input_size, and with
    ``seams`` ``"seam"`` (H, W) bool: ``seam_map`` of the visible parts at input_size."""

    def __init__(self, root: str | Path, split: str, input_size: tuple[int, int], num_classes: int,
                 cfg: DataConfig | None = None, augment: bool = False, seed: int = 0, seams: bool = False):
        self.root, self.split = Path(root), split
        self.records = load_records(root, split)
        self.input_size = tuple(input_size)
        self.num_classes = num_classes
        self.cfg = cfg or DataConfig()
        self.augment = augment and self.cfg.augment
        self.seed = seed
        self.seams = seams

    def __len__(self) -> int:
        return len(self.records)

    def get(self, index: int, key: int | None = None) -> dict[str, torch.Tensor]:
        """Sample ``index``; ``key`` seeds the augmentation (None: no augmentation)."""
        rec = self.records[index]
        rgb = rec.load_rgb()
        parts = part_map(rec, rgb.shape[:2])
        maps = [label_map(rec, rgb.shape[:2], self.num_classes, parts)] + ([parts] if self.seams else [])
        h, w = self.input_size
        if rgb.shape[:2] != (h, w):
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_LINEAR)
            maps = [cv2.resize(m.astype(np.int32), (w, h), interpolation=cv2.INTER_NEAREST).astype(np.int64)
                    for m in maps]
        if self.augment and key is not None:
            rng = _rng(self.seed, index, key)
            rgb = color_jitter(rgb, rng, self.cfg.color_jitter, self.cfg.hue_jitter)
            if rng.random() < 0.5:  # horizontal flip is label-preserving for segmentation
                rgb, maps = rgb[:, ::-1], [m[:, ::-1] for m in maps]
        out = {"image": torch.from_numpy(normalize_rgb(np.ascontiguousarray(rgb))),
               "label": torch.from_numpy(np.ascontiguousarray(maps[0]))}
        if self.seams:
            out["seam"] = torch.from_numpy(seam_map(maps[1]))
        return out

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return self.get(index)


class ObjectModels:
    """Surface points (m) and info of every model of a BOP dataset, sampled once (seeded per object)."""

    def __init__(self, root: str | Path, pool: int = 4000, seed: int = 0):
        self.root = Path(root)
        self.infos = bop.load_models_info(root)
        self.pool = pool
        self.seed = seed
        self._points: dict[int, np.ndarray] = {}

    def points(self, obj_id: int) -> np.ndarray:
        """(pool, 3) surface points of the model in its frame (m)."""
        if obj_id not in self._points:
            mesh = bop_models.load_model(self.root, obj_id)
            self._points[obj_id] = bop_models.sample_model_points(mesh, self.pool, seed=self.seed + obj_id)
        return self._points[obj_id]


def usable(inst: bop.GTInstance, cfg: DataConfig) -> bool:
    """Whether an annotated instance is visible enough to train on (``min_visib_fract``, ``min_points``);
    instances without gt_info count as usable."""
    return inst.info is None or (inst.info.visib_fract >= cfg.min_visib_fract
                                 and inst.info.px_count_visib >= cfg.min_points)


@dataclass(frozen=True)
class CropSource:
    """Where a ``ClsDataset``'s crops come from besides the annotated instances, and where they are kept:
    ``segmenter`` (RGB (H, W, 3) uint8 -> the parts it finds, (class, mask (H, W) bool) each, e.g. a trained seg net's
    ``Segmenter.parts``; None: the annotated instances only), ``segmenter_id`` naming it in the cache (e.g. a hash of
    its weights), ``cache`` (a ``.npy`` path, or None) and whether a progress bar shows their computation."""

    segmenter: Callable[[np.ndarray], list[tuple[int, np.ndarray]]] | None = None
    segmenter_id: str = ""
    cache: str | Path | None = None
    progress: bool = False


class ClsDataset(Dataset):
    """Instance classifier samples: ``{"image": (C, S, S) float32, "label": index into model.obj_ids}``, cropped with
    the settings of ``model`` (``perception.inputs.prepare_cls_input``).

    One sample per annotated visible instance (its ground-truth mask) and, when ``source.segmenter`` is given
    (a function RGB -> parts, e.g. a trained segmentation net's), one per part of at least ``min_points`` pixels
    labelled with the ground-truth object covering most of it: the classifier then
    learns on the fragments it will see at run time. Segments mostly on background are skipped, unless 0
    ("not a block") is in ``obj_ids``: then those with at most ``BACKGROUND_MAX_FG`` of their pixels on
    objects are its samples. ``height_range`` > 0: crops with the height channel, above each image's supporting
    plane (``perception.plane``, fitted with the default settings and seed 0, as the estimator does).
    Crops are computed once, at construction; with ``source.cache`` (a ``.npy`` path) they are also written there,
    with a ``.json`` beside it holding their labels and what they were computed from (dataset, split, crop settings,
    the objects, a hash of the annotations and ``source.segmenter_id``, which must name the segmenter), and a later
    construction with the same key reads them back as a memory map instead (a resumed training run starts at once).
    Augmentation (seeded by index and key): a random permutation of the colour channels (block colours carry no class
    information), brightness and contrast, a rotation by a multiple of 90 degrees and a mirror flip (the blocks'
    shapes are mirror-symmetric).
    """

    BACKGROUND_MAX_FG = 0.2
    CACHE_VERSION = 1

    def __init__(self, root: str | Path, split: str, model: ClassifierConfig, cfg: DataConfig | None = None,
                 augment: bool = False, seed: int = 0, source: CropSource | None = None):
        self.cfg = cfg or DataConfig()
        self.obj_ids = list(model.obj_ids)
        self.augment = augment and self.cfg.augment
        self.seed = seed
        source = source or CropSource()
        records = load_records(root, split)
        key = {"version": self.CACHE_VERSION, "root": str(Path(root).resolve()), "split": split,
               "images": len(records), "annotations": fingerprint(records),
               "obj_ids": self.obj_ids, "crop": [model.crop_size, model.crop_side, model.depth_range,
                                                 model.height_range],
               "selection": [self.cfg.min_visib_fract, self.cfg.min_points, self.BACKGROUND_MAX_FG],
               "segmenter": source.segmenter_id if source.segmenter is not None else None}
        cached = read_crop_cache(Path(source.cache), key) if source.cache is not None else None
        if cached is None:
            crops, labels = self._crops(records, split, model, source)
            if not crops:
                raise DatasetError(f"no usable object instance in {Path(root) / split} for the classifier")
            cached = (write_crop_cache(Path(source.cache), key, crops, labels) if source.cache is not None
                      else (crops, labels))
        self.crops = cached[0]  # (C, S, S) float16 each: a list, or a read-only memory map of the cache
        self.labels = np.asarray(cached[1], dtype=np.int64)

    def _crops(self, records: list, split: str, model: ClassifierConfig, source: CropSource
               ) -> tuple[list[np.ndarray], list[int]]:
        """The crops (C, S, S) float16, in a list (stacking them would double the peak memory), and their labels."""
        from posegrasp.progress import track

        crops, labels = [], []
        for rec in track(records, f"crops {split}", enabled=source.progress):
            rgb, depth, K = rec.load_rgb(), rec.load_depth(), rec.camera.K
            masks = [(inst.obj_id, rec.load_mask(inst.gt_index)) for inst in rec.instances
                     if inst.obj_id in self.obj_ids and usable(inst, self.cfg)]
            if source.segmenter is not None:
                gt = label_map(rec, rgb.shape[:2])
                for _, m in source.segmenter(rgb):
                    g = gt[m]
                    if g.size < self.cfg.min_points:
                        continue
                    major = int(np.bincount(g).argmax())
                    if major in self.obj_ids and (major > 0 or (g > 0).mean() <= self.BACKGROUND_MAX_FG):
                        masks.append((major, m))
            plane = fit_support_plane(depth, K) if model.height_range > 0 else None
            for obj_id, m in masks:
                x = prepare_cls_input(rgb, depth, K, m, model, plane)
                if x is not None:
                    crops.append(x.astype(np.float16))
                    labels.append(self.obj_ids.index(obj_id))
        return crops, labels

    def __len__(self) -> int:
        return len(self.labels)

    def get(self, index: int, key: int | None = None) -> dict[str, torch.Tensor | int]:
        """Sample ``index``; ``key`` seeds the augmentation (None: none)."""
        x = self.crops[index].astype(np.float32)
        if self.augment and key is not None:
            rng = _rng(self.seed, index, key)
            j = self.cfg.color_jitter
            rgb = x[rng.permutation(3)] * rng.uniform(1 - j, 1 + j)
            mean = rgb.mean()
            x[:3] = np.clip((rgb - mean) * rng.uniform(1 - j, 1 + j) + mean, 0.0, 1.0)
            x = np.rot90(x, int(rng.integers(4)), axes=(1, 2))
            if rng.random() < 0.5:
                x = x[:, :, ::-1]
        return {"image": torch.from_numpy(normalize_cls_input(np.ascontiguousarray(x))),
                "label": int(self.labels[index])}

    def __getitem__(self, index: int) -> dict[str, torch.Tensor | int]:
        return self.get(index)


class PoseDataset(Dataset):
    """One sample per visible annotated object instance of the pose net ``model``'s objects, with its
    ``num_points`` depth points and ``crop_size`` colour crop.

    Sample keys: image (3, S, S), choose (N,) int64, points (N, 3) camera frame (m), model_points
    (M, 3) object frame (m), target (M, 3) = model points under the ground truth (m), obj (head
    index), symmetric (bool), T (4, 4) float64 ground truth, obj_id, scene_id, im_id, gt_index;
    sym_targets (S, M, 3): the model points under T S_k for the identity and each discrete symmetry S_k of
    the object (S = 1 + the most discrete symmetries of any object of the dataset, padded with the
    identity's copy), and continuous (bool): the object has a continuous symmetry.
    """

    def __init__(self, root: str | Path, split: str, model: PoseNetConfig, cfg: DataConfig | None = None,
                 augment: bool = False, seed: int = 0, models: ObjectModels | None = None):
        self.root, self.split = Path(root), split
        self.cfg = cfg or DataConfig()
        self.models = models or ObjectModels(root, self.cfg.model_pool)
        self.obj_ids = list(model.obj_ids)
        missing = [o for o in self.obj_ids if o not in self.models.infos]
        if missing:
            raise DatasetError(f"object ids {missing} are not in {bop.models_info_path(root)}")
        self.num_points, self.crop_size = model.num_points, model.crop_size
        self.augment = augment and self.cfg.augment
        self.seed = seed
        self.records = records = load_records(root, split)
        self.index: list[tuple[int, int]] = []
        for ri, rec in enumerate(records):
            self.index += [(ri, inst.gt_index) for inst in rec.instances
                           if inst.obj_id in self.obj_ids and usable(inst, self.cfg)]
        if not self.index:
            raise DatasetError(f"no usable object instance in {self.root / split} (min_visib_fract "
                               f"{self.cfg.min_visib_fract}, min_points {self.cfg.min_points})")
        self.num_sym = 1 + max(len(self.models.infos[o].symmetries_discrete) for o in self.obj_ids)

    def __len__(self) -> int:
        return len(self.index)

    def symmetric(self, obj_id: int) -> bool:
        return self.models.infos[obj_id].symmetric

    def _sym_targets(self, obj_id: int, model: np.ndarray, T: np.ndarray) -> np.ndarray:
        """(num_sym, M, 3) float32: ``model`` under T S_k, identity first, padded with the identity's copy."""
        syms = [np.eye(4)] + list(self.models.infos[obj_id].symmetries_discrete)
        syms += [np.eye(4)] * (self.num_sym - len(syms))
        out = np.stack([model @ (T @ S)[:3, :3].T + (T @ S)[:3, 3] for S in syms])
        return out.astype(np.float32)

    def get(self, index: int, key: int | None = None) -> dict[str, torch.Tensor | int | bool]:
        """Sample ``index``; ``key`` seeds augmentation (None: none). An instance with too few valid
        depth points is replaced by the next usable one (deterministically)."""
        for k in range(len(self.index)):
            s = self._sample((index + k) % len(self.index), key)
            if s is not None:
                return s
        raise DatasetError(f"no instance in {self.root / self.split} has {self.cfg.min_points} valid depth points")

    def __getitem__(self, index: int) -> dict[str, torch.Tensor | int | bool]:
        return self.get(index)

    def _sample(self, index: int, key: int | None) -> dict | None:
        ri, gi = self.index[index]
        rec = self.records[ri]
        inst = rec.instances[gi]
        aug = self.augment and key is not None
        rng = _rng(self.seed, index, key)
        depth = rec.load_depth()
        mask = rec.load_mask(gi)
        if int((mask & (depth > 0)).sum()) < self.cfg.min_points:
            return None
        rgb = rec.load_rgb()
        if aug:
            rgb = color_jitter(rgb, rng, self.cfg.color_jitter, self.cfg.hue_jitter)
        prep = prepare_pose_input(rgb, depth, rec.camera.K, mask, self.num_points, self.crop_size, rng,
                                  self.cfg.depth_noise if aug else 0.0)
        img, choose, pts = prep
        pool = self.models.points(inst.obj_id)
        mi = rng.choice(len(pool), size=min(self.cfg.num_model_points, len(pool)), replace=False)
        model = pool[np.sort(mi)]
        T = inst.T_cam_obj
        target = model @ T[:3, :3].T + T[:3, 3]
        if aug and self.cfg.translation_noise > 0:
            shift = rng.uniform(-self.cfg.translation_noise, self.cfg.translation_noise, 3)
            pts = pts + shift.astype(np.float32)
            target = target + shift
            T = T.copy()
            T[:3, 3] += shift
        return {
            "image": torch.from_numpy(img), "choose": torch.from_numpy(choose),
            "points": torch.from_numpy(pts.astype(np.float32)),
            "model_points": torch.from_numpy(model.astype(np.float32)),
            "target": torch.from_numpy(target.astype(np.float32)),
            "obj": self.obj_ids.index(inst.obj_id), "symmetric": self.symmetric(inst.obj_id),
            "sym_targets": torch.from_numpy(self._sym_targets(inst.obj_id, model, T)),
            "continuous": bool(self.models.infos[inst.obj_id].symmetries_continuous),
            "T": torch.from_numpy(T), "obj_id": inst.obj_id, "scene_id": rec.scene_id, "im_id": rec.im_id,
            "gt_index": gi,
        }


def collate(samples: list[dict]) -> dict[str, torch.Tensor]:
    """Stack a list of samples into a batch (ints and bools become tensors)."""
    return torch.utils.data.default_collate(samples)
