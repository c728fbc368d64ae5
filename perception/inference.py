"""The two-stage estimator: segmentation, then per-object pose and iterative refinement.

    est = Estimator("runs/blocks")           # RUN dir with seg/, pose/ and optionally cls/, refine/
    for det in est(rgb, depth, K):           # uint8 (H, W, 3), float32 metres (H, W), (3, 3)
        det.obj_id, det.T_cam_obj, det.score, det.mask

Several blocks of one type are told apart as the connected components of their class mask. When the
run has an instance classifier (``cls/``, ``perception.classifier``; with further ensemble members ``cls_<name>/``,
whose class probabilities are averaged), every connected segment of the class map is re-labelled by it before the
instances are formed. With block models (``models``) every
estimate is refined against the depth image (``perception.icp``) and the parts of a mask its fitted model leaves
unexplained become detections of their own (``perception.split``: touching blocks segmented as one).
Last, the outlines of the class map and of the detections' masks are snapped to the colour image's edges
(``perception.guided``); the poses stay those fitted to the masks before.
Works on real camera data as well as on simulated frames: it only needs RGB, depth in metres and
the intrinsics. Objects whose mask has fewer valid depth pixels than ``min_valid_points`` are
declared invalid and skipped, as in the paper.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from threadpoolctl import ThreadpoolController
from torch.nn.utils.fusion import fuse_conv_bn_eval

from posegrasp.perception import checkpoint as ckpt_mod
from posegrasp.perception.classifier import ClassifierConfig
from posegrasp.perception.crop import backproject, mask_bbox, padded_box
from posegrasp.perception.data import (normalize_cls_input, normalize_rgb, prepare_cls_input,
                             prepare_pose_input, segment_components)
from posegrasp.perception.guided import GuidedConfig, argmax_planes, refine_labels
from posegrasp.perception.icp import ICPConfig, NearestGrid, distinct_rotations, refine_poses
from posegrasp.perception.plane import PlaneConfig, clear_plane, fit_support_plane
from posegrasp.perception.refiner import refine
from posegrasp.perception.seg_net import SegNetConfig
from posegrasp.perception.split import ModelSurface, SplitConfig, unexplained_parts
from posegrasp.perception.torch_geometry import make_transform, quat_to_rotmat
from posegrasp import bop
from posegrasp.errors import UserError


_BLAS: ThreadpoolController | None = None

#: The pose net's points per object and crop side (px) when its estimates are refined against the depth image.
REFINED_POSE_INPUT = (250, 48)


def one_blas_thread() -> contextlib.AbstractContextManager:
    """A context in which numpy's BLAS (OpenBLAS) runs on one thread. The pipeline's numpy products are small, but
    past ~2.6e5 multiply-adds OpenBLAS splits them over its threads, which then spin-wait for more work and take the
    cores from torch's next stage: on 2 cores a classifier after the supporting plane's fit ran 2x slower."""
    global _BLAS
    if _BLAS is None:
        _BLAS = ThreadpoolController()
    return _BLAS.limit(limits=1, user_api="blas")


def _with_one_blas_thread(method: Callable) -> Callable:
    """``method`` run in ``one_blas_thread()``."""
    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return method(*args, **kwargs)
    return wrapper


@dataclass
class Detection:
    """One estimated object: BOP id, pose T_cam_obj (4x4, m, OpenCV camera frame), score in [0, 1]
    (mean segmentation probability over the mask x the pose confidence) and mask (H, W) bool."""

    obj_id: int
    T_cam_obj: np.ndarray
    score: float
    mask: np.ndarray


class Segmenter:
    """The segmentation stage alone: a seg net and its config; ``segmenter(rgb)`` -> class map."""

    def __init__(self, model: torch.nn.Module, cfg: SegNetConfig):
        self.model, self.cfg = for_inference(model), cfg

    @classmethod
    def load(cls, ckpt: str | Path) -> "Segmenter":
        """From a ``seg`` checkpoint directory."""
        model, cfg, _ = ckpt_mod.load_model(Path(ckpt), "seg")
        return cls(model, cfg)

    @torch.no_grad()
    def __call__(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Class map (H, W) int64 (0 background, else obj_id) and class probabilities (H, W, C)
        float32: softmax at the net's input size, bilinearly resized to the image (OpenCV, channels
        last, which is ~5x faster on a CPU than arg-maxing upsampled logits in torch); the class map is their
        arg-max (``upsampled_argmax``)."""
        h, w = rgb.shape[:2]
        ih, iw = self.cfg.input_size
        x = rgb if (h, w) == (ih, iw) else cv2.resize(rgb, (iw, ih), interpolation=cv2.INTER_LINEAR)
        logits = self.model(torch.from_numpy(normalize_rgb(x))[None])  # (1, C, ih, iw)
        small = torch.softmax(logits[0], dim=0)  # (C, ih, iw)
        prob = np.ascontiguousarray(small.permute(1, 2, 0).numpy())  # (ih, iw, C)
        if (h, w) == (ih, iw):
            return argmax_planes(small.numpy()).astype(np.int64), prob
        prob = cv2.resize(prob, (w, h), interpolation=cv2.INTER_LINEAR)
        if prob.ndim == 2:  # OpenCV drops a single channel axis
            prob = prob[..., None]
        return upsampled_argmax(small.numpy(), prob), prob


class Estimator:
    """Segmentation + pose + refinement from a run directory (``seg/``, ``pose/``, ``refine/``).

    refine_iterations: None = the refiner's configured count (0 when there is no refiner);
    0 disables refinement (ablation). classify: None = re-label segments with the run's ``cls/``
    classifier (and its ensemble members ``cls_<name>/``) when it has one; False = never (ablation: the paper's
    pipeline); True = required.
    min_valid_points: minimum valid-depth pixels per object. models: a BOP dataset root whose
    ``models/`` hold the objects' meshes; with it every estimate is refined against the depth image by
    ICP from rotation hypotheses (``perception.icp``, settings ``icp``); None skips that step.
    support_plane: fit the frame's dominant plane (``perception.plane``); segmented pixels on it become
    background and ICP hypotheses sunk into it lose.
    split: with ``models``, the part of a detection's mask its fitted model leaves unexplained becomes a
    detection of its own (``perception.split``: touching blocks merged into one segment), and then two fits of one
    block are one detection (``drop_duplicates``); ``rounds = 0`` turns both off. guided: once the poses are
    fitted, the class map's and the masks' outlines are snapped to the colour image's edges (``perception.guided``);
    ``radius = 0`` turns it off.
    pose_points, pose_crop: the depth points sampled per object for the pose net and the side (px) of its colour crop.
    None: with ``models`` 250 and 48 (``REFINED_POSE_INPUT``), else as in the net's training. The attention over the
    points costs O(N^2) and the colour CNN O(S^2); once the depth refinement fits the pose, the shipped net (trained
    with 500 points and 80 px) is as accurate with the smaller inputs (1234 against 1229 of the 1379 instances of the
    test, val and fresh splits within 0.1 d), while the pose net alone is not (test acc 59.8 against 76.5 %).
    threads: torch CPU threads (None leaves the setting alone). seed: point sampling seed (each call is deterministic).
    ``timings`` holds the seconds spent per stage in the last call and ``last_labels`` its class map (H, W).
    """

    def __init__(self, weights: str | Path, refine_iterations: int | None = None, min_valid_points: int = 50,
                 threads: int | None = None, seed: int = 0, classify: bool | None = None,
                 models: str | Path | None = None, icp: ICPConfig | None = None, support_plane: bool = True,
                 split: SplitConfig | None = None, guided: GuidedConfig | None = None, pose_points: int | None = None,
                 pose_crop: int | None = None):
        weights = Path(weights)
        if not weights.is_dir():
            raise UserError(f"weights directory {weights} does not exist")
        if threads is not None:
            torch.set_num_threads(threads)
        self.segmenter = Segmenter.load(weights / "seg")
        self.seg_cfg = self.segmenter.cfg
        self.pose, self.pose_cfg, _ = ckpt_mod.load_model(weights / "pose", "pose")
        for_inference(self.pose)
        self.refiner, self.refiner_cfg = None, None
        if (weights / "refine").exists():
            self.refiner, self.refiner_cfg, _ = ckpt_mod.load_model(weights / "refine", "refine")
            if list(self.refiner_cfg.obj_ids) != list(self.pose_cfg.obj_ids) or \
                    self.refiner_cfg.emb_dim != self.pose_cfg.emb_dim:
                raise UserError(f"refiner in {weights / 'refine'} was trained for another pose net")
        self.classifiers: list[torch.nn.Module] = []
        self.cls_cfg: ClassifierConfig | None = None  # the crop settings of the members
        if classify is not False and (weights / "cls").exists():
            self.classifiers, self.cls_cfg = _load_classifiers(weights)
        elif classify:
            raise UserError(f"{weights} has no cls/ checkpoint: train one with 'posegrasp train cls'")
        default_iters = self.refiner_cfg.iterations if self.refiner_cfg is not None else 0
        self.refine_iterations = default_iters if refine_iterations is None else refine_iterations
        if self.refine_iterations > 0 and self.refiner is None:
            raise UserError(f"{weights} has no refine/ checkpoint: cannot refine")
        self.min_valid_points = min_valid_points
        points, crop = REFINED_POSE_INPUT if models is not None else (self.pose_cfg.num_points, self.pose_cfg.crop_size)
        self.pose_points = points if pose_points is None else pose_points
        self.pose_crop = crop if pose_crop is None else pose_crop
        if self.pose_points < 1 or self.pose_crop < 8 or self.pose_crop % 8:
            raise UserError(f"pose_points must be >= 1 and pose_crop a multiple of 8 px, got {self.pose_points} and "
                            f"{self.pose_crop}")
        self.seed = seed
        self.icp = icp or ICPConfig()
        self.icp.validate()
        self.support_plane, self.plane_cfg = support_plane, PlaneConfig()
        self.split_cfg = split or SplitConfig()
        self.guided_cfg = guided or GuidedConfig()
        self.guided_cfg.validate()
        self.model_points: dict[int, np.ndarray] | None = None
        self.hypotheses: dict[int, np.ndarray] = {}
        self.grids: dict[int, NearestGrid] = {}
        self.surfaces: dict[int, ModelSurface] = {}
        if models is not None:
            infos = bop.load_models_info(models)
            missing = [o for o in self.obj_ids if o not in infos]
            if missing:
                raise UserError(f"models in {models} lack objects {missing} of the pose net")
            self.model_points = {o: bop.sample_model_points(bop.load_model(models, o), 500, seed=o)
                                 for o in self.obj_ids}
            self.hypotheses = {o: distinct_rotations(self.icp.rotations(), infos[o].symmetries_discrete,
                                                     [a for a, _ in infos[o].symmetries_continuous])
                               for o in self.obj_ids}
            self.grids = {o: NearestGrid(self.model_points[o]) for o in self.obj_ids}
            if self.split_cfg.rounds > 0:
                self.surfaces = {o: ModelSurface(bop.sample_model_points(bop.load_model(models, o),
                                                                          self.split_cfg.model_points, seed=o))
                                 for o in self.obj_ids}
        self.timings: dict[str, float] = {"seg": 0.0, "cls": 0.0, "guided": 0.0, "pose": 0.0, "refine": 0.0,
                                          "icp": 0.0, "split": 0.0}
        self.last_labels: np.ndarray | None = None

    @property
    def obj_ids(self) -> list[int]:
        """BOP ids of the objects the pose net knows."""
        return list(self.pose_cfg.obj_ids)

    def segment(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Class map and class probabilities of an RGB image (see ``Segmenter``)."""
        return self.segmenter(rgb)

    @_with_one_blas_thread
    @torch.no_grad()
    def estimate(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, masks: list[tuple[int, np.ndarray]],
                 mask_scores: list[float] | None = None, plane: np.ndarray | None = None) -> list[Detection]:
        """Poses of objects given their masks (obj_id, bool (H, W)); skips objects the pose net does
        not know and masks with fewer than ``min_valid_points`` valid depth pixels. Each detection
        carries the very mask array it was given. plane: the supporting plane for the depth refinement
        (fitted here when None and ``support_plane`` is on)."""
        t0 = time.perf_counter()
        if plane is None and self.support_plane and self.model_points is not None:
            plane = fit_support_plane(depth, K, self.seed, self.plane_cfg)
        rng = np.random.default_rng(self.seed)
        cfg = self.pose_cfg
        items, kept = [], []
        for k, (obj_id, mask) in enumerate(masks):
            box = padded_box(mask, 0)
            if obj_id not in cfg.obj_ids or box is None or \
                    int((mask[box] & (depth[box] > 0)).sum()) < self.min_valid_points:
                continue
            prep = prepare_pose_input(rgb, depth, K, mask, self.pose_points, self.pose_crop, rng)
            if prep is None:
                continue
            items.append(prep)
            kept.append(k)
        if not items:
            self.timings.update(pose=time.perf_counter() - t0, refine=0.0, icp=0.0)
            return []
        img = torch.from_numpy(np.stack([i[0] for i in items]))
        choose = torch.from_numpy(np.stack([i[1] for i in items]))
        points = torch.from_numpy(np.stack([i[2] for i in items]))
        obj = torch.tensor([cfg.index_of(masks[k][0]) for k in kept])
        q, t, conf, best, emb = self.pose.predict(img, points, choose, obj)
        T = make_transform(quat_to_rotmat(q), points[torch.arange(len(kept)), best] + t)  # (B, 4, 4)
        t1 = t2 = time.perf_counter()
        if self.refine_iterations > 0 and self.refiner is not None:
            T = refine(self.refiner, T, points, emb, obj, self.refine_iterations)
            t2 = time.perf_counter()
        poses = [T[j].double().numpy() for j in range(len(kept))]
        if self.model_points is not None:
            poses = self._depth_refine(poses, [masks[k] for k in kept], depth, K, rng, plane)
        out = [Detection(obj_id=int(masks[k][0]), T_cam_obj=T_j, mask=masks[k][1],
                         score=float((1.0 if mask_scores is None else mask_scores[k]) * float(conf[j])))
               for j, (k, T_j) in enumerate(zip(kept, poses))]
        self.timings.update(pose=t1 - t0, refine=t2 - t1, icp=time.perf_counter() - t2)
        return out

    def _depth_refine(self, poses: list[np.ndarray], masks: list[tuple[int, np.ndarray]], depth: np.ndarray,
                      K: np.ndarray, rng: np.random.Generator, plane: np.ndarray | None) -> list[np.ndarray]:
        """``perception.icp.refine_poses`` of the estimates (4x4 each) on (up to ``icp.max_points`` of) their masks'
        valid depth points (obj_id, (H, W) bool each)."""
        observed = []
        for _, m in masks:  # (each mask has valid depth: ``estimate`` keeps no other)
            r0, r1, c0, c1 = box = mask_bbox(m)
            idx = np.flatnonzero(m[r0:r1, c0:c1] & (depth[r0:r1, c0:c1] > 0))  # raster order, as in the image
            if idx.size > self.icp.max_points:
                idx = idx[np.sort(rng.choice(idx.size, self.icp.max_points, replace=False))]
            observed.append(backproject(depth, K, box, idx))
        ids = [o for o, _ in masks]
        return [T for T, _ in refine_poses(poses, [self.model_points[o] for o in ids], observed, depth, K, self.icp,
                                           [self.hypotheses[o] for o in ids], plane, [self.grids[o] for o in ids])]

    @_with_one_blas_thread
    @torch.no_grad()
    def classify(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, labels: np.ndarray,
                 plane: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Re-label every connected segment of the class map (H, W) with the instance classifier (plane: the
        supporting plane, for a classifier with the height channel; fitted here when None).

        Returns the new class map and the per-pixel confidence (H, W) float32: the classifier's
        probability of the chosen class on re-labelled segments, 0 elsewhere. Segments it calls "not a
        block" (id 0, when it has that class) become background. Segments without enough valid depth for
        a crop keep their label and get confidence 0."""
        new, conf = labels.copy(), np.zeros(labels.shape, dtype=np.float32)
        segs = [m for _, m in segment_components(labels, 1)]
        for m, c in zip(segs, self._classify_masks(rgb, depth, K, segs, plane)):
            if c is not None:
                new[m], conf[m] = c
        return new, conf

    def _classify_masks(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, masks: list[np.ndarray],
                        plane: np.ndarray | None) -> list[tuple[int, float] | None]:
        """(obj_id, probability) by the instance classifier for each mask (H, W) bool, in order; None where the
        mask lacks the valid depth for a crop. plane: for the height channel (fitted here when None)."""
        cfg = self.cls_cfg
        if cfg.height_range > 0 and plane is None:
            plane = fit_support_plane(depth, K, self.seed, self.plane_cfg)
        crops = [prepare_cls_input(rgb, depth, K, m, cfg.crop_size, cfg.crop_side, cfg.depth_range,
                                   height_range=cfg.height_range, plane=plane) for m in masks]
        ok = [i for i, x in enumerate(crops) if x is not None]
        out: list[tuple[int, float] | None] = [None] * len(masks)
        if ok:
            x = torch.from_numpy(np.stack([normalize_cls_input(crops[i]) for i in ok]))  # (S, C, size, size)
            prob = torch.stack([torch.softmax(m(x[:, :m.cfg.in_channels]), dim=1) for m in self.classifiers])
            pmax, k = prob.mean(dim=0).max(dim=1)  # (S,)
            for i, kk, pp in zip(ok, k.tolist(), pmax.tolist()):
                out[i] = (cfg.obj_ids[kk], pp)
        return out

    @_with_one_blas_thread
    def __call__(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray) -> list[Detection]:
        """Detect and estimate every known object in an RGB-D frame (depth in metres, 0 = invalid)."""
        rgb, depth, K = _check_inputs(rgb, depth, K)
        t0 = time.perf_counter()
        labels, prob = self.segment(rgb)
        plane = None
        if self.support_plane:  # segmented pixels lying on the table become background
            labels, plane = clear_plane(labels, depth, K, self.seed, self.plane_cfg)
        t1 = time.perf_counter()
        conf, t_cls = None, 0.0
        if self.classifiers:
            labels, conf = self.classify(rgb, depth, K, labels, plane)
            t_cls = time.perf_counter() - t1
        self.last_labels = labels
        masks, scores = [], []
        for obj_id, m in segment_components(labels, self.min_valid_points):
            if obj_id not in self.obj_ids or obj_id >= prob.shape[-1]:
                continue
            masks.append((obj_id, m))
            # foreground probability x the classifier's confidence, or the seg net's class probability
            s = (1.0 - prob[..., 0][m]) * conf[m] if conf is not None else prob[..., obj_id][m]
            scores.append(float(s.mean()))
        self.timings.update(seg=time.perf_counter() - t0 - t_cls, cls=t_cls)
        dets = self.estimate(rgb, depth, K, masks, scores, plane)
        t4, stages = time.perf_counter(), {k: self.timings[k] for k in ("pose", "refine", "icp")}
        if self.surfaces:
            dets = self.split_merged(rgb, depth, K, dets, prob, plane)
            dets = self.drop_duplicates(dets)
        t5, t_guided = time.perf_counter(), 0.0
        if self.guided_cfg.radius > 0:
            dets = self.snap_outlines(rgb, dets)
            t_guided = time.perf_counter() - t5
        self.timings.update(stages, split=t5 - t4, guided=t_guided)
        return dets

    @_with_one_blas_thread
    def snap_outlines(self, rgb: np.ndarray, dets: list[Detection]) -> list[Detection]:
        """``perception.guided``: the class map ``last_labels`` with its outlines snapped to the colour edges, and
        each detection's mask likewise: the pixels of its type in the refined map within the filter's radius of
        its mask; a pixel that several such masks reach stays with those that held it. The poses are the ones
        fitted to the masks before (outlines shifted a few pixels onto a neighbour hurt the fits more than they
        help)."""
        r = self.guided_cfg.radius
        labels = self.last_labels = refine_labels(self.last_labels, rgb, self.guided_cfg)
        boxes = [padded_box(d.mask, r) for d in dets]  # each grown mask lies in its mask's box widened by r
        grown = [(labels[b] == d.obj_id) & _dilate(d.mask[b], r) for d, b in zip(dets, boxes)]
        claims = np.zeros(labels.shape, dtype=np.uint8)
        for b, g in zip(boxes, grown):
            claims[b] += g
        out = []
        for d, b, g in zip(dets, boxes, grown):
            mask = np.zeros_like(d.mask)
            mask[b] = g & ((claims[b] == 1) | d.mask[b])
            out.append(dataclasses.replace(d, mask=mask))
        return out

    @_with_one_blas_thread
    def split_merged(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, dets: list[Detection],
                     prob: np.ndarray, plane: np.ndarray | None) -> list[Detection]:
        """``perception.split``: each detection whose fitted model leaves a large part of its mask unexplained
        is fitted again to the rest, and each such part is typed (``_part_types``) and fitted as a detection of
        its own; ``split_cfg.rounds`` times. A split is undone when a part and the rest are fitted as the same block
        (``_same_block``): the part was a strip of it that the first fit missed. Updates ``last_labels``."""
        cfg = self.split_cfg
        done: list[Detection] = []  # detections not to be tested again
        for _ in range(cfg.rounds):
            split: list[tuple[Detection, list[np.ndarray]]] = []
            for d in dets:
                explained = self.surfaces[d.obj_id].explained(d.T_cam_obj, d.mask, depth, K, cfg.tol)
                ps = unexplained_parts(d.mask, explained, depth, cfg)
                if ps:
                    split.append((d, ps))
                else:
                    done.append(d)
            if not split:
                return done
            all_types = iter(self._part_types(rgb, depth, K, [p for _, ps in split for p in ps], prob, plane))
            groups, masks, scores, todo = [], [], [], []
            for d, ps in split:
                rest = d.mask & ~np.any(ps, axis=0)
                types = [next(all_types) for _ in ps]
                groups.append((d, rest, ps, [o for o, _ in types]))
                masks += [(d.obj_id, rest)] + [(o, p) for p, (o, _) in zip(ps, types)]
                scores += [d.score] + [float((1.0 - prob[..., 0][p]).mean()) * pc for p, (_, pc) in zip(ps, types)]
            fitted = {id(f.mask): f for f in self.estimate(rgb, depth, K, masks, scores, plane)}
            for d, rest, ps, types in groups:
                new = [fitted[id(p)] for p in ps if id(p) in fitted]
                first = [fitted[id(rest)]] if id(rest) in fitted else []
                if any(self._same_block(n, f) for n in new for f in first):
                    done.append(d)  # one block: keep the first fit, its mask whole
                    continue
                todo += new + first
                for p, o in zip(ps, types):
                    self.last_labels[p] = o
            dets = todo
        return done + dets

    def drop_duplicates(self, dets: list[Detection]) -> list[Detection]:
        """``dets`` without those fitted where a detection of the same type with a larger mask sits: their centres
        closer than ``split_cfg.duplicate`` x the block's smallest side, which two blocks cannot be (one block
        seen as two segments, or split in two)."""
        if self.split_cfg.duplicate <= 0 or self.model_points is None:  # (the blocks' sizes come with the models)
            return dets
        kept: list[Detection] = []
        for d in sorted(dets, key=lambda d: -int(d.mask.sum())):
            side = float(np.ptp(self.model_points[d.obj_id], axis=0).min())
            if all(k.obj_id != d.obj_id or np.linalg.norm(k.T_cam_obj[:3, 3] - d.T_cam_obj[:3, 3]) >=
                   self.split_cfg.duplicate * side for k in kept):
                kept.append(d)
        return [d for d in dets if any(d is k for k in kept)]

    def _same_block(self, a: Detection, b: Detection) -> bool:
        """Whether two fitted detections are one block twice: the same type, and the median distance of ``a``'s
        model points (placed at its pose) to ``b``'s placed surface below ``split_cfg.same_block``."""
        if a.obj_id != b.obj_id:
            return False
        pts = self.model_points[a.obj_id] @ a.T_cam_obj[:3, :3].T + a.T_cam_obj[:3, 3]  # camera frame
        dist, _ = self.surfaces[b.obj_id].tree.query((pts - b.T_cam_obj[:3, 3]) @ b.T_cam_obj[:3, :3])
        return float(np.median(dist)) < self.split_cfg.same_block

    def _part_types(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, parts: list[np.ndarray],
                    prob: np.ndarray, plane: np.ndarray | None) -> list[tuple[int, float]]:
        """(obj_id, probability) of each part (H, W) bool: the instance classifier's (0: not a block, so the part
        is not fitted and becomes background), else (no classifier, or no crop) the seg net's most probable
        object class (``prob`` (H, W, C)) over the part. All parts go through the classifier as one batch."""
        by_cls = ([None] * len(parts) if not self.classifiers else
                  self._classify_masks(rgb, depth, K, parts, plane))
        out = []
        for p, c in zip(parts, by_cls):
            if c is None:
                mean = prob[p][:, 1:].mean(axis=0)  # (C - 1,) object classes
                c = (int(mean.argmax()) + 1, float(mean.max()))
            out.append(c)
        return out


def upsampled_argmax(small: np.ndarray, prob: np.ndarray) -> np.ndarray:
    """``prob.argmax(axis=-1)`` as int64 (H, W), where ``prob`` (H, W, C) is ``small`` (C, h, w) resized bilinearly by
    OpenCV (``INTER_LINEAR``, half-pixel centres). A pixel's value is a convex combination of ``small`` at the (up to)
    2 x 2 source pixels around x_s = (x + 1/2) w / W - 1/2 (likewise y), all within one pixel of the nearest,
    round(x_s). Where ``small``'s arg-max is one class c over that nearest pixel's 3 x 3 neighbourhood, p_c >= p_k at
    each source pixel, so also in their combination: the arg-max is c. So the class map is the nearest-neighbour
    upsampling of ``small``'s, and only the pixels near its class boundaries (a few per cent of a frame) are arg-maxed
    in ``prob``: the same map (to float rounding) ~3x faster."""
    lab = argmax_planes(small)  # (h, w)
    disc = np.ones((3, 3), dtype=np.uint8)
    mixed = (cv2.dilate(lab, disc) != cv2.erode(lab, disc)).view(np.uint8)  # neighbourhoods of more than one class
    H, W = prob.shape[:2]
    out = cv2.resize(lab, (W, H), interpolation=cv2.INTER_NEAREST_EXACT)  # source pixel round(x_s), round(y_s)
    near = np.nonzero(cv2.resize(mixed, (W, H), interpolation=cv2.INTER_NEAREST_EXACT))
    out[near] = prob[near].argmax(axis=-1)
    return out.astype(np.int64)


def for_inference(model: torch.nn.Module) -> torch.nn.Module:
    """``model`` itself, in eval mode, its BatchNorms folded into their convolutions (``fold_batch_norms``) and its 2D
    convolutions' weights channels-last: the outputs stay the same (to float rounding; inputs may stay NCHW) and come
    ~35 % faster on a CPU (oneDNN's native layout), a classifier's on a frame's 19 crops another ~35 % faster without
    the BatchNorms. For inference only: the model no longer trains or loads a checkpoint as it did."""
    fold_batch_norms(model.eval())
    return model.to(memory_format=torch.channels_last)


def fold_batch_norms(model: torch.nn.Module) -> None:
    """Each BatchNorm2d of ``model`` (in eval mode) folded into the Conv2d whose output it normalises and replaced by an
    identity: W' = W g / s, b' = (b - mu) g / s + beta per output channel (g, beta: its affine weights; mu, s^2: its
    running mean and variance + eps). The pairs are a Conv2d followed by a BatchNorm2d in an ``nn.Sequential`` and
    those a module names in its ``conv_bn_pairs`` (attribute names: (conv, bn), ...)."""
    for m in list(model.modules()):
        pairs = list(getattr(m, "conv_bn_pairs", ()))
        if isinstance(m, torch.nn.Sequential):
            pairs += [(str(i), str(i + 1)) for i in range(len(m) - 1)
                      if isinstance(m[i], torch.nn.Conv2d) and isinstance(m[i + 1], torch.nn.BatchNorm2d)]
        for conv, bn in pairs:
            setattr(m, conv, fuse_conv_bn_eval(getattr(m, conv), getattr(m, bn)))
            setattr(m, bn, torch.nn.Identity())


def _load_classifiers(weights: Path) -> tuple[list[torch.nn.Module], ClassifierConfig]:
    """The run's instance classifier ``cls/`` and the further members of its ensemble, ``cls_<name>/`` (by name), and
    the crop settings they share: the same objects and crop geometry; members with the height channel share its
    range, and those without read the crop's first 6 channels."""
    dirs = [weights / "cls"] + sorted(p for p in weights.glob("cls_*") if p.is_dir())
    models, cfgs = [], []
    for d in dirs:
        model, cfg, _ = ckpt_mod.load_model(d, "cls")
        models.append(for_inference(model))
        cfgs.append(cfg)
    key = [(list(c.obj_ids), c.crop_size, c.crop_side, c.depth_range) for c in cfgs]
    for d, k in zip(dirs[1:], key[1:]):
        if k != key[0]:
            raise UserError(f"classifier {d} differs from {dirs[0]} in its objects or crop settings ({k} vs {key[0]}): "
                            "an ensemble's members must share them")
    heights = sorted({c.height_range for c in cfgs if c.height_range > 0})
    if len(heights) > 1:
        raise UserError(f"the classifiers in {weights} use height ranges {heights}: an ensemble's members share one")
    return models, dataclasses.replace(cfgs[0], height_range=heights[0] if heights else 0.0)


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """Mask (h, w) bool dilated by a disc of radius r px (nothing beyond its border)."""
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(mask.view(np.uint8), disc, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0


def _check_inputs(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rgb, depth, K = np.asarray(rgb), np.asarray(depth), np.asarray(K, dtype=np.float64)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
    if depth.shape != rgb.shape[:2]:
        raise ValueError(f"depth must be (H, W) = {rgb.shape[:2]}, got {depth.shape}")
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got {K.shape}")
    depth = np.nan_to_num(depth.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    return rgb, depth, K
