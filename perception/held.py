"""A held part's position from a look at it in the hand: the pose it is believed held in, shifted onto the depth image.

Closing fingers shift a part by millimetres, so the pose the pick's estimate gives it in the hand is a good start.
The observed points kept are those within ``start_reach`` of the model placed there (its seen faces; the arm beyond
is left out), less those within ``self_filter`` of the hand's own surface where the caller gives it (the fingers
beside the part: a cell knows its hand's pose and meshes). Each step pairs points both ways within a reach that
shrinks from ``start_reach`` to ``reach``: each observed point p with its nearest model point, and each model point
facing the camera with its nearest observed point (so a face seen from below is pulled back over the points seen,
not only onto their plane), and shifts the model by the pairs' mean difference, its turn R kept::

    t_{k+1} = t_k + mean_i ( b_i - a_i )      (pairs a_i -> b_i: model point -> observed point, camera frame)

A face seen from below pins the part's position well; its turn about the face's normal ICP pins poorly (a turn
fitted by ICP as well turned more held parts past 3 deg than the pick's estimate had), so ICP keeps the turn. The
turn is pinned by the outline instead: with ``turn_deg`` > 0 and the caller's ``up`` (the axis of the turn, camera
frame), the fit is turned about ``up`` through the observed points' centre by every ``3 turn_step_deg`` within
+-``turn_deg`` and then by ``turn_step_deg`` each side of the best, each turn shifted again, and the one of least
score is kept::

    score = mean_i min(d_i, truncation) + violation_weight v

d_i: the distance of observed point i to the nearest model point; v: the share of the model points facing the camera
that project onto pixels seen through (no depth) or seen more than ``violation_margin`` behind them (a part turned a
degree off sticks out of its seen outline). It needs no training and no plane: what a cell's in-hand check does with
the part's CAD model. Points are camera-frame metres; K is the 3x3 intrinsic matrix.
"""

from __future__ import annotations

from dataclasses import field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from posegrasp.bop import models as bop_models
from posegrasp.config import settings, within
from posegrasp.geometry import axis_angle_R, make_T
from posegrasp.perception.crop import backproject, seen_facing


@settings
class HeldFitConfig:
    """Shifting a held part's believed pose onto a look's depth image (``perception.held``)."""

    #: Observed points farther (m) than this from the model at the believed pose are left out; the pairs' reach
    #: starts there ...
    start_reach: float = field(default=0.012, metadata=within(1e-4, 0.1))
    #: ... and shrinks by 10 % a step down to this (m).
    reach: float = field(default=0.006, metadata=within(1e-4, 0.1))
    #: Observed points this near (m) the hand's own surface (the caller's ``exclude``: the fingers beside the part)
    #: are left out.
    self_filter: float = field(default=0.004, metadata=within(0.0, 0.05))
    #: ICP steps.
    iterations: int = field(default=120, metadata=within(1, 1000))
    #: Observed points fitted (a seeded random subset) ...
    max_points: int = field(default=3000, metadata=within(3, 1_000_000))
    #: ... and fewer than this, observed or paired: no fit (the part is not seen).
    min_points: int = field(default=50, metadata=within(3, 1_000_000))
    #: Surface points sampled on each model.
    model_points: int = field(default=5000, metadata=within(3, 10_000_000))
    #: The turn about the caller's ``up`` searched (deg, each side of the believed turn); 0: the turn is kept.
    turn_deg: float = field(default=0.0, metadata=within(0.0, 90.0))
    #: The turn search's step (deg): every third step within +-turn_deg, then one step each side of the best.
    turn_step_deg: float = field(default=0.25, metadata=within(0.001, 90.0))
    #: ICP steps after each turn (at the least reach).
    turn_iterations: int = field(default=10, metadata=within(1, 1000))
    #: The turn score's distances are clipped here (m) ...
    truncation: float = field(default=0.003, metadata=within(1e-5, 0.1))
    #: ... and its violation share weighs this (m per share) ...
    violation_weight: float = field(default=0.01, metadata=within(0.0, 100.0))
    #: ... a model point violating where it lies this far (m) in front of the seen surface, or where none is seen.
    violation_margin: float = field(default=0.003, metadata=within(0.0, 0.1))
    #: The model points whose violation counts face the camera at least this much (the cosine of their normal's
    #: angle to the line of sight): a side seen edge-on moves in and out of the outline with any turn.
    facing: float = field(default=0.5, metadata=within(0.0, 1.0))


class HeldFit:
    """Held parts' positions fitted to depth images, with the models of the BOP models root ``models`` (each sampled
    at its first use)."""

    def __init__(self, models: str | Path, cfg: HeldFitConfig | None = None):
        self.root = Path(models)
        self.cfg = cfg or HeldFitConfig()
        self._models: dict[int, tuple[np.ndarray, np.ndarray, cKDTree]] = {}

    def model(self, obj_id: int) -> tuple[np.ndarray, np.ndarray, cKDTree]:
        """Object ``obj_id``'s surface points (M, 3), their outward normals (M, 3) (object frame, m) and the
        points' k-d tree."""
        if obj_id not in self._models:
            pts, normals = bop_models.sample_model_surface(bop_models.load_model(self.root, obj_id),
                                                           self.cfg.model_points, seed=obj_id)
            self._models[obj_id] = pts, normals, cKDTree(pts)
        return self._models[obj_id]

    def __call__(self, obj_id: int, T_cam_obj: np.ndarray, depth: np.ndarray, K: np.ndarray, seed: int = 0,
                 exclude: np.ndarray | None = None, up: np.ndarray | None = None) -> np.ndarray | None:
        """Object ``obj_id`` believed at ``T_cam_obj`` (4, 4), shifted onto the depth image (H, W) (m, 0: none) seen
        through K (3, 3): T_cam_obj with the fitted translation (and, given ``up`` and ``turn_deg``, turned about
        ``up``: module doc), or None where fewer than ``min_points`` points lie near it or pair with it (``seed`` draws
        the points fitted). ``exclude``: (M, 3) camera-frame points (m) on the hand; observed points within
        ``self_filter`` of them are not the part's."""
        c = self.cfg
        pts, _, tree = self.model(obj_id)
        R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3].copy()
        H, W = depth.shape
        P = backproject(depth, K, (0, H, 0, W), np.flatnonzero(depth > 0))
        P = P[tree.query((P - t) @ R, distance_upper_bound=c.start_reach)[0] < c.start_reach]
        if exclude is not None and len(exclude) and len(P) and c.self_filter > 0:
            P = P[cKDTree(exclude).query(P, distance_upper_bound=c.self_filter)[0] >= c.self_filter]
        if len(P) < c.min_points:
            return None
        if len(P) > c.max_points:
            P = P[np.sort(np.random.default_rng(seed).choice(len(P), c.max_points, replace=False))]
        seen = cKDTree(P)
        t = self._shift(obj_id, R, t, P, seen, c.start_reach, c.iterations)
        if t is not None and up is not None and c.turn_deg > 0:
            R, t = self._turn(obj_id, R, t, P, seen, depth, K, np.asarray(up, float))
        if t is None:
            return None
        out = np.array(T_cam_obj, float)
        out[:3, :3], out[:3, 3] = R, t
        return out

    def _shift(self, obj_id: int, R: np.ndarray, t: np.ndarray, P: np.ndarray, seen: cKDTree, reach: float,
               steps: int) -> np.ndarray | None:
        """The translation t (3,) of the model turned R shifted onto the observed points P (N, 3) (``steps`` ICP
        steps from ``reach``: module doc); None where too few points pair."""
        c = self.cfg
        pts, normals, tree = self.model(obj_id)
        facing = np.einsum("ij,ij->i", normals @ R.T, pts @ R.T + t) < 0.0  # toward the camera (the turn is kept)
        front = pts[facing]
        for _ in range(steps):
            reach = max(c.reach, 0.9 * reach)
            d, j = tree.query((P - t) @ R, distance_upper_bound=reach)
            M = front @ R.T + t
            d2, i2 = seen.query(M, distance_upper_bound=reach)
            if (d < reach).sum() + (d2 < reach).sum() < c.min_points:
                return None
            t = t + np.concatenate([P[d < reach] - (pts[j[d < reach]] @ R.T + t), P[i2[d2 < reach]] - M[d2 < reach]]
                                   ).mean(axis=0)
        return t

    def _score(self, obj_id: int, R: np.ndarray, t: np.ndarray, P: np.ndarray, depth: np.ndarray, K: np.ndarray
               ) -> float:
        """The turn score (m, lower is better: module doc) of the model at (R, t) against the observed points P and
        the depth image."""
        c = self.cfg
        pts, normals, tree = self.model(obj_id)
        fit = np.minimum(tree.query((P - t) @ R, distance_upper_bound=c.truncation)[0], c.truncation).mean()
        M, _, dz = seen_facing(pts, normals, make_T(R, t), K, depth, c.facing)
        viol = ((dz == 0) | (dz > M[:, 2] + c.violation_margin)).sum() / max(len(M), 1)
        return float(fit + c.violation_weight * viol)

    def _turn(self, obj_id: int, R: np.ndarray, t: np.ndarray, P: np.ndarray, seen: cKDTree, depth: np.ndarray,
              K: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The fit (R, t) turned about ``up`` through the observed points' centre to the least score (module doc)."""
        c = self.cfg
        centre, up = P.mean(axis=0), up / np.linalg.norm(up)
        tried: dict[float, tuple[float, np.ndarray, np.ndarray | None]] = {}

        def turned(deg: float) -> tuple[float, np.ndarray, np.ndarray | None]:
            if deg not in tried:
                G = axis_angle_R(up, np.radians(deg))
                Rg = G @ R
                tg = self._shift(obj_id, Rg, centre + G @ (t - centre), P, seen, c.reach, c.turn_iterations)
                tried[deg] = (np.inf if tg is None else self._score(obj_id, Rg, tg, P, depth, K), Rg, tg)
            return tried[deg]

        coarse = 3 * c.turn_step_deg
        n = int(c.turn_deg // coarse)
        best = min((k * coarse for k in range(-n, n + 1)), key=lambda d: turned(d)[0])
        best = min((best - c.turn_step_deg, best, best + c.turn_step_deg), key=lambda d: turned(d)[0])
        return turned(best)[1:]
