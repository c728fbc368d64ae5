"""Pose and segmentation metrics, exactly as the field computes them.

ADD and ADD-S as Hinterstoisser et al. 2012 define them, the AUC of their accuracy curve as PoseCNN's (Xiang et al. 2018).

Poses are given as a rotation R (3, 3) and a translation t (3,) in metres, mapping model points
(object frame, metres) into the camera frame. Distances are in metres, angles in degrees.
Nearest neighbours are exact, from a k-d tree (``scipy.spatial.cKDTree``); nothing here imports torch, so the
grasp trials' workers score poses without loading it.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

ADDSDirection = Literal["gt_to_est", "est_to_gt"]


def _apply(R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Points (N, 3) in the object frame -> camera frame under (R, t)."""
    return np.asarray(pts, dtype=np.float64) @ np.asarray(R, dtype=np.float64).T + np.asarray(t, dtype=np.float64)


def nearest_distances(query: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """For each query point (Q, 3), the Euclidean distance to its nearest point in ref (M, 3)."""
    return cKDTree(np.asarray(ref, dtype=np.float64)).query(np.asarray(query, dtype=np.float64))[0]


def add(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray, pts: np.ndarray) -> float:
    """ADD: mean distance between model points under the estimate and under the ground truth (m)."""
    d = _apply(R_e, t_e, pts) - _apply(R_g, t_g, pts)
    return float(np.linalg.norm(d, axis=1).mean())


def adds(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray, pts: np.ndarray,
         direction: ADDSDirection = "gt_to_est") -> float:
    """ADD-S (m): mean over points of the distance to the nearest point of the other model copy.

    ``gt_to_est`` (default, BOP and YCB toolbox): each ground-truth-transformed point queries the
    estimate-transformed points. ``est_to_gt``: the other way (DenseFusion's LineMOD evaluation).
    """
    pe, pg = _apply(R_e, t_e, pts), _apply(R_g, t_g, pts)
    if direction == "gt_to_est":
        return float(nearest_distances(pg, pe).mean())
    if direction == "est_to_gt":
        return float(nearest_distances(pe, pg).mean())
    raise ValueError(f"unknown ADD-S direction {direction!r}")


def rotation_error_deg(R_e: np.ndarray, R_g: np.ndarray) -> float:
    """re = arccos(clip((trace(R_e R_g^T) - 1) / 2, -1, 1)) in degrees."""
    c = (np.trace(np.asarray(R_e) @ np.asarray(R_g).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def rotation_error_sym_deg(R_e: np.ndarray, R_g: np.ndarray, discrete: list[np.ndarray] | None = None,
                           continuous_axes: list[np.ndarray] | None = None) -> float:
    """Rotation error (deg) up to the object's symmetries: the smallest error of R_e S over the
    discrete symmetries S (4x4 or 3x3, identity included); with a continuous symmetry axis a, the
    rotation about a is free and the error is the angle between R_e S a and R_g a."""
    Ss = [np.eye(3)] + [np.asarray(S)[:3, :3] for S in (discrete or [])]
    if continuous_axes:
        a = np.asarray(continuous_axes[0], dtype=np.float64)
        a = a / np.linalg.norm(a)
        g = np.asarray(R_g) @ a
        return float(min(np.degrees(np.arccos(np.clip(np.dot(np.asarray(R_e) @ S @ a, g), -1.0, 1.0))) for S in Ss))
    return float(min(rotation_error_deg(np.asarray(R_e) @ S, R_g) for S in Ss))


def translation_error(t_e: np.ndarray, t_g: np.ndarray) -> float:
    """te = ||t_e - t_g|| (m)."""
    return float(np.linalg.norm(np.asarray(t_e, dtype=np.float64) - np.asarray(t_g, dtype=np.float64)))


def ycb_auc(distances: np.ndarray | list[float], max_threshold: float = 0.1) -> float:
    """Area under the accuracy-threshold curve up to ``max_threshold`` (m), as a percentage.

    The YCB-Video toolbox rule (VOCap): distances above the threshold count as failures (inf),
    accuracy at the k-th sorted finite distance is k / n over all n, the curve is closed at
    ``max_threshold`` with the last accuracy (right endpoint), made monotone, and integrated.
    """
    d = np.asarray(distances, dtype=np.float64).copy()
    n = d.size
    if n == 0:
        return float("nan")
    d[d > max_threshold] = np.inf
    d = np.sort(d)
    acc = np.arange(1, n + 1, dtype=np.float64) / n
    finite = np.isfinite(d)
    d, acc = d[finite], acc[finite]
    if d.size == 0:
        return 0.0
    mrec = np.concatenate([[0.0], d, [max_threshold]])
    mpre = np.concatenate([[0.0], acc, [acc[-1]]])
    mpre = np.maximum.accumulate(mpre)
    i = np.nonzero(mrec[1:] != mrec[:-1])[0] + 1
    return float(np.sum((mrec[i] - mrec[i - 1]) * mpre[i]) / max_threshold * 100.0)


def accuracy_below(distances: np.ndarray | list[float], threshold: float = 0.02) -> float:
    """Fraction of distances strictly below ``threshold`` (m): the "< 2 cm" accuracy, in [0, 1]."""
    d = np.asarray(distances, dtype=np.float64)
    return float(np.mean(d < threshold)) if d.size else float("nan")


def accuracy_at_diameter(distances: np.ndarray | list[float], diameter: float, fraction: float = 0.1) -> float:
    """LineMOD accuracy: fraction of distances strictly below ``fraction * diameter`` (m), in [0, 1]."""
    return accuracy_below(distances, fraction * diameter)


def threshold_curve(errors: np.ndarray | list[float], thresholds: np.ndarray) -> np.ndarray:
    """Accuracy (fraction of errors <= each threshold) for an accuracy-vs-threshold plot."""
    e = np.asarray(errors, dtype=np.float64)
    if e.size == 0:
        return np.full(len(thresholds), np.nan)
    return (e[None, :] <= np.asarray(thresholds, dtype=np.float64)[:, None]).mean(axis=1)


def confusion_matrix(pred: np.ndarray, label: np.ndarray, num_classes: int) -> np.ndarray:
    """(num_classes, num_classes) int64 counts, rows = label class, columns = predicted class."""
    p = np.asarray(pred, dtype=np.int64).ravel()
    g = np.asarray(label, dtype=np.int64).ravel()
    keep = (g >= 0) & (g < num_classes) & (p >= 0) & (p < num_classes)
    return np.bincount(g[keep] * num_classes + p[keep], minlength=num_classes ** 2).reshape(num_classes, num_classes)


def segmentation_scores(conf: np.ndarray) -> dict[str, object]:
    """Per-class pixel accuracy and IoU from a confusion matrix, and their means (percentages).

    PA_c = correct_c / label pixels of c; IoU_c = |pred AND label| / |pred OR label|. Classes
    absent from the labels have no PA (nan) and are left out of mPA; a class in neither prediction
    nor label has no IoU and is left out of mIoU (a class only predicted counts with IoU 0).
    """
    conf = np.asarray(conf, dtype=np.float64)
    tp = np.diag(conf)
    label_tot = conf.sum(axis=1)
    pred_tot = conf.sum(axis=0)
    union = label_tot + pred_tot - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        pa = np.where(label_tot > 0, tp / label_tot, np.nan)
        iou = np.where(union > 0, tp / union, np.nan)
    present = label_tot > 0
    return {
        "pa": pa * 100.0,
        "iou": iou * 100.0,
        "mPA": float(np.nanmean(pa[present]) * 100.0) if present.any() else float("nan"),
        "mIoU": float(np.nanmean(iou) * 100.0) if (union > 0).any() else float("nan"),
    }


def mask_ious(parts: np.ndarray, n_parts: int, masks: list[np.ndarray]) -> np.ndarray:
    """(len(masks), n_parts) IoU of each predicted instance mask (H, W) bool with each ground-truth part of ``parts``
    (H, W) int (0 none, k the k-th part's visible pixels): |m AND p_k| / |m OR p_k|.

    Visible parts do not overlap, so a mask has IoU > 0.5 with at most one part: at that threshold every match is
    one to one, as in COCO's and the panoptic quality's instance matching.
    """
    sizes = np.bincount(parts.ravel(), minlength=n_parts + 1)[1:].astype(np.float64)
    out = np.zeros((len(masks), n_parts))
    for i, m in enumerate(masks):
        inter = np.bincount(parts[m], minlength=n_parts + 1)[1:].astype(np.float64)
        union = sizes + float(m.sum()) - inter
        out[i] = np.divide(inter, union, out=np.zeros(n_parts), where=union > 0)
    return out


def instance_scores(ious: np.ndarray, same_type: np.ndarray, threshold: float = 0.5) -> tuple[int, int, int]:
    """(ground-truth parts matched, predictions matched, parts matched whatever the type) at IoU > ``threshold``
    (>= 0.5), from ``mask_ious``'s (P, G) matrix and (P, G) bool ``same_type`` (prediction's type is the part's)."""
    hit = ious > threshold
    typed = hit & same_type
    return int(typed.any(axis=0).sum()), int(typed.any(axis=1).sum()), int(hit.any(axis=0).sum())
