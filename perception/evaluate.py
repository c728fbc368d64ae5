"""Evaluation of a trained run on a BOP split, measured as the field does (ADD(-S), AUC, BOP 2019 AR).

Writes into ``out``: ``metrics.json`` (segmentation mPA / mIoU, per object and overall ADD, ADD-S,
AUC, < 2 cm accuracy, accuracy at 0.1 x diameter, time per stage, the ablation flags),
``per_object.csv``, ``instances.csv`` (one row per evaluated ground-truth instance),
``curves.png`` (accuracy against ADD(-S), rotation error up to the object's symmetries and translation
error thresholds), ``scores_bop19.json`` (BOP 2019 AR, AR_VSD, AR_MSSD, AR_MSPD overall and per object, on the
targets of ``test_targets_bop19.json``, or of the ground truth when the dataset has none: ``perception.bop19``; also
by visible-fraction bin, ``bop19.ar_by_visib`` in ``metrics.json``)
and a BOP results CSV ``<method>_<dataset>-<split>.csv``.

Ablations: ``refiner_iterations = 0`` evaluates without the refiner, ``depth_fit = false`` without the depth fit; a
pose net trained with
``use_pam = use_cam = use_gfem = false`` is the DenseFusion-like variant (its flags are reported);
``masks = "gt"`` isolates the pose stage by using ground-truth visible masks; ``classify = false``
evaluates without the instance classifier (the paper's pipeline).
"""

from __future__ import annotations

import csv
import io
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from posegrasp import bop
from posegrasp.bop import results as bop_results
from posegrasp.bop import models as bop_models
from posegrasp import io as pio
from posegrasp.config import settings, within
from posegrasp.errors import ConfigError
from posegrasp.lock import folder_lock
from posegrasp.outputs import Record
from posegrasp.perception import bop19 as B
from posegrasp.perception import metrics as M
from posegrasp.perception.data import label_map, load_records, part_map
from posegrasp.perception.depth_render import DepthRenderer
from posegrasp.perception.estimator import STAGES, Detection, Estimator, EstimatorConfig
from posegrasp.perception.guided import GuidedConfig
from posegrasp.perception.split import SplitConfig
from posegrasp.perception.type_check import TypeCheckConfig

RE_THRESHOLDS = np.linspace(0.0, 30.0, 61)  # degrees
TE_THRESHOLDS = np.linspace(0.0, 0.05, 51)  # metres
ADD_THRESHOLDS = np.linspace(0.0, 0.02, 41)  # metres
RE_SYM_GOAL = 15.0  # degrees: the rotation error (up to symmetry) the "re_sym_<15deg" accuracy counts below


#: ``EvalConfig.masks``' values.
MASKS = ("pred", "gt")


@settings
class EvalConfig:
    """How ``posegrasp eval`` runs the estimator on a BOP split and scores it."""

    #: Keys of settings files under their old names (``posegrasp.config``).
    RENAMED = {"icp": "depth_fit", "refine_iterations": "refiner_iterations"}

    #: BOP split to evaluate (`--split`).
    split: str = "test"
    #: `pred` (full pipeline) or `gt` (ground-truth visible masks: the pose stage alone; `--gt-masks`).
    masks: str = "pred"
    #: Refiner iterations: -1 as trained, 0 none (`--no-refiner`).
    refiner_iterations: int = field(default=-1, metadata=within(-1, 100))
    #: Re-label segments with the run's instance classifier when it has one (`--no-cls`).
    classify: bool = True
    #: Fit every estimate to the depth image with the dataset's models (`--no-depth-fit`).
    depth_fit: bool = True
    #: Use the frame's supporting plane (`--no-plane`).
    plane: bool = True
    #: Snap the class map's outlines to the colour edges (`--no-guided`).
    guided: bool = True
    #: Split off the parts of a mask its fitted model leaves unexplained; needs `depth_fit` (`--no-split`).
    split_merged: bool = True
    #: Fit a part of uncertain type as each likely type; needs `depth_fit` (`--no-type-check`).
    type_check: bool = True
    #: The seg net and classifiers in int8 where the run has their measured ranges (`--no-int8`: float).
    int8: bool = True
    #: Ground-truth instances less visible are not evaluated (BOP: 0.1).
    min_visib_fract: float = field(default=0.1, metadata=within(0, 1))
    #: Objects with fewer valid-depth pixels in their mask are skipped.
    min_valid_points: int = field(default=50, metadata=within(0, 10000000))
    #: Drop detections with fewer mask pixels (at 640x480); the trials' model provider uses 150.
    min_mask_px: int = field(default=0, metadata=within(0, 10000000))
    #: Surface points per model for ADD and ADD-S.
    model_points: int = field(default=1000, metadata=within(1, 1000000))
    #: Images evaluated; 0: all (`--max-images`).
    max_images: int = field(default=0, metadata=within(0, 1000000000))
    #: Method name in the results CSV's file name.
    method: str = "posegrasp"
    #: Torch CPU threads (`--threads`).
    threads: int = field(default=2, metadata=within(1, 256))
    #: Seed of the estimator's point sampling.
    seed: int = field(default=0, metadata=within(0, 9223372036854775807))

    def __post_init__(self) -> None:
        if self.masks not in MASKS:
            raise ConfigError(f"masks = {self.masks!r}: use 'pred' or 'gt'")

    def estimator(self, models: Path) -> EstimatorConfig:
        """The estimator's settings for these, with the dataset root ``models`` for the depth fit."""
        return EstimatorConfig(
            refiner_iterations=None if self.refiner_iterations < 0 else self.refiner_iterations,
            min_valid_points=self.min_valid_points, threads=self.threads, seed=self.seed, int8=self.int8,
            classify=None if self.classify else False, models=models if self.depth_fit else None,
            support_plane=self.plane, split=SplitConfig() if self.split_merged else SplitConfig(rounds=0),
            guided=GuidedConfig() if self.guided else GuidedConfig(radius=0),
            type_check=TypeCheckConfig() if self.type_check else TypeCheckConfig(weight=0.0))


def _summary(rows: list[dict[str, Any]], diameter: float | None) -> dict[str, float]:
    """Aggregate instance rows (distances inf when missed) into the reported numbers (percentages)."""
    n = len(rows)
    add = np.array([r["add"] for r in rows])
    adds = np.array([r["adds"] for r in rows])
    addss = np.array([r["add_or_adds"] for r in rows])
    det = np.array([r["detected"] for r in rows], dtype=bool)
    if diameter is not None:
        acc01 = M.accuracy_at_diameter(addss, diameter) * 100.0
    else:  # overall: each instance against its own object's diameter
        acc01 = float(np.mean([r["add_or_adds"] < 0.1 * r["diameter"] for r in rows]) * 100.0) if n else float("nan")
    fin = det & np.isfinite(adds)
    nan = float("nan")
    re_det = np.array([r["re_sym"] for r in rows if r["detected"]])
    return {
        "n": n,
        "detected": float(det.mean() * 100.0) if n else float("nan"),
        "ADD_AUC": M.ycb_auc(add),
        "ADD-S_AUC": M.ycb_auc(adds),
        "ADD(-S)_AUC": M.ycb_auc(addss),
        "ADD-S_<2cm": M.accuracy_below(adds, 0.02) * 100.0,
        "ADD(-S)_acc_0.1d": acc01,
        "mean_ADD": float(add[fin].mean()) if fin.any() else float("nan"),
        "mean_ADD-S": float(adds[fin].mean()) if fin.any() else float("nan"),
        "median_re_sym_deg": float(np.median([r["re_sym"] for r in rows if r["detected"]])) if fin.any() else nan,
        "median_te": float(np.median([r["te"] for r in rows if r["detected"]])) if fin.any() else nan,
        "re_sym_<15deg_of_detected": float(np.mean(re_det < RE_SYM_GOAL) * 100.0) if re_det.size else nan,
        "re_sym_<15deg": float(np.sum(re_det < RE_SYM_GOAL) / n * 100.0) if n else nan,
        "re_sym_AUC_30deg": M.ycb_auc(np.array([r["re_sym"] for r in rows]), max_threshold=30.0),
    }


def _curves_png(rows: list[dict[str, Any]], obj_ids: list[int]) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    groups = [(f"obj {o}", [r for r in rows if r["obj_id"] == o]) for o in obj_ids] + [("all", rows)]
    for name, rs in groups:
        if not rs:
            continue
        lw = 2.5 if name == "all" else 1.0
        re = [r["re_sym"] if r["detected"] else np.inf for r in rs]
        te = [r["te"] if r["detected"] else np.inf for r in rs]
        axes[0].plot(RE_THRESHOLDS, M.threshold_curve(re, RE_THRESHOLDS) * 100, lw=lw, label=name)
        axes[1].plot(TE_THRESHOLDS * 100, M.threshold_curve(te, TE_THRESHOLDS) * 100, lw=lw, label=name)
        addss = [r["add_or_adds"] for r in rs]
        axes[2].plot(ADD_THRESHOLDS * 100, M.threshold_curve(addss, ADD_THRESHOLDS) * 100, lw=lw, label=name)
    axes[0].set(xlabel="rotation error threshold (deg, up to symmetry)", ylabel="accuracy (%)", ylim=(0, 101),
                xlim=(0, 30))
    axes[1].set(xlabel="translation error threshold (cm)", ylabel="accuracy (%)", ylim=(0, 101), xlim=(0, 5))
    axes[2].set(xlabel="ADD(-S) threshold (cm)", ylabel="accuracy (%)", ylim=(0, 101), xlim=(0, 2))
    for a in axes:
        a.grid(alpha=0.3)
    axes[2].legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()


def _csv_bytes(rows: list[dict[str, Any]], columns: list[str]) -> bytes:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue().encode()


#: The record that makes a folder an eval's (of the network or of any method): ``eval`` writes only into its own.
EVAL_RECORD = (Record("metrics.json", ("data", "split", "bop19")),)


def evaluate(data: str | Path, weights: str | Path, out: str | Path, cfg: EvalConfig | None = None,
             progress: bool = True) -> dict[str, Any]:
    """Evaluate the run ``weights`` on split ``cfg.split`` of BOP dataset ``data``; write reports in
    ``out`` (locked meanwhile: ``posegrasp.lock``); return the metrics dict (also in ``out/metrics.json``)."""
    with folder_lock(out, owns=EVAL_RECORD):
        return _evaluate(Path(data), weights, Path(out), cfg, progress)


@dataclass
class _Tally:
    """What an evaluation gathers image by image: one row per ground-truth instance (``_match``), the BOP results,
    the BOP 2019 errors, the segmentation's confusion matrix (C, C) and the seconds per stage and image."""

    conf: np.ndarray
    times: dict[str, list[float]]
    rows: list[dict[str, Any]] = field(default_factory=list)
    results: list[bop_results.PoseResult] = field(default_factory=list)
    groups: list[B.ObjectErrors] = field(default_factory=list)
    #: Instance masks (predicted ones only): parts, parts matched, matched whatever the type, detections, matched.
    inst: np.ndarray = field(default_factory=lambda: np.zeros(5, dtype=np.int64))


#: What a method makes of one frame: its detections (each with ``obj_id``, ``T_cam_obj`` 4x4 in metres, camera frame,
#: and ``score``), the seconds of its stages and its class map (H, W) for the segmentation scores (None: it has none).
FrameResult = tuple[list[Any], dict[str, float], "np.ndarray | None"]
#: A pose estimation method as eval runs it: (record, rgb (H, W, 3) uint8, depth (H, W) m, K (3, 3), the
#: ground-truth masks [(obj_id, mask)] with ``masks = "gt"``, else []) -> ``FrameResult``.
FrameMethod = Callable[[bop.ImageRecord, np.ndarray, np.ndarray, np.ndarray, list], FrameResult]


@dataclass(frozen=True)
class Method:
    """What ``evaluate_method`` scores: the per-frame ``run``, the objects it knows, its stages' names (the keys of
    ``time_per_image_s`` besides ``total``), its segmentation classes (0: no class map) and the report's first keys
    (what was evaluated)."""

    run: FrameMethod
    obj_ids: list[int]
    stages: tuple[str, ...] = ()
    num_classes: int = 0
    head: dict[str, Any] = field(default_factory=dict)


def _tally(method: Method, data: Path, records: list[bop.ImageRecord], infos: dict[int, bop.ObjectInfo],
           obj_ids: list[int], cfg: EvalConfig, progress: bool) -> _Tally:
    """Run ``method`` on every image of ``records`` and score its detections of the objects ``obj_ids``."""
    from posegrasp.progress import track

    pts = {o: bop_models.sample_model_points(bop_models.load_model(data, o), cfg.model_points, seed=o) for o in obj_ids}
    bop19, targets = _bop19_setup(data, cfg.split, records, infos)
    nc = method.num_classes
    tally = _Tally(np.zeros((nc, nc), dtype=np.int64), {k: [] for k in (*method.stages, "total")})
    for rec in track(records, f"eval {cfg.split}", enabled=progress):
        rgb, depth, K = rec.load_rgb(), rec.load_depth(), rec.camera.K
        gts = [g for g in rec.instances if g.obj_id in obj_ids
               and (g.info is None or g.info.visib_fract >= cfg.min_visib_fract)]
        gt_masks = [(g.obj_id, rec.load_mask(g.gt_index)) for g in gts] if cfg.masks == "gt" else []
        t0 = time.perf_counter()
        dets, timings, labels = method.run(rec, rgb, depth, K, gt_masks)
        total = time.perf_counter() - t0
        if labels is not None:
            tally.conf += M.confusion_matrix(labels, label_map(rec, rgb.shape[:2]), nc)
        for k, v in timings.items():
            tally.times[k].append(v)
        tally.times["total"].append(total)
        tally.rows.extend(_match(rec, gts, dets, pts, infos, gt_masks))
        if not gt_masks and all(getattr(d, "mask", None) is not None for d in dets):
            _instances(tally, rec, gts, dets, rgb.shape[:2])
        tally.results.extend(bop_results.PoseResult(rec.scene_id, rec.im_id, d.obj_id, d.score, d.T_cam_obj, total)
                             for d in dets)
        tally.groups.extend(bop19.image(
            depth, K, [B.Truth(g.obj_id, g.T_cam_obj, g.info.visib_fract if g.info else 1.0) for g in rec.instances],
            [B.ScoredPose(d.obj_id, d.score, d.T_cam_obj) for d in dets], targets.get((rec.scene_id, rec.im_id), {})))
    return tally


def _instances(tally: _Tally, rec: bop.ImageRecord, gts: list[bop.GTInstance], dets: list[Any],
               shape: tuple[int, int]) -> None:
    """Score the detections' masks as instances against the visible parts (``metrics.mask_ious``): the parts ``gts``
    found (their rows' ``mask_iou``: the best IoU of any detection), the detections that are a part of any."""
    ious = M.mask_ious(part_map(rec, shape), len(rec.instances), [d.mask for d in dets])  # (D, all parts)
    same = np.array([[d.obj_id == g.obj_id for g in rec.instances] for d in dets], dtype=bool).reshape(ious.shape)
    cols = [g.gt_index for g in gts]
    found, _, found_any = M.instance_scores(ious[:, cols], same[:, cols])
    tally.inst += (len(gts), found, found_any, len(dets), M.instance_scores(ious, same)[1])
    best = ious[:, cols].max(axis=0) if len(dets) else np.zeros(len(gts))
    for row, iou in zip(tally.rows[len(tally.rows) - len(gts):], best):
        row["mask_iou"] = float(iou)


def _estimator_method(weights: str | Path, data: Path, cfg: EvalConfig) -> Method:
    """The network of the run ``weights`` as eval runs it (``cfg``: masks, ablations, ``min_mask_px``)."""
    est = Estimator(weights, cfg.estimator(data))

    def run(rec: bop.ImageRecord, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, gt_masks: list) -> FrameResult:
        if cfg.masks == "pred":
            res = est(rgb, depth, K)
            return [d for d in res.detections if _kept(d, cfg.min_mask_px)], res.timings, res.labels
        # no segmentation, classifier, split or guided stage with ground-truth masks
        dets, stages = est.estimate(rgb, depth, K, gt_masks)
        return dets, {**dict.fromkeys(STAGES, 0.0), **stages}, None

    pose_cfg = est.pose_cfg
    head = {"weights": str(weights),
            "ablation": {"pam": pose_cfg.use_pam, "cam": pose_cfg.use_cam, "gfem": pose_cfg.use_gfem,
                         "refiner_iterations": est.refiner_iterations, "masks": cfg.masks,
                         "classifier": est.classifier is not None and cfg.masks == "pred", "depth_fit": cfg.depth_fit,
                         "plane": cfg.plane, "guided": cfg.guided, "split_merged": cfg.split_merged and cfg.depth_fit,
                         "type_check": cfg.type_check and cfg.depth_fit, "int8": est.int8_nets}}
    return Method(run, list(est.obj_ids), STAGES, est.seg_cfg.num_classes, head)


def _evaluate(data: Path, weights: str | Path, out: Path, cfg: EvalConfig | None, progress: bool) -> dict[str, Any]:
    cfg = cfg or EvalConfig()
    return _score(Path(data), _estimator_method(weights, Path(data), cfg), Path(out), cfg, progress)


def evaluate_method(data: str | Path, method: Method, out: str | Path, cfg: EvalConfig | None = None,
                    progress: bool = True) -> dict[str, Any]:
    """``evaluate`` of any pose estimation ``method`` (``grasping.provider_eval`` scores a ``--perception``
    provider with it): the same metrics, tables and results CSV in ``out`` (locked meanwhile)."""
    with folder_lock(out, owns=EVAL_RECORD):
        return _score(Path(data), method, Path(out), cfg or EvalConfig(), progress)


def _score(data: Path, method: Method, out: Path, cfg: EvalConfig, progress: bool) -> dict[str, Any]:
    """Run ``method`` on the split, score it and write the reports (module doc) into ``out``."""
    infos = bop.load_models_info(data)
    obj_ids = [o for o in method.obj_ids if o in infos]
    records = load_records(data, cfg.split)
    if cfg.max_images:
        records = records[:cfg.max_images]
    tally = _tally(method, data, records, infos, obj_ids, cfg, progress)
    rows, nc = tally.rows, method.num_classes

    per_object = {o: _summary([r for r in rows if r["obj_id"] == o], infos[o].diameter) for o in obj_ids}
    overall = _summary(rows, None)
    head = dict(method.head)
    report: dict[str, Any] = {
        "data": str(data), "split": cfg.split, **{k: head.pop(k) for k in ("weights", "perception") if k in head},
        "images": len(records), "config": asdict(cfg), **head,
        "segmentation": None,
        "overall": overall,
        "mean_over_objects": {k: _nanmean([per_object[o][k] for o in obj_ids if per_object[o]["n"]])
                              for k in overall if k != "n"},
        "per_object": {str(o): per_object[o] for o in obj_ids},
        "time_per_image_s": {k: float(np.mean(v)) if v else 0.0 for k, v in tally.times.items()},
    }
    if nc and cfg.masks == "pred":
        s = M.segmentation_scores(tally.conf)
        report["segmentation"] = {"mPA": s["mPA"], "mIoU": s["mIoU"],
                                  "per_class": {str(c): {"PA": _f(s["pa"][c]), "IoU": _f(s["iou"][c])}
                                                for c in range(nc)}}
    parts, found, found_any, n_det, n_det_found = (int(x) for x in tally.inst)
    if parts:
        report["instances"] = {"iou_above": 0.5, "parts": parts, "detections": n_det,
                               "recall": 100.0 * found / parts, "recall_any_type": 100.0 * found_any / parts,
                               "precision": 100.0 * n_det_found / n_det if n_det else float("nan")}
    cols = ["obj_id", "n", "detected", "ADD_AUC", "ADD-S_AUC", "ADD(-S)_AUC", "ADD-S_<2cm", "ADD(-S)_acc_0.1d",
            "mean_ADD", "mean_ADD-S", "median_re_sym_deg", "median_te"]
    scores = B.scores(tally.groups, infos, bop.load_camera(data).width)
    report["bop19"] = {**{k: scores[k] for k in ("ar", "ar_vsd", "ar_mssd", "ar_mspd", "targets")},
                       "ar_by_visib": scores["by_visib"]}
    check_score_ranges(report, scores)
    write_all(out, {
        "per_object.csv": _csv_bytes([{"obj_id": o, **per_object[o]} for o in obj_ids] + [{"obj_id": "all", **overall}],
                                     cols),
        "instances.csv": _csv_bytes(rows, ["scene_id", "im_id", "gt_index", "obj_id", "symmetric", "visib_fract",
                                           "detected", "score", "add", "adds", "add_or_adds", "re", "re_sym", "te",
                                           "mask_iou"]),
        "curves.png": _curves_png(rows, obj_ids),
        "scores_bop19.json": (pio.dumps_json(pio.jsonable(scores, nan_to_null=True)) + "\n").encode(),
        f"{cfg.method}_{data.resolve().name}-{cfg.split}.csv": bop_results.results_csv(tally.results),
        "metrics.json": (pio.dumps_json(pio.jsonable(report, nan_to_null=True)) + "\n").encode()})
    return report


#: Keys of eval's reports holding fractions in [0, 1] and percentages in [0, 100] (NaN: nothing to score).
FRACTION_KEYS = frozenset({"ar", "ar_vsd", "ar_mssd", "ar_mspd"})
PERCENT_KEYS = frozenset({"detected", "ADD_AUC", "ADD-S_AUC", "ADD(-S)_AUC", "ADD-S_<2cm", "ADD(-S)_acc_0.1d",
                          "re_sym_<15deg_of_detected", "re_sym_<15deg", "re_sym_AUC_30deg", "mPA", "mIoU", "PA", "IoU",
                          "recall", "recall_any_type", "precision"})


def check_score_ranges(*reports: Any) -> None:
    """Raise RuntimeError (an internal error: no file is written) if a score in ``reports`` (nested dicts and lists)
    lies outside its range: ``FRACTION_KEYS`` in [0, 1], ``PERCENT_KEYS`` in [0, 100]."""
    def walk(x: Any, where: str) -> None:
        if isinstance(x, dict):
            for k, v in x.items():
                hi = 1.0 if k in FRACTION_KEYS else 100.0 if k in PERCENT_KEYS else None
                if hi is not None and isinstance(v, (int, float)) and not (np.isnan(v) or 0.0 <= v <= hi):
                    raise RuntimeError(f"internal error: score {where}{k} = {v} outside [0, {hi:g}]; nothing written")
                walk(v, f"{where}{k}.")
        elif isinstance(x, list):
            for i, v in enumerate(x):
                walk(v, f"{where}{i}.")
    for r in reports:
        walk(r, "")


def write_all(out: Path, files: dict[str, bytes]) -> None:
    """Write ``files`` (name -> bytes) into ``out`` all or none: each into a staging folder beside ``out`` (synced),
    then renamed into ``out``, ``metrics.json`` last. A failed write (a full disk) leaves ``out`` as it was."""
    import shutil
    import tempfile

    out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        for name, data in files.items():
            pio.write_bytes(stage / name, data)
        for name in sorted(files, key=lambda n: n == "metrics.json"):
            os.replace(stage / name, out / name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _bop19_setup(data: Path, split: str, records: list[bop.ImageRecord], infos: dict[int, bop.ObjectInfo]
                 ) -> tuple[B.Bop19, dict[tuple[int, int], dict[int, int]]]:
    """The BOP 2019 scorer on the dataset's ``models_eval/`` (else ``models/``) and the targets per image
    ({(scene_id, im_id): {obj_id: inst_count}}) of the evaluated images: ``test_targets_bop19.json`` for the
    test split when the dataset has it, else the instances at least 10 % visible."""
    meshes = {o: bop_models.load_model(bop.eval_model_path(data, o)) for o in infos}
    scorer = B.Bop19({o: np.asarray(m.vertices) for o, m in meshes.items()}, infos, DepthRenderer(meshes))
    listed = bop.load_test_targets(data) if split == "test" else None
    shown = {(r.scene_id, r.im_id) for r in records}
    targets: dict[tuple[int, int], dict[int, int]] = {}
    for t in bop.targets_from_gt(records) if listed is None else listed:
        if (t.scene_id, t.im_id) in shown and t.obj_id in infos:
            targets.setdefault((t.scene_id, t.im_id), {})[t.obj_id] = t.inst_count
    return scorer, targets


def _kept(d: Detection, min_mask_px: int) -> bool:
    """Is detection ``d``'s mask at least ``min_mask_px`` pixels at 640x480 (``grasping.perception.visible_enough``'s
    rule)?"""
    return int(d.mask.sum()) >= min_mask_px * d.mask.size / (640 * 480)


def _nanmean(v: list[float]) -> float:
    a = np.asarray(v, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else float("nan")


def _f(x: Any) -> Any:
    """JSON-safe float (nan -> None)."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    return None if not np.isfinite(x) else x


def _match(rec: bop.ImageRecord, gts: list[bop.GTInstance], dets: list[Detection], pts: dict[int, np.ndarray],
           infos: dict[int, bop.ObjectInfo], gt_masks: list[tuple[int, np.ndarray]]) -> list[dict[str, Any]]:
    """One row per ground-truth instance with its errors against its detection (inf if missed).

    With ground-truth masks (``gt_masks``, in ``gts`` order) a detection belongs to the instance
    whose mask it carries. Otherwise each detection, most confident first, goes to the unmatched
    instance of its object with the smallest ADD-S.
    """
    rows = []
    assigned: dict[int, Detection] = {}
    if gt_masks:
        for d in dets:
            for gi, (_, m) in enumerate(gt_masks):
                if d.mask is m:
                    assigned[gi] = d
    else:
        for d in sorted(dets, key=lambda d: -d.score):
            cands = [(M.adds(d.T_cam_obj[:3, :3], d.T_cam_obj[:3, 3], g.T_cam_obj[:3, :3], g.T_cam_obj[:3, 3],
                             pts[g.obj_id]), gi)
                     for gi, g in enumerate(gts) if g.obj_id == d.obj_id and gi not in assigned]
            if cands:
                assigned[min(cands)[1]] = d
    for gi, g in enumerate(gts):
        sym = infos[g.obj_id].symmetric
        row = {"scene_id": rec.scene_id, "im_id": rec.im_id, "gt_index": g.gt_index, "obj_id": g.obj_id,
               "symmetric": sym, "visib_fract": g.info.visib_fract if g.info else float("nan"),
               "diameter": infos[g.obj_id].diameter, "detected": gi in assigned, "score": 0.0,
               "add": np.inf, "adds": np.inf, "add_or_adds": np.inf, "re": np.inf, "re_sym": np.inf, "te": np.inf}
        if gi in assigned:
            d = assigned[gi]
            Re, te, Rg, tg = d.T_cam_obj[:3, :3], d.T_cam_obj[:3, 3], g.T_cam_obj[:3, :3], g.T_cam_obj[:3, 3]
            row.update(score=d.score, add=M.add(Re, te, Rg, tg, pts[g.obj_id]),
                       adds=M.adds(Re, te, Rg, tg, pts[g.obj_id]),
                       re=M.rotation_error_deg(Re, Rg), te=M.translation_error(te, tg),
                       re_sym=M.rotation_error_sym_deg(Re, Rg, infos[g.obj_id].symmetries_discrete,
                                                       [a for a, _ in infos[g.obj_id].symmetries_continuous]))
            row["add_or_adds"] = row["adds"] if sym else row["add"]
        rows.append(row)
    return rows
