"""The two-stage estimator: segmentation, then per-object pose, the refiner and the depth fit.

    est = Estimator("runs/blocks")           # RUN dir with seg/, pose/ and optionally cls/, refiner/
    res = est(rgb, depth, K)                 # uint8 (H, W, 3), float32 metres (H, W), (3, 3)
    for det in res.detections:
        det.obj_id, det.T_cam_obj, det.score, det.mask
    res.labels, res.timings                  # class map (H, W); seconds per stage

Several blocks of one type are told apart as the connected components of their class mask. When the
run has an instance classifier (``cls/``, ``perception.classifier``; with further ensemble members ``cls_<name>/``,
``perception.ensemble``), every connected segment of the class map is re-labelled by it before the
instances are formed. With block models (``EstimatorConfig.models``) every
estimate is fitted to the depth image (``perception.depth_fit``) and the parts of a mask its fitted model leaves
unexplained become detections of their own (``perception.split``: touching blocks segmented as one).
Last, the outlines of the class map and of the detections' masks are snapped to the colour image's edges
(``perception.guided``); the poses stay those fitted to the masks before.
Works on real camera data as well as on simulated frames: it only needs RGB, depth in metres and
the intrinsics. Objects whose mask has fewer valid depth pixels than ``min_valid_points`` are
declared invalid and skipped, as in the paper.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.config import settings, within
from posegrasp.errors import ConfigError, DatasetError, WeightsError
from posegrasp.perception import checkpoint as ckpt_mod
from posegrasp.perception.crop import backproject, mask_bbox, padded_box
from posegrasp.perception.ensemble import ClassifierEnsemble
from posegrasp.perception.depth_fit import DepthFitConfig, ObjectModel, fit_poses
from posegrasp.perception.depth_fit.distance_field import distinct
from posegrasp.perception.depth_fit.rivals import Rivals
from posegrasp.perception.depth_fit.starts import Symmetries
from posegrasp.perception.guided import GuidedConfig, snap_labels
from posegrasp.perception.inputs import check_frame, prepare_pose_input, seam_components, segment_components
from posegrasp.perception.int8 import runs_int8
from posegrasp.perception.plane import PlaneConfig, clear_plane, fit_support_plane
from posegrasp.perception.refiner import refine
from posegrasp.perception.runtime import for_inference, packed, with_one_blas_thread
from posegrasp.perception.segmenter import ClassProbabilities, Segmenter
from posegrasp.perception.split import SplitConfig, drop_duplicates, same_place, unexplained_parts
from posegrasp.perception.torch_geometry import make_transform, quat_to_rotmat
from posegrasp.perception.type_check import TypeCheckConfig, best_per_part, candidates, cost

#: The pose net's points per object and crop side (px) when its estimates are fitted to the depth image.
DEPTH_FIT_POSE_INPUT = (250, 48)

#: The stages ``EstimateResult.timings`` reports, in this order.
STAGES = ("seg", "cls", "guided", "pose", "refiner", "depth_fit", "split")


@settings
class EstimatorConfig:
    """How an ``Estimator`` runs a trained run's nets: segmentation, pose, refiner, instance classifier, then
    (with ``models``) the depth fit, the mask splits and the guided outlines."""

    #: Refiner iterations: unset, the refiner's configured count (0 when the run has none); 0 turns it off.
    refiner_iterations: int | None = field(default=None, metadata=within(0, 100))
    #: Objects with fewer valid-depth pixels in their mask are skipped.
    min_valid_points: int = field(default=50, metadata=within(0, 10000000))
    #: Run the seg net and classifiers in int8 where their folders hold ranges (``posegrasp quantize``); false: float.
    int8: bool = True
    #: Torch CPU threads; unset leaves the process's setting alone.
    threads: int | None = field(default=None, metadata=within(1, 256))
    #: Seed of the depth points sampled per object (each call is deterministic).
    seed: int = field(default=0, metadata=within(0, 9223372036854775807))
    #: Re-label segments with the run's instance classifier: unset, when the run has one; false never; true required.
    classify: bool | None = None
    #: A BOP dataset root whose ``models/`` hold the meshes; with it every estimate is fitted to the depth image
    #: (settings ``depth_fit``).
    models: str | Path | None = None
    #: The depth fit's settings, by stage.
    depth_fit: DepthFitConfig = field(default_factory=DepthFitConfig)
    #: Fit the frame's dominant plane: segmented pixels on it become background and fits sunk into it lose.
    support_plane: bool = True
    #: With ``models``: a mask's part its fitted model leaves unexplained becomes a detection of its own.
    split: SplitConfig = field(default_factory=SplitConfig)
    #: With a seg net that has a seam head: pixels of a higher seam probability cut the parts apart.
    seam_threshold: float = field(default=0.15, metadata=within(0, 1))
    #: With ``models``, a seam head and the classifier: a part of uncertain type is fitted as each likely type.
    type_check: TypeCheckConfig = field(default_factory=TypeCheckConfig)
    #: Once the poses are fitted, the masks' outlines are snapped to the colour image's edges.
    guided: GuidedConfig = field(default_factory=GuidedConfig)
    #: Depth points per object for the pose net; unset: 250 with ``models``, else as in the net's training.
    pose_points: int | None = field(default=None, metadata=within(1, 100000))
    #: Side (px) of the pose net's colour crop, a multiple of 8; unset: 48 with ``models``, else as in the net's
    #: training.
    pose_crop: int | None = field(default=None, metadata=within(8, 1024))

    def __post_init__(self) -> None:
        if self.pose_crop is not None and self.pose_crop % 8:
            raise ConfigError(f"pose_crop = {self.pose_crop}: use a multiple of 8 px")


@dataclass
class Detection:
    """One estimated object: BOP id, pose T_cam_obj (4x4, m, OpenCV camera frame), score in [0, 1]
    (mean segmentation probability over the mask x the pose confidence) and mask (H, W) bool."""

    obj_id: int
    T_cam_obj: np.ndarray
    score: float
    mask: np.ndarray


@dataclass
class EstimateResult:
    """What one ``Estimator`` call found in a frame: its detections, the class map (H, W) int64 (0 background, else
    obj_id) after every stage, and the seconds spent per stage (keys ``STAGES``, in that order)."""

    detections: list[Detection]
    labels: np.ndarray
    timings: dict[str, float]


class Estimator:
    """Segmentation + pose + refiner + depth fit from a run directory (``seg/``, ``pose/``, optionally ``refiner/``,
    ``cls/``), configured by ``EstimatorConfig``. ``est(rgb, depth, K)`` -> ``EstimateResult``; the estimator keeps no
    state between calls."""

    def __init__(self, weights: str | Path, cfg: EstimatorConfig | None = None):
        cfg = cfg or EstimatorConfig()
        weights = Path(weights)
        if not weights.is_dir():
            raise WeightsError(f"weights directory {weights} does not exist")
        if cfg.threads is not None:
            torch.set_num_threads(cfg.threads)
        self.segmenter = Segmenter.load(weights / "seg", cfg.int8)
        self.seg_cfg = self.segmenter.cfg
        self.pose, self.pose_cfg, _ = ckpt_mod.load_model(weights / "pose", "pose")
        packed(for_inference(self.pose))
        self.refiner, self.refiner_cfg = None, None
        refiner_dir = ckpt_mod.stage_dir(weights, "refiner")
        if refiner_dir.exists():
            self.refiner, self.refiner_cfg, _ = ckpt_mod.load_model(refiner_dir, "refiner")
            if list(self.refiner_cfg.obj_ids) != list(self.pose_cfg.obj_ids) or \
                    self.refiner_cfg.emb_dim != self.pose_cfg.emb_dim:
                raise WeightsError(f"refiner in {refiner_dir} was trained for another pose net")
        self.classifier: ClassifierEnsemble | None = None
        if cfg.classify is not False and (weights / "cls").exists():
            self.classifier = ClassifierEnsemble.load(weights, cfg.int8)
        elif cfg.classify:
            raise WeightsError(f"{weights} has no cls/ checkpoint: train one with 'posegrasp train cls'")
        default_iters = self.refiner_cfg.iterations if self.refiner_cfg is not None else 0
        self.refiner_iterations = default_iters if cfg.refiner_iterations is None else cfg.refiner_iterations
        if self.refiner_iterations > 0 and self.refiner is None:
            raise WeightsError(f"{weights} has no refiner/ checkpoint: set refiner_iterations = 0")
        self.min_valid_points = cfg.min_valid_points
        points, crop = (DEPTH_FIT_POSE_INPUT if cfg.models is not None else
                        (self.pose_cfg.num_points, self.pose_cfg.crop_size))
        self.pose_points = points if cfg.pose_points is None else cfg.pose_points
        self.pose_crop = crop if cfg.pose_crop is None else cfg.pose_crop
        self.seed, self.depth_fit_cfg, self.seam_threshold = cfg.seed, cfg.depth_fit, cfg.seam_threshold
        self.support_plane, self.plane_cfg = cfg.support_plane, PlaneConfig()
        self.split_cfg, self.guided_cfg, self.type_check_cfg = cfg.split, cfg.guided, cfg.type_check
        self._meshes = self._read_models(cfg.models) if cfg.models is not None else {}

    @property
    def int8_nets(self) -> list[str]:
        """The nets that run in int8 (``perception.int8``) by their folders' names: "seg", "cls", "cls_<name>"."""
        nets = [("seg", self.segmenter.model)]
        if self.classifier is not None:
            nets += list(zip(self.classifier.names, self.classifier.models))
        return [name for name, m in nets if runs_int8(m)]

    def _read_models(self, models: str | Path) -> dict[int, tuple[object, Symmetries]]:
        """The mesh and symmetries of every object of the pose net, read and checked, from the BOP root ``models``."""
        infos = bop.load_models_info(models)
        missing = [o for o in self.obj_ids if o not in infos]
        if missing:
            raise DatasetError(f"models in {models} lack objects {missing} of the pose net")
        return {o: (bop_models.load_model(models, o), infos[o].symmetry_rotations()) for o in self.obj_ids}

    @functools.cached_property
    def objects(self) -> dict[int, ObjectModel]:
        """Each object's ``ObjectModel`` by obj_id (with its split surface when splitting is on; none without
        ``EstimatorConfig.models``), made on first use: a process that only checks the weights skips 0.3 s an object."""
        surface = self.split_cfg.model_points if self.split_cfg.rounds > 0 else 0
        return {o: ObjectModel.of_mesh(mesh, syms, self.depth_fit_cfg, seed=o, surface_points=surface)
                for o, (mesh, syms) in self._meshes.items()}

    @property
    def obj_ids(self) -> list[int]:
        """BOP ids of the objects the pose net knows."""
        return list(self.pose_cfg.obj_ids)

    def segment(self, rgb: np.ndarray) -> tuple[np.ndarray, ClassProbabilities]:
        """Class map and class probabilities of an RGB image (see ``Segmenter``)."""
        return self.segmenter(rgb)

    @with_one_blas_thread
    def estimate(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, masks: list[tuple[int, np.ndarray]],
                 mask_scores: list[float] | None = None, plane: np.ndarray | None = None
                 ) -> tuple[list[Detection], dict[str, float]]:
        """Poses of objects given their masks (obj_id, bool (H, W)); skips objects the pose net does
        not know and masks with fewer than ``min_valid_points`` valid depth pixels. Each detection
        carries the very mask array it was given. plane: the supporting plane for the depth fit
        (fitted here when None and ``support_plane`` is on). Returns the detections and the seconds spent on
        stages ``pose``, ``refiner`` and ``depth_fit``."""
        _, dets, stages, _ = self._estimate(rgb, depth, K, masks, mask_scores, plane)
        return dets, stages

    @torch.no_grad()
    def _estimate(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, masks: list[tuple[int, np.ndarray]],
                  mask_scores: list[float] | None, plane: np.ndarray | None, rivals: Rivals | None = None
                  ) -> tuple[list[int], list[Detection], dict[str, float], list[float] | None]:
        """``estimate``, and first the index in ``masks`` of each detection's mask, last each detection's depth fit
        score (m; None without the depth fit). ``rivals`` (of ``masks``: one mask given as several types): the pose net
        runs once per mask, as its first type, and the depth fit drops the trailing types (score inf)."""
        t0 = time.perf_counter()
        if plane is None and self.support_plane and self.objects and masks:  # the plane the masks' objects rest on
            plane = fit_support_plane(depth, K, self.seed, self.plane_cfg, np.any([m for _, m in masks], axis=0))
        rng = np.random.default_rng(self.seed)
        cfg = self.pose_cfg
        items, kept, preps = [], [], {}  # preps: by mask, for a mask given as several types
        for k, (obj_id, mask) in enumerate(masks):
            box = padded_box(mask, 0)
            if obj_id not in cfg.obj_ids or box is None or \
                    int((mask[box] & (depth[box] > 0)).sum()) < self.min_valid_points:
                continue
            if id(mask) not in preps:
                preps[id(mask)] = prepare_pose_input(rgb, depth, K, mask, self.pose_points, self.pose_crop, rng)
            prep = preps[id(mask)]
            if prep is None:
                continue
            items.append(prep)
            kept.append(k)
        if not items:
            return [], [], {"pose": time.perf_counter() - t0, "refiner": 0.0, "depth_fit": 0.0}, None
        # rivals (one mask given as several types: one prep) go through the pose net once, as the first of their types
        run, rows = distinct(items) if rivals else (list(range(len(items))),) * 2
        img = torch.from_numpy(np.stack([items[j][0] for j in run]))  # (B, 3, S, S)
        choose = torch.from_numpy(np.stack([items[j][1] for j in run]))  # (B, N)
        points = torch.from_numpy(np.stack([items[j][2] for j in run]))  # (B, N, 3)
        obj = torch.tensor([cfg.index_of(masks[kept[j]][0]) for j in run])  # (B,)
        q, t, conf, best, emb = self.pose.predict(img, points, choose, obj)
        T = make_transform(quat_to_rotmat(q), points[torch.arange(len(run)), best] + t)  # (B, 4, 4)
        t1 = t2 = time.perf_counter()
        if self.refiner_iterations > 0 and self.refiner is not None:
            T = refine(self.refiner, T, points, emb, obj, self.refiner_iterations)
            t2 = time.perf_counter()
        T, conf = T[rows], conf[rows]  # (len(kept), 4, 4), (len(kept),)
        poses, fit = list(T.double().numpy()), None  # (rows of one new array)
        if self.objects:
            poses, fit = self._depth_fit(poses, [masks[k] for k in kept], depth, K, rng, plane,
                                         None if rivals is None else rivals.take(kept))
        out = [Detection(obj_id=int(masks[k][0]), T_cam_obj=T_j, mask=masks[k][1],
                         score=float((1.0 if mask_scores is None else mask_scores[k]) * float(conf[j])))
               for j, (k, T_j) in enumerate(zip(kept, poses))]
        return kept, out, {"pose": t1 - t0, "refiner": t2 - t1, "depth_fit": time.perf_counter() - t2}, fit

    def _depth_fit(self, poses: list[np.ndarray], masks: list[tuple[int, np.ndarray]], depth: np.ndarray,
                   K: np.ndarray, rng: np.random.Generator, plane: np.ndarray | None, rivals: Rivals | None = None
                   ) -> tuple[list[np.ndarray], list[float]]:
        """``perception.depth_fit.fit_poses`` of the estimates (4x4 each) on (up to ``depth_fit.fit.max_points`` of)
        their masks' valid depth points (obj_id, (H, W) bool each): the fitted poses and their scores (m)."""
        max_points = self.depth_fit_cfg.fit.max_points
        seen: dict[int, np.ndarray] = {}  # one mask given as several types: one set of points, one part
        for _, m in masks:  # (each mask has valid depth: ``estimate`` keeps no other)
            if id(m) in seen:
                continue
            r0, r1, c0, c1 = box = mask_bbox(m)
            idx = np.flatnonzero(m[r0:r1, c0:c1] & (depth[r0:r1, c0:c1] > 0))  # raster order, as in the image
            if idx.size > max_points:
                idx = idx[np.sort(rng.choice(idx.size, max_points, replace=False))]
            seen[id(m)] = backproject(depth, K, box, idx)
        observed = [seen[id(m)] for _, m in masks]
        models = [self.objects[o] for o, _ in masks]
        fitted = fit_poses(poses, models, observed, depth, K, self.depth_fit_cfg, plane, rivals)
        return [T for T, _ in fitted], [s for _, s in fitted]

    @with_one_blas_thread
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
                b = padded_box(m, 0)  # the segment's box: its pixels set there, not looked for in the whole map
                new[b][m[b]], conf[b][m[b]] = c
        return new, conf

    def _classify_parts(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, parts: list[tuple[int, np.ndarray]],
                        labels: np.ndarray, plane: np.ndarray | None
                        ) -> tuple[list[tuple[int, np.ndarray]], np.ndarray, np.ndarray, list[list[tuple[int, float]]]]:
        """``classify`` for parts (class, mask (H, W) bool) already cut apart: each re-typed by the instance
        classifier (a part it calls "not a block" dropped; one without a crop keeps its type at confidence 0).
        Returns the parts, the class map (H, W) with their new types, the per-pixel confidence (H, W) float32 and
        each part's candidate types (obj_id, probability) for the type check, its type first."""
        labels, conf, out, cands = labels.copy(), np.zeros(labels.shape, dtype=np.float32), [], []
        ids, plane = list(self.classifier.cfg.obj_ids), self._cls_plane(depth, K, plane)
        for (c, m), prob in zip(parts, self.classifier.probabilities(rgb, depth, K, [m for _, m in parts], plane)):
            typed = [(c, 0.0)] if prob is None else candidates(prob, ids, self.type_check_cfg)
            if prob is not None:
                c = typed[0][0]
                labels[m], conf[m] = typed[0]
            if c:
                out.append((c, m))
                cands.append(typed)
        return out, labels, conf, cands

    def _classify_masks(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, masks: list[np.ndarray],
                        plane: np.ndarray | None) -> list[tuple[int, float] | None]:
        """The ensemble's (obj_id, probability) of each mask; plane: for the height channel (fitted here when None)."""
        return self.classifier(rgb, depth, K, masks, self._cls_plane(depth, K, plane))

    def _cls_plane(self, depth: np.ndarray, K: np.ndarray, plane: np.ndarray | None) -> np.ndarray | None:
        """The plane for a classifier with the height channel: ``plane``, or fitted here when None."""
        fit = self.classifier.cfg.height_range > 0 and plane is None
        return fit_support_plane(depth, K, self.seed, self.plane_cfg) if fit else plane

    @with_one_blas_thread
    def __call__(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray) -> EstimateResult:
        """Detect and estimate every known object in an RGB-D frame (depth in metres, 0 = invalid)."""
        rgb, depth, K = check_frame(rgb, depth, K)
        t0 = time.perf_counter()
        labels, prob, seams = self.segmenter.run(rgb)
        plane = None
        if self.support_plane:  # segmented pixels lying on the table become background
            labels, plane = clear_plane(labels, depth, K, self.seed, self.plane_cfg)
        t1 = time.perf_counter()
        conf, t_cls, cands = None, 0.0, None
        if seams is not None:  # parts cut apart along the seams, then typed one by one
            parts = seam_components(labels, seams > self.seam_threshold, self.min_valid_points)
            if self.classifier is not None:
                parts, labels, conf, cands = self._classify_parts(rgb, depth, K, parts, labels, plane)
        else:
            if self.classifier is not None:
                labels, conf = self.classify(rgb, depth, K, labels, plane)
            parts = segment_components(labels, self.min_valid_points)
        if self.classifier is not None:
            t_cls = time.perf_counter() - t1
        timings = {"seg": time.perf_counter() - t0 - t_cls, "cls": t_cls}
        if cands is not None and self.objects and any(len(c) > 1 for c in cands):
            dets, stages, labels = self.check_types(rgb, depth, K, parts, cands, prob, plane, labels)
        else:
            masks, scores = [], []
            for obj_id, m in parts:
                if obj_id not in self.obj_ids or obj_id >= prob.shape[-1]:
                    continue
                masks.append((obj_id, m))
                # foreground probability x the classifier's confidence, or the seg net's class probability
                s = (1.0 - prob.at(m, 0)) * conf[m] if conf is not None else prob.at(m, obj_id)
                scores.append(float(s.mean()))
            dets, stages = self.estimate(rgb, depth, K, masks, scores, plane)
        t4 = time.perf_counter()
        if self.objects and self.split_cfg.rounds > 0:
            dets, labels = self.split_merged(rgb, depth, K, dets, prob, plane, labels)
            dets = self.drop_duplicates(dets)
        t5, t_guided = time.perf_counter(), 0.0
        if self.guided_cfg.radius > 0:
            dets, labels = self.snap_outlines(rgb, labels, dets)
            t_guided = time.perf_counter() - t5
        timings.update(guided=t_guided, **stages, split=t5 - t4)
        return EstimateResult(dets, labels, timings)

    @with_one_blas_thread
    def snap_outlines(self, rgb: np.ndarray, labels: np.ndarray, dets: list[Detection]
                      ) -> tuple[list[Detection], np.ndarray]:
        """``perception.guided``: the class map ``labels`` (H, W) with its outlines snapped to the colour edges, and
        each detection's mask likewise: the pixels of its type in the snapped map within the filter's radius of
        its mask; a pixel that several such masks reach stays with those that held it. The poses are the ones
        fitted to the masks before (outlines shifted a few pixels onto a neighbour hurt the fits more than they
        help). Returns the detections with their new masks and the new class map."""
        r = self.guided_cfg.radius
        labels = snap_labels(labels, rgb, self.guided_cfg)
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
        return out, labels

    def check_types(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, parts: list[tuple[int, np.ndarray]],
                    cands: list[list[tuple[int, float]]], prob: ClassProbabilities, plane: np.ndarray | None,
                    labels: np.ndarray) -> tuple[list[Detection], dict[str, float], np.ndarray]:
        """``perception.type_check``: each part (obj_id, mask (H, W) bool) estimated and fitted as each of its
        candidate types (obj_id, classifier probability) in one batch, and kept as the best. Returns the detections,
        the seconds per stage (as ``estimate``) and the class map (H, W) with the parts' chosen types (a copy)."""
        masks, scores, owner, probs = [], [], [], []
        for i, ((_, m), typed) in enumerate(zip(parts, cands)):
            fg = 1.0 - prob.at(m, 0)
            for obj_id, p in typed:
                if obj_id in self.obj_ids and obj_id < prob.shape[-1]:
                    masks.append((obj_id, m))
                    scores.append(float((fg * np.float32(p)).mean()))
                    owner.append(i)
                    probs.append(p)
        cfg = self.type_check_cfg
        rivals = Rivals(owner, [cost(p, cfg) for p in probs], cfg.steps_margin, cfg.turns_margin)
        kept, fitted, stages, fit = self._estimate(rgb, depth, K, masks, scores, plane, rivals)
        best = best_per_part([owner[k] for k in kept], fit or [], [probs[k] for k in kept], cfg)
        dets, labels = [fitted[j] for j in best], labels.copy()
        for d in dets:
            labels[d.mask] = d.obj_id
        return dets, stages, labels

    @with_one_blas_thread
    def split_merged(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, dets: list[Detection],
                     prob: ClassProbabilities, plane: np.ndarray | None, labels: np.ndarray
                     ) -> tuple[list[Detection], np.ndarray]:
        """``perception.split``: each detection whose fitted model leaves a large part of its mask unexplained
        is fitted again to the rest, and each such part is typed (``_part_types``) and fitted as a detection of
        its own; ``split_cfg.rounds`` times. A split is undone when a part and the rest are fitted as the same block
        (``_same_block``): the part was a strip of it that the first fit missed. Returns the detections and the class
        map ``labels`` (H, W) with the split parts relabelled (a copy when any is; ``labels`` itself is kept)."""
        cfg = self.split_cfg
        done: list[Detection] = []  # detections not to be tested again
        for _ in range(cfg.rounds):
            split: list[tuple[Detection, list[np.ndarray]]] = []
            for d in dets:
                explained = self.objects[d.obj_id].surface.explained(d.T_cam_obj, d.mask, depth, K, cfg.tol)
                ps = unexplained_parts(d.mask, explained, depth, cfg)
                if ps:
                    split.append((d, ps))
                else:
                    done.append(d)
            if not split:
                return done, labels
            all_types = iter(self._part_types(rgb, depth, K, [p for _, ps in split for p in ps], prob, plane))
            groups, masks, scores, todo = [], [], [], []
            for d, ps in split:
                rest = d.mask & ~np.any(ps, axis=0)
                types = [next(all_types) for _ in ps]
                groups.append((d, len(masks), ps, [o for o, _ in types]))  # the rest's mask at that index, then ps
                masks += [(d.obj_id, rest)] + [(o, p) for p, (o, _) in zip(ps, types)]
                scores += [d.score] + [float((1.0 - prob.at(p, 0)).mean()) * pc for p, (_, pc) in zip(ps, types)]
            kept, fits, _, _ = self._estimate(rgb, depth, K, masks, scores, plane)
            fitted = dict(zip(kept, fits))  # index in masks -> its detection
            labels = labels.copy()
            for d, i, ps, types in groups:
                new = [fitted[j] for j in range(i + 1, i + 1 + len(ps)) if j in fitted]
                first = [fitted[i]] if i in fitted else []
                if any(self._same_block(n, f) for n in new for f in first):
                    done.append(d)  # one block: keep the first fit, its mask whole
                    continue
                todo += new + first
                for p, o in zip(ps, types):
                    labels[p] = o
            dets = todo
        return done + dets, labels

    def drop_duplicates(self, dets: list[Detection]) -> list[Detection]:
        """``perception.split.drop_duplicates`` of ``dets`` (with the blocks' sides from the models)."""
        sides = {o: x.smallest_side for o, x in self.objects.items()}
        return drop_duplicates(dets, sides, self.split_cfg.duplicate) if self.objects else dets

    def _same_block(self, a: Detection, b: Detection) -> bool:
        """Whether two fitted detections are one block twice: the same type, at poses that place it alike
        (``perception.split.same_place`` within ``split_cfg.same_block``)."""
        tol = self.split_cfg.same_block
        return a.obj_id == b.obj_id and same_place(self.objects[a.obj_id].points, a.T_cam_obj,
                                                   self.objects[b.obj_id].surface, b.T_cam_obj, tol)

    def _part_types(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, parts: list[np.ndarray],
                    prob: ClassProbabilities, plane: np.ndarray | None) -> list[tuple[int, float]]:
        """(obj_id, probability) of each part (H, W) bool: the instance classifier's (0: not a block, so the part
        is not fitted and becomes background), else (no classifier, or no crop) the seg net's most probable
        object class (``prob``, (H, W, C)) over the part. All parts go through the classifier as one batch."""
        by_cls = ([None] * len(parts) if self.classifier is None else
                  self._classify_masks(rgb, depth, K, parts, plane))
        out = []
        for p, c in zip(parts, by_cls):
            if c is None:
                mean = prob.at(p)[:, 1:].mean(axis=0)  # (C - 1,) object classes
                c = (int(mean.argmax()) + 1, float(mean.max()))
            out.append(c)
        return out


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """Mask (h, w) bool dilated by a disc of radius r px (nothing beyond its border)."""
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(mask.view(np.uint8), disc, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0

