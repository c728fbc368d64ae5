"""BOP 2019 pose metrics: VSD, MSSD, MSPD and their average recall AR, as bop_toolkit defines them (Hodan et al. 2020).

Units: metres for poses, model points, depth and distances (bop_toolkit works in mm: every threshold here is
the same fraction of the object's diameter, or the same 15 mm), pixels for MSPD. Poses are 4x4 ``T_cam_obj``
(OpenCV camera). With S the object's symmetries (``symmetry_transforms``) and x its evaluation points:

- MSSD = min_S max_x ||T_e x - T_g S x||; correct below theta x diameter, theta in 0.05 ... 0.50.
- MSPD = min_S max_x ||proj(T_e x) - proj(T_g S x)|| px; correct below k x width / 640, k in 5 ... 50.
- VSD (delta 15 mm, step cost, "bop19" visibility): on the distance images (along the ray) of the model rendered
  at the estimate and at the ground truth and of the test image, V_gt = (d_gt > 0) & ((d_gt - d_test <= delta) |
  (d_test == 0)), V_est the same for d_est OR'ed with V_gt & (d_est > 0); e = (|U| - |I| + #{I: |d_gt - d_est| >=
  tau}) / |U| (1 if U is empty), tau in 0.05 ... 0.50 x diameter; correct below theta in 0.05 ... 0.50.

Per image and object with a target (``inst_count`` instances), the ``inst_count`` best-scored estimates are
matched greedily, in decreasing score order, each to the unmatched valid instance (the ``inst_count`` most
visible) with the lowest error below the threshold. Recall = matched / targets; AR_VSD, AR_MSSD, AR_MSPD are the
mean recalls over their thresholds (10 x 10, 10, 10) and AR their mean. The same scores by visible-fraction bin
(``VISIB_BINS``) count the valid instances in the bin as its targets and the matches of those.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, NamedTuple

import numpy as np

from posegrasp.bop import ObjectInfo
from posegrasp.geometry import axis_angle_R

VSD_DELTA = 0.015  #: m
VSD_TAUS = np.arange(0.05, 0.51, 0.05)  #: x diameter
THETAS = np.arange(0.05, 0.51, 0.05)  #: VSD error thresholds; MSSD thresholds x diameter
MSPD_PX = np.arange(5, 51, 5)  #: px x image width / 640
MAX_SYM_STEP = 0.01  #: a continuous symmetry's step moves the farthest vertex at most this x diameter
#: Visible-fraction bins [lo, hi) AR is also reported by (the last one closed at 1.0).
VISIB_BINS = ((0.1, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 0.9), (0.9, 1.0))
_CHUNK = 64  # symmetries per batch (memory: chunk x points x 3 doubles)


def symmetry_transforms(info: ObjectInfo, max_step: float = MAX_SYM_STEP) -> np.ndarray:
    """(S, 4, 4) symmetry transforms (m) of an object, identity first: each continuous symmetry discretised in
    ceil(pi / max_step) steps about its axis through its offset, composed as C @ D with every discrete one D
    (identity included). bop_toolkit's ``get_symmetry_transformations``, except that its continuous steps
    start at the first step, leaving the identity out for objects with a continuous symmetry (a perfect
    estimate of a cylinder then scores up to 1 % of its diameter)."""
    disc = [np.eye(4)] + [np.asarray(D, dtype=np.float64) for D in info.symmetries_discrete]
    cont = [np.eye(4)]
    for axis, offset in info.symmetries_continuous:
        n = int(np.ceil(np.pi / max_step))
        for i in range(1, n):
            C = np.eye(4)
            C[:3, :3] = axis_angle_R(axis, i * 2.0 * np.pi / n)
            C[:3, 3] = offset - C[:3, :3] @ offset
            cont.append(C)
    return np.array([C @ D for D in disc for C in cont])


def _transformed(points: np.ndarray, T: np.ndarray, syms: np.ndarray) -> Iterator[np.ndarray]:
    """The points (N, 3) under T @ S for the symmetries S (S, 4, 4), a few symmetries (chunk, N, 3) at a time."""
    for s in range(0, len(syms), _CHUNK):
        TS = T @ syms[s:s + _CHUNK]
        yield points @ TS[:, :3, :3].transpose(0, 2, 1) + TS[:, None, :3, 3]


def mssd(T_e: np.ndarray, T_g: np.ndarray, points: np.ndarray, syms: np.ndarray) -> float:
    """Maximum symmetry-aware surface distance (m) over the points (N, 3) and symmetries (S, 4, 4).

    ||T_e x - T_g S x|| = ||R_g^T (T_e x - t_g) - S x||, so the symmetric points stay in the object frame. It is a
    convex function of x: its maximum is reached at a vertex of the points' convex hull (pass those: same value)."""
    y = (points @ T_e[:3, :3].T + T_e[:3, 3] - T_g[:3, 3]) @ T_g[:3, :3]
    best = np.inf
    for sx in _transformed(points, np.eye(4), syms):
        d = y - sx
        best = min(best, float(np.einsum("snk,snk->sn", d, d).max(axis=1).min()))
    return float(np.sqrt(best))


def mspd(T_e: np.ndarray, T_g: np.ndarray, points: np.ndarray, syms: np.ndarray, K: np.ndarray) -> float:
    """Maximum symmetry-aware projection distance (px) through intrinsics K (OpenCV camera)."""
    # pixel differences: (fx x, fy y) / z differences, the principal point cancelling out
    F = np.diag([K[0, 0], K[1, 1], 1.0, 1.0])
    pe = points @ (F @ T_e)[:3, :3].T + (F @ T_e)[:3, 3]
    pe = pe[:, :2] / pe[:, 2:]
    best = np.inf
    for pg in _transformed(points, F @ T_g, syms):
        d = pe - pg[..., :2] / pg[..., 2:]
        best = min(best, float(np.einsum("snk,snk->sn", d, d).max(axis=1).min()))
    return float(np.sqrt(best))


def ray_factor(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) distance along the ray per unit depth: sqrt(((u - cx) / fx)^2 + ((v - cy) / fy)^2 + 1)."""
    u = (np.arange(width) - K[0, 2]) / K[0, 0]
    v = (np.arange(height) - K[1, 2]) / K[1, 1]
    return np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0).astype(np.float32)


def vsd(dist_est: np.ndarray, dist_gt: np.ndarray, dist_test: np.ndarray, diameter: float,
        delta: float = VSD_DELTA, taus: np.ndarray = VSD_TAUS) -> np.ndarray:
    """VSD errors (one per tau x diameter) from distance images (m along the ray, 0 = none) of the model at the
    estimate and at the ground truth and of the test image (step cost, "bop19" visibility)."""
    rows = np.flatnonzero((dist_est > 0).any(axis=1) | (dist_gt > 0).any(axis=1))
    cols = np.flatnonzero((dist_est > 0).any(axis=0) | (dist_gt > 0).any(axis=0))
    if not len(rows):
        return np.ones(len(taus))
    sl = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    d_est, d_gt, d_test = dist_est[sl], dist_gt[sl], dist_test[sl]
    no_test = d_test == 0
    v_gt = (d_gt > 0) & ((d_gt - d_test <= delta) | no_test)
    v_est = ((d_est > 0) & ((d_est - d_test <= delta) | no_test)) | (v_gt & (d_est > 0))
    inter = v_gt & v_est
    n_union, n_inter = int(np.count_nonzero(v_gt | v_est)), int(np.count_nonzero(inter))
    if n_union == 0:
        return np.ones(len(taus))
    d = np.abs(d_gt[inter] - d_est[inter]) / diameter
    costs = (d[None, :] >= np.asarray(taus)[:, None]).sum(axis=1)
    return (costs + n_union - n_inter) / n_union


# ------------------------------------------------------------------------------------------------- per image

class ScoredPose(NamedTuple):
    """A pose estimate: object id, score, ``T_cam_obj`` (4x4, m)."""

    obj_id: int
    score: float
    T_cam_obj: np.ndarray


class Truth(NamedTuple):
    """A ground-truth instance: object id, ``T_cam_obj`` (4x4, m), visible fraction."""

    obj_id: int
    T_cam_obj: np.ndarray
    visib_fract: float


@dataclass
class ObjectErrors:
    """One image's errors for one object with targets: its ``targets`` (inst_count), which of its ground-truth
    instances are valid (the ``targets`` most visible), and the errors of its best-scored estimates (at most
    ``targets``, best first) against each instance: MSSD (E, G) m, MSPD (E, G) px, VSD (E, G, taus); ``visib``
    (G,): the instances' visible fractions (unset: 1)."""

    obj_id: int
    targets: int
    valid: np.ndarray
    mssd: np.ndarray
    mspd: np.ndarray
    vsd: np.ndarray
    visib: np.ndarray | None = None

    def in_bin(self, lo: float, hi: float) -> np.ndarray:
        """Bool (G,): the instances whose visible fraction lies in [lo, hi) ([lo, hi] when hi >= 1)."""
        v = np.ones(self.valid.shape) if self.visib is None else np.asarray(self.visib)
        return (v >= lo) & ((v < hi) | (hi >= 1.0))


class Bop19:
    """The BOP 2019 errors of a frame's estimates. ``points``: {obj_id: evaluation points (N, 3) m};
    ``infos``: the objects' diameters and symmetries; ``renderer(obj_id, T_cam_obj, K, height, width)`` -> depth
    (m) of the model alone (``perception.depth_render``)."""

    def __init__(self, points: dict[int, np.ndarray], infos: dict[int, ObjectInfo], renderer):
        self.infos, self.render = infos, renderer
        self.points = {o: np.asarray(p, np.float64) for o, p in points.items()}
        self.hull = {o: p[_hull_vertices(p)] for o, p in self.points.items()}  # enough for MSSD
        self.syms = {o: symmetry_transforms(infos[o]) for o in points}

    def image(self, depth: np.ndarray, K: np.ndarray, truths: list[Truth], estimates: list[ScoredPose],
              targets: dict[int, int]) -> list[ObjectErrors]:
        """Errors for every object of ``targets`` ({obj_id: inst_count}) in one image; ``depth`` the test image
        (m, 0 = none), ``truths`` every annotated instance (in annotation order)."""
        h, w = depth.shape
        factor = ray_factor(K, h, w)
        dist_test = depth.astype(np.float32) * factor
        out = []
        for oid, n in sorted(targets.items()):
            gts = [t for t in truths if t.obj_id == oid]
            ranked = sorted(range(len(gts)), key=lambda i: gts[i].visib_fract, reverse=True)[:n]  # stable
            valid = np.isin(np.arange(len(gts)), ranked)
            ests = sorted((e for e in estimates if e.obj_id == oid), key=lambda e: e.score, reverse=True)[:n]
            E, G, T = len(ests), len(gts), len(VSD_TAUS)
            errs = ObjectErrors(oid, n, valid, np.full((E, G), np.inf), np.full((E, G), np.inf), np.ones((E, G, T)),
                                np.array([g.visib_fract for g in gts], dtype=np.float64))
            if E and G and oid in self.points:
                pts, syms, diameter = self.points[oid], self.syms[oid], self.infos[oid].diameter
                d_gt = [self.render(oid, g.T_cam_obj, K, h, w) * factor for g in gts]
                for i, e in enumerate(ests):
                    d_est = self.render(oid, e.T_cam_obj, K, h, w) * factor
                    for j, g in enumerate(gts):
                        errs.mssd[i, j] = mssd(e.T_cam_obj, g.T_cam_obj, self.hull[oid], syms)
                        errs.mspd[i, j] = mspd(e.T_cam_obj, g.T_cam_obj, pts, syms, K)
                        errs.vsd[i, j] = vsd(d_est, d_gt[j], dist_test, diameter)
            out.append(errs)
        return out


def _hull_vertices(points: np.ndarray) -> np.ndarray:
    """Indices of the points on their convex hull's vertices (all of them if the hull is flat)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return np.sort(ConvexHull(points).vertices)
    except QhullError:
        return np.arange(len(points))


# ------------------------------------------------------------------------------------------------- scores

def taken(errors: np.ndarray, valid: np.ndarray, threshold: float) -> np.ndarray:
    """Greedy matching (bop_toolkit's ``match_poses``): estimates (rows, best score first) each take the
    unmatched valid instance (column) with the lowest error below ``threshold``; bool (G,): the instances taken."""
    out = np.zeros(errors.shape[1], bool)
    for row in errors:
        ok = valid & ~out & (row < threshold)
        if ok.any():
            out[np.argmin(np.where(ok, row, np.inf))] = True
    return out


def matched(errors: np.ndarray, valid: np.ndarray, threshold: float) -> int:
    """The number of instances ``taken`` at ``threshold``."""
    return int(taken(errors, valid, threshold).sum())


def _recalls(groups: list[ObjectErrors], diameter: float, width: int, bins: tuple[tuple[float, float], ...] = ()
             ) -> list[dict[str, np.ndarray | int]]:
    """Matched counts at every threshold of each metric, summed over ``groups`` (one object's): over all the
    instances (first), then over those of each visible-fraction bin (its targets: its valid instances)."""
    def zero(targets: int) -> dict[str, np.ndarray | int]:
        return {"targets": targets, "vsd": np.zeros((len(VSD_TAUS), len(THETAS))), "mssd": np.zeros(len(THETAS)),
                "mspd": np.zeros(len(MSPD_PX))}

    out = [zero(sum(g.targets for g in groups))] + [zero(0) for _ in bins]
    for g in groups:
        hits = {"vsd": np.array([[taken(g.vsd[:, :, i], g.valid, th) for th in THETAS] for i in range(len(VSD_TAUS))]),
                "mssd": np.array([taken(g.mssd, g.valid, th * diameter) for th in THETAS]),
                "mspd": np.array([taken(g.mspd, g.valid, k * width / 640.0) for k in MSPD_PX])}  # (..., G)
        sels = [np.ones(g.valid.shape, bool)] + [g.in_bin(lo, hi) for lo, hi in bins]
        for c, sel in zip(out, sels):
            for k, h in hits.items():
                c[k] = c[k] + h[..., sel].sum(axis=-1)
        for c, sel in zip(out[1:], sels[1:]):
            c["targets"] += int((g.valid & sel).sum())
    return out


def _ar(counts: dict[str, np.ndarray | int]) -> dict[str, float | int]:
    n = counts["targets"]
    if not n:
        return {"ar": float("nan"), "ar_vsd": float("nan"), "ar_mssd": float("nan"), "ar_mspd": float("nan"),
                "targets": 0}
    r = {f"ar_{k}": float(np.mean(counts[k]) / n) for k in ("vsd", "mssd", "mspd")}
    return {"ar": float(np.mean(list(r.values()))), **r, "targets": int(n)}


def scores(groups: list[ObjectErrors], infos: dict[int, ObjectInfo], width: int,
           bins: tuple[tuple[float, float], ...] = VISIB_BINS) -> dict:
    """AR, AR_VSD, AR_MSSD, AR_MSPD over every target (as BOP reports a dataset), per object (``per_object``, keyed
    by obj_id as text) and per visible-fraction bin (``by_visib``: one entry per bin, ``visib`` [lo, hi] with the
    scores and the bin's ``targets``); ``width`` of the images in px (MSPD's thresholds scale with width / 640)."""
    per = {o: _recalls([g for g in groups if g.obj_id == o], infos[o].diameter, width, bins)
           for o in sorted({g.obj_id for g in groups})}
    totals = []
    for b in range(len(bins) + 1):
        total = {"targets": sum(c[b]["targets"] for c in per.values())}
        for k in ("vsd", "mssd", "mspd"):
            total[k] = sum((c[b][k] for c in per.values()), np.zeros_like(_recalls([], 1.0, width)[0][k]))
        totals.append(total)
    return {**_ar(totals[0]), "per_object": {str(o): _ar(c[0]) for o, c in per.items()},
            "by_visib": [{"visib": [lo, hi], **_ar(t)} for (lo, hi), t in zip(bins, totals[1:])]}
