"""Depth refinement of a pose estimate: ICP from a set of rotation hypotheses, scored against the depth image.

The pose net's translations are good (median 6 mm) but its rotations often sit on a near-symmetry of a
block: a brick turned 90 deg or an arch upside down covers almost the same points, so ADD-S stays small
while the grasp closes on the wrong faces. Like PoseCNN's and DenseFusion's "+ICP" variants, this step
fits the model to the observed points, here from H starting rotations R_est Q (Q: by default the 24
rotations of the cube group, in the object frame) so that it can leave a wrong basin:

    for each hypothesis h:  repeat `iterations` times: match each observed point p_i to its nearest model
                            point m_j under (R_h, t_h); (R_h, t_h) <- Kabsch(m_j -> p_i)
    score_h = mean_i min(d_i, truncation) + violation_weight * v_h + float_weight * f_h

d_i: distance of observed point i to the model at the final pose; v_h: the share of model points that
project onto valid depth pixels and lie more than ``violation_margin`` in front of the observed surface
(the model would fill space the camera sees through), plus, given the supporting plane, the share of model
points more than ``violation_margin`` beneath it (sunk into the table); f_h, given the plane: the height of the
lowest model point above it, less ``float_margin``, in cm, within [0, 1] (a block resting on nothing: an arch standing
on the stack task's 3 mm pad was fitted lying on a side with its top where the seen top is, floating 6-9 mm up; the
margin, 4 mm, lets a block stand on the pad).
The hypothesis with the lowest score wins. The nearest model point is looked up in a voxel grid around the model
(``NearestGrid``: the nearest point of every cell centre, computed once per model), so a step costs O(H N) instead
of the O(H N M) of an exhaustive search; points beyond the grid take the nearest point of its closest cell. The last ``exact_steps`` steps take the
exact nearest points (from a k-d tree of the model), for the ``polish`` hypotheses that score best by the grid's
distances only. The final scores are fine: their fit term takes each observed point's distance from the model's
surface, interpolated in a 1 mm grid of it (``perception.distance_field``; within 0.01-0.03 mm on average near a
block, where the nearest of the 1500 model points lies 0.45-0.73 mm off, and without a k-d search), and their other terms
all the model points.
A block resting on the table and seen from above constrains its turn about the table's normal least (a cube's top
face fits its points at any yaw), so after the first steps the best hypothesis of each of the ``yaw_seeds`` best-scoring faces
turned up (``up_face``: which of the model's rests lies nearest the plane's normal) is turned about the plane's normal (the
camera's optical axis without a plane), through the object's centre, by every ``yaw_step_deg`` of the turn that maps
the model onto itself about that axis (360 deg / the number of its symmetries about it), and fitted again before the
exact steps: on the val split with ground-truth masks, the fit started at the true pose
scored better than the one found from the pose net's estimate in every one of the 85 instances turned more than
15 deg, so the fit lacked starts, not a better score.
Hypotheses that differ by a symmetry of the object start the same fit, so only one of them is run
(``distinct_rotations``); given the plane, each also starts a second time moved along the plane's normal until
the model rests on it (seen from above, an arch's top or a lying cylinder's side also fits 2 cm too deep). With
``level_rests`` these resting starts are also levelled (``level``: the rest of the model nearest the normal turned onto
it, so a stable face of its convex hull lies on the plane, ``perception.rests``; ``rest_starts``: a rest that no
hypothesis is nearest to gets the one nearest it, as an L-block standing as an inverted V on the ends of its bars, 45 deg
from every object axis; val, ground-truth masks: AR 0.932 -> 0.944, the L-block's 0.873 -> 0.938, levelled onto the
nearest object axis before) and fitted with that held: each step solves for a turn about the normal n and a shift
along the plane only (``_Kabsch``'s held rows: with q_i = R m_i, the turn by a maximising sum_i w_i G(a) q_i .
(p_i - c_p), a = atan2(sum w n . (q x p), sum w (q . p - (n . q)(n . p)))), then sets the model back resting on the
plane. A free
fit of a standing arch seen at a slant slid off to a tilted pose that scored worse than the standing one, and a fit
levelled after each free step drifted in yaw (val, ground-truth masks: AR 0.854 free, 0.875 levelled after each
step, 0.923 with the turn fit). Last, each object's best fit is turned about the normal through its centre by every
3 ``yaw_search_step_deg`` within +-``yaw_search_deg``, then by one step each side of the best, and the best-scoring
turn kept: seen from above, a cube's side faces give the fit little to turn it by, but a model a degree off in yaw
sticks out of the observed silhouette, which the free-space term sees (the stack task's looks: the cube's median yaw
error 2.4 -> 1.2 deg). Then (``pattern_rounds``) each object's best fits on
``pattern_fits`` different rests are moved by a pattern search on the fine score (``_pattern_search``: shifts of
+-2, 1, 0.5 mm along two axes of the plane and turns of as many degrees about its normal, the best move of each round
kept where it lowers the score): seen from straight above, a flat face's points pin neither its shift nor its turn,
and ICP stops where the squared distances balance.
Points are camera-frame metres; K is the 3x3 intrinsic matrix.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from posegrasp.perception.distance_field import DistanceField, Fields
from posegrasp.perception.rests import Rests


def cube_rotations() -> np.ndarray:
    """The 24 proper rotations that map the coordinate axes onto themselves, (24, 3, 3)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[[0, 1, 2], list(perm)] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return np.stack(out)


@dataclass
class ICPConfig:
    """iterations: ICP steps per hypothesis, the last ``exact_steps`` of them (at most) with the exact nearest
    model points instead of the voxel grid, and only for the ``polish`` hypotheses (0: all) that score
    best before them (with the grid's distances). max_points: observed points used (random subset).
    truncation (m): per-point distance cap in the score. violation_margin (m) and violation_weight (m per
    unit share): the free-space term. float_margin (m) and float_weight (m): given the plane, a pose whose lowest
    model point lies more than float_margin above it costs float_weight x (height - margin) / 1 cm, at most
    float_weight (a block resting on nothing; 0: off). hypotheses: "cube" (24 rotations) or "identity" (plain ICP).
    yaw_step_deg: the turns about the plane's normal tried from the best hypothesis of each of an object's
    ``yaw_seeds`` best faces up after the first ``iterations - exact_steps`` steps, each fitted ``yaw_iterations``
    more grid steps (0: none). The ``polish`` hypotheses are each turned at least 10 deg from the others.
    level_rests: the starts moved to rest on the plane are also levelled, and fitted as turns about its normal
    and shifts along it, resting (module doc). yaw_search_deg and yaw_search_step_deg: each object's best fit at the
    end is turned about the normal through its centre by every third step within +-yaw_search_deg, then by one step
    each side of the best, and the best-scoring turn kept (0: off). pattern_rounds: then each object's best fits on
    ``pattern_fits`` different rests are moved by a pattern search on the fine score, that many rounds per scale
    (``_pattern_search``; 0: off; 1 raised AR on val 0.884 -> 0.908 and on test 0.878 -> 0.900, 2 gave 0.915 and
    0.899). model_points: surface points sampled on each model (``Estimator``;
    in random order); rank_points: the first of them, for the free-space, plane and floating terms of
    the scores that rank the many hypotheses before the exact steps (those terms cost O(H M), the fit's grid lookups
    O(H N)); the fine scores take them all."""

    iterations: int = 12
    exact_steps: int = 3
    polish: int = 3
    max_points: int = 300
    truncation: float = 0.01
    violation_margin: float = 0.005
    violation_weight: float = 0.01
    float_margin: float = 0.004
    float_weight: float = 0.01
    hypotheses: str = "cube"
    yaw_step_deg: float = 15.0
    yaw_seeds: int = 3
    yaw_iterations: int = 10
    level_rests: bool = True
    yaw_search_deg: float = 15.0
    yaw_search_step_deg: float = 1.0
    pattern_rounds: int = 1
    pattern_fits: int = 2
    model_points: int = 1500
    rank_points: int = 500

    def validate(self) -> None:
        """Raise ValueError on an unusable configuration."""
        self.rotations()
        if min(self.iterations, self.exact_steps, self.polish) < 0:
            raise ValueError(f"ICP iterations ({self.iterations}), exact_steps ({self.exact_steps}) and polish "
                             f"({self.polish}) must be >= 0")
        if self.yaw_step_deg < 0 or self.yaw_seeds < 1 or self.yaw_iterations < 0:
            raise ValueError(f"ICP yaw_step_deg ({self.yaw_step_deg}) and yaw_iterations ({self.yaw_iterations}) "
                             f"must be >= 0 and yaw_seeds ({self.yaw_seeds}) >= 1")
        if self.yaw_search_deg < 0 or self.yaw_search_step_deg <= 0:
            raise ValueError(f"ICP yaw_search_deg ({self.yaw_search_deg}) must be >= 0 and yaw_search_step_deg "
                             f"({self.yaw_search_step_deg}) positive")
        if self.pattern_rounds < 0 or self.pattern_fits < 1:
            raise ValueError(f"ICP pattern_rounds ({self.pattern_rounds}) must be >= 0 and pattern_fits "
                             f"({self.pattern_fits}) >= 1")
        if self.model_points < 3 or not 1 <= self.rank_points <= self.model_points:
            raise ValueError(f"ICP model_points ({self.model_points}) must be >= 3 and rank_points "
                             f"({self.rank_points}) within [1, model_points]")
        if self.max_points < 3:
            raise ValueError(f"ICP max_points must be >= 3 (a rigid fit needs 3 points), got {self.max_points}")
        if self.truncation <= 0 or min(self.violation_margin, self.violation_weight, self.float_margin,
                                       self.float_weight) < 0:
            raise ValueError(f"ICP truncation ({self.truncation}) must be positive, violation_margin "
                             f"({self.violation_margin}), violation_weight ({self.violation_weight}), float_margin "
                             f"({self.float_margin}) and float_weight ({self.float_weight}) >= 0")

    def rotations(self) -> np.ndarray:
        """The starting rotations Q (H, 3, 3), object frame."""
        if self.hypotheses == "cube":
            return cube_rotations()
        if self.hypotheses == "identity":
            return np.eye(3)[None]
        raise ValueError(f"ICP hypotheses must be 'cube' or 'identity', got {self.hypotheses!r}")


def distinct_rotations(Q: np.ndarray, discrete: list[np.ndarray], axes: list[np.ndarray],
                       tol_deg: float = 1.0) -> np.ndarray:
    """The hypotheses Q (H, 3, 3) less those that start the same fit under the object's symmetries.

    With S a symmetry (S maps the model onto itself), R Q_i S places the model exactly where R Q_i
    does, so Q_j is dropped when Q_i^T Q_j = D C for a kept Q_i, D the identity or a discrete symmetry
    (4x4, rotation part) and C a rotation about a continuous symmetry axis (the identity without one).
    The translation parts of the symmetries are ignored: ICP absorbs them. Q keeps its order."""
    Ds = [np.eye(3)] + [np.asarray(D)[:3, :3] for D in discrete]
    cos_tol = np.cos(np.radians(tol_deg))

    def is_symmetry(g: np.ndarray) -> bool:
        for D in Ds:
            C = D.T @ g
            if (np.trace(C) - 1) / 2 > cos_tol or any(np.asarray(a) @ C @ np.asarray(a) > cos_tol for a in axes):
                return True
        return False

    kept: list[np.ndarray] = []
    for q in Q:
        if not any(is_symmetry(k.T @ q) for k in kept):
            kept.append(q)
    return np.stack(kept)


class NearestGrid:
    """The nearest of the model points (M, 3) (object frame, m) to every cell centre of a voxel grid of side
    ``cell`` (m) over the model's bounding box widened by ``margin`` (m): ``grid(points)`` gives the index of an
    (approximately, within half a cell diagonal) nearest model point of each point (N, 3), object frame. ``field``:
    the model's ``DistanceField``, for the scores' fit term (None: that of the model points, unsigned)."""

    def __init__(self, model: np.ndarray, cell: float = 0.002, margin: float = 0.02,
                 field: DistanceField | None = None):
        if cell <= 0 or margin < 0:
            raise ValueError(f"NearestGrid needs cell > 0 and margin >= 0, got cell={cell}, margin={margin}")
        model = np.asarray(model, dtype=np.float64)
        self.lo = model.min(axis=0) - margin
        self.shape = np.ceil((model.max(axis=0) + margin - self.lo) / cell).astype(int) + 1
        self.cell = cell
        self.tree = cKDTree(model)  # for exact matches
        centres = self.lo + np.stack(np.meshgrid(*[np.arange(n) for n in self.shape], indexing="ij"), -1) * cell
        self.index = torch.from_numpy(self.tree.query(centres.reshape(-1, 3))[1].astype(np.int64))  # C order
        self.field = field or DistanceField(model)

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        return _Grids([self], 0)(points[None], torch.zeros(1, dtype=torch.long))[0]


class _Grids:
    """Several objects' ``NearestGrid``s as one lookup: model o's points start at row o x ``stride`` of the stacked
    models, and ``grids(points, obj)`` maps points (H, N, 3), row h in the frame of object obj[h], to rows of them;
    ``grids.posed(p, R, t, obj)`` does the same for camera-frame points p (H, 3, N) (coordinates first: batched
    products with 3-long rows are ~8x slower on a CPU) of objects at poses (R, t). ``fields``: their distance fields."""

    def __init__(self, grids: list[NearestGrid], stride: int):
        self.trees = [g.tree for g in grids]
        self.fields = Fields([g.field for g in grids])
        self.index = torch.cat([g.index + o * stride for o, g in enumerate(grids)])
        self.start = torch.tensor([0] + [len(g.index) for g in grids[:-1]]).cumsum(0)  # (O,)
        self.lo = torch.tensor(np.stack([g.lo for g in grids]), dtype=torch.float32)  # (O, 3)
        self.cell = torch.tensor([g.cell for g in grids], dtype=torch.float32)  # (O,)
        self.max = torch.tensor(np.stack([g.shape - 1 for g in grids]), dtype=torch.float32)  # (O, 3)
        # (O, 3, 1); float32 holds the flat cell indices exactly (fewer than 2^24 cells)
        self.strides = torch.tensor(np.stack([[g.shape[1] * g.shape[2], g.shape[2], 1] for g in grids]),
                                    dtype=torch.float32)[..., None]

    def __call__(self, points: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        return self.local(points.transpose(1, 2), obj)

    def local(self, points: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        """Rows (H, N) of the nearest model points of points (H, 3, N) in their objects' frames."""
        return self._lookup((points - self.lo[obj, :, None]) / self.cell[obj, None, None], obj)

    def posed(self, p: torch.Tensor, R: torch.Tensor, t: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        """Rows (H, N) of the nearest model points of p (H, 3, N) in the frames R (H, 3, 3), t (H, 3): cell
        coordinates (R^T (p - t) - lo) / cell = (R / cell)^T p - (R^T t + lo) / cell, in one batched product."""
        s = 1.0 / self.cell[obj, None, None]  # (H, 1, 1)
        offset = ((t[:, None] @ R)[:, 0] + self.lo[obj]) * s[:, 0]  # (H, 3)
        return self._lookup(torch.baddbmm(-offset[:, :, None], R.transpose(1, 2) * s, p), obj)

    def _lookup(self, cells: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        """Rows (H, N) for cell coordinates (H, 3, N)."""
        ijk = torch.minimum(cells.round_().clamp_(min=0), self.max[obj, :, None])  # (H, 3, N), whole numbers
        return torch.take(self.index, (ijk * self.strides[obj]).sum(dim=1).long() + self.start[obj, None])

    def exact(self, points: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        """The rows (H, N) in each object's model of the exact nearest model points of points (H, N, 3), row h in the
        frame of object obj[h]."""
        idx = torch.empty(points.shape[:2], dtype=torch.long)
        for o in obj.unique().tolist():
            h = obj == o
            i = self.trees[o].query(points[h].reshape(-1, 3).numpy())[1]
            idx[h] = torch.from_numpy(i).view(-1, points.shape[1])
        return idx


class _Kabsch:
    """Batched weighted least-squares rigid fits dst ~ R src + t to fixed targets dst (H, N, 3) with weights w (H, N)
    >= 0 (0: a padding point); ``fit(src)`` (H, 3, N) (any strides) -> R (H, 3, 3), t (H, 3). With the weights
    normalised to sum to 1 and the targets' weighted centroid c_d, the cross-covariance is
    sum_i w_i (s_i - c_s)(d_i - c_d)^T = S^T (w (D - c_d)), since the centred targets' weighted sum is 0; the right
    factor is computed once. Rows ``held`` are fitted as turns of their R0 about the unit normal n only:
    with q_i = R0 s_i and C = sum_i w_i q_i (d_i - c_d)^T, sum_i w_i G(a) q_i . (d_i - c_d) is cos(a) A + sin(a) B,
    A = tr C - n^T C n, B = n . (C_yz - C_zy, C_zx - C_xz, C_xy - C_yx), so the turn is a = atan2(B, A)."""

    def __init__(self, dst: torch.Tensor, w: torch.Tensor):
        self.w = (w / w.sum(dim=1, keepdim=True))[:, None, :]  # (H, 1, N)
        self.cd = (self.w @ dst)[:, 0]  # (H, 3)
        self.wd = self.w.transpose(1, 2) * (dst - self.cd[:, None])  # (H, N, 3)

    def fit(self, src: torch.Tensor, held: torch.Tensor | None = None, R0: torch.Tensor | None = None,
            n: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The fits of every row; the rows ``held`` (H,) as turns of R0 (H, 3, 3) about n (3,) (class doc)."""
        cs = (src * self.w).sum(dim=2)  # (H, 3)
        C = torch.bmm(src, self.wd)  # (H, 3, 3) cross-covariance
        if held is None or not bool(held.any()):
            R = _svd_rotation(C)
        else:
            R = torch.empty_like(C)
            free = ~held
            if bool(free.any()):
                R[free] = _svd_rotation(C[free])
            Rh = R0[held]
            Ch = Rh @ C[held]
            A = Ch.diagonal(dim1=1, dim2=2).sum(dim=1) - (Ch @ n) @ n
            B = torch.stack([Ch[:, 1, 2] - Ch[:, 2, 1], Ch[:, 2, 0] - Ch[:, 0, 2], Ch[:, 0, 1] - Ch[:, 1, 0]], 1) @ n
            R[held] = turns_about(n, torch.atan2(B, A)) @ Rh
        return R, self.cd - (R @ cs[:, :, None])[:, :, 0]


def _svd_rotation(C: torch.Tensor) -> torch.Tensor:
    """The rotations (H, 3, 3) that maximise tr(R C) for cross-covariances C (H, 3, 3) (Kabsch, no reflection)."""
    U, _, Vt = torch.linalg.svd(C)
    d = torch.sign(torch.linalg.det(Vt.transpose(1, 2) @ U.transpose(1, 2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=1))
    return Vt.transpose(1, 2) @ D @ U.transpose(1, 2)


def turns_about(n: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """Rotations (S, 3, 3) by ``angles`` (S,) (rad) about the unit axis n (3,), or about each of the axes n (S, 3):
    I + sin(a) N + (1 - cos(a)) N^2, N the cross-product matrix of the axis (Rodrigues)."""
    u = n.expand(len(angles), 3)
    N = torch.zeros(len(angles), 3, 3, dtype=n.dtype)  # N v = u x v
    N[:, 0, 1], N[:, 0, 2], N[:, 1, 2] = -u[:, 2], u[:, 1], -u[:, 0]
    N[:, 1, 0], N[:, 2, 0], N[:, 2, 1] = u[:, 2], -u[:, 1], u[:, 0]
    return torch.eye(3, dtype=n.dtype) + torch.sin(angles)[:, None, None] * N + \
        (1 - torch.cos(angles))[:, None, None] * (N @ N)


def _columns(table: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Columns idx (H, N) of a (3, R) table, as (H, 3, N) (a view of a (3, H, N) tensor)."""
    return table.index_select(1, idx.reshape(-1)).view(3, *idx.shape).transpose(0, 1)


def _padded(arrays: list[np.ndarray], fill: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Point sets (n_i, 3) as one float32 tensor (O, max n_i, 3), padded with ``fill``, and its validity mask
    (O, max n_i)."""
    n = max(len(a) for a in arrays)
    out, valid = torch.full((len(arrays), n, 3), fill), torch.zeros(len(arrays), n, dtype=torch.bool)
    for i, a in enumerate(arrays):
        out[i, :len(a)], valid[i, :len(a)] = torch.from_numpy(np.asarray(a, dtype=np.float32)), True
    return out, valid


def refine_pose(T_cam_obj: np.ndarray, model: np.ndarray, observed: np.ndarray, depth: np.ndarray, K: np.ndarray,
                cfg: ICPConfig | None = None, rotations: np.ndarray | None = None, plane: np.ndarray | None = None,
                grid: NearestGrid | None = None, symmetries: tuple[np.ndarray, np.ndarray] | None = None,
                rests: Rests | None = None) -> tuple[np.ndarray, float]:
    """The best-scoring ICP result over the hypotheses (see module docstring) for one object.

    T_cam_obj (4, 4) estimate; model (M, 3) surface points, object frame (m); observed (N, 3) camera-frame
    points of the object's mask (m); depth (H, W) m; rotations (H, 3, 3): the hypotheses, by default
    ``cfg.rotations()`` (``distinct_rotations`` of them for a symmetric object); plane (4,): the supporting
    plane (``perception.plane``), or None; grid: the model's ``NearestGrid`` (built here when None); symmetries:
    the rotations (S, 3, 3) of the model's discrete symmetries and its continuous axes (A, 3), object frame, which
    spare the yaw turns that a symmetry repeats (None: none); rests: the model's ways of resting on the plane
    (``perception.rests``; None: on a face normal to an object axis). Returns (T_cam_obj refined, its score in m)."""
    return refine_poses([T_cam_obj], [model], [observed], depth, K, cfg, None if rotations is None else [rotations],
                        plane, None if grid is None else [grid], None if symmetries is None else [symmetries],
                        None if rests is None else [rests])[0]


def refine_poses(estimates: list[np.ndarray], models: list[np.ndarray], observed: list[np.ndarray],
                 depth: np.ndarray, K: np.ndarray, cfg: ICPConfig | None = None,
                 rotations: list[np.ndarray] | None = None, plane: np.ndarray | None = None,
                 grids: list[NearestGrid] | None = None,
                 symmetries: list[tuple[np.ndarray, np.ndarray]] | None = None,
                 rests: list[Rests] | None = None) -> list[tuple[np.ndarray, float]]:
    """``refine_pose`` for several objects of one frame at once, their hypotheses in one batch (much of a step's
    cost is fixed: 5 blocks take half the time they take one by one). Per object: estimate, model, observed points,
    rotations, grid, symmetries and rests as ``refine_pose`` takes them; the result of each is what ``refine_pose`` gives it alone,
    up to float rounding."""
    if not estimates:
        return []
    cfg = cfg or ICPConfig()
    rotations = rotations or [cfg.rotations()] * len(estimates)
    m, m_ok = _padded(models, 1e3)  # (O, M, 3); padding far off, never a nearest point
    p, p_ok = _padded(observed)  # (O, N, 3)
    grids = grids or [NearestGrid(x, field=DistanceField(x, margin=cfg.truncation)) for x in models]
    short = [g.field.margin for g in grids if g.field.margin < cfg.truncation]
    if short:  # beyond its grid a field gives its margin: the fit term would stop short of the truncation
        raise ValueError(f"ICP truncation ({cfg.truncation} m) exceeds a model's distance field margin ({min(short)} m); "
                         f"build the fields with margin >= truncation")
    grids = _Grids(grids, m.shape[1])
    dz = torch.from_numpy(np.asarray(depth, dtype=np.float32))
    pl = None if plane is None else torch.from_numpy(np.asarray(plane, dtype=np.float32))
    T = torch.from_numpy(np.stack(estimates).astype(np.float32))  # (O, 4, 4)
    obj = torch.cat([torch.full((len(Q),), o) for o, Q in enumerate(rotations)])  # (H,): each hypothesis' object
    R = T[obj, :3, :3] @ torch.from_numpy(np.concatenate(rotations)).float()  # (H, 3, 3)
    t = T[obj, :3, 3]  # (H, 3)
    if rests is None:  # the object axes, as classes under the objects' symmetries
        rests = [Rests.axes()] * len(estimates) if symmetries is None else [Rests.axes(*sym) for sym in symmetries]
    ups, labels = _stacked(rests)  # (O, U, 3), (O, U)
    held = torch.zeros(len(R), dtype=torch.bool)  # (H,): the hypotheses kept level and resting on the plane
    if pl is not None:  # each hypothesis also starts moved along the plane normal to rest on the plane
        R2, src = rest_starts(R, obj, pl[:3], ups, labels, symmetries=symmetries) if cfg.level_rests \
            else (R, torch.arange(len(R)))
        R, t = torch.cat([R, R2]), torch.cat([t, resting(R2, t[src], m, m_ok, obj[src], pl)])
        obj, held = torch.cat([obj, obj[src]]), torch.cat([held, torch.full((len(R2),), cfg.level_rests)])

    low = torch.zeros(len(R))  # (H,): with a = R^T n, which stays put in a held row, its lowest point's height
    if held.any():  # less n . t + d, min_i m_i . a, stays put too
        low = (m[obj] @ (R.transpose(1, 2) @ pl[:3])[:, :, None])[..., 0].masked_fill(~m_ok[obj], torch.inf).min(1)[0]

    def step(src: torch.Tensor, R0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # one fit, the held ones level
        if not bool(held.any()):
            return fit.fit(src)
        R, t = fit.fit(src, held, R0, pl[:3])
        t[held] = t[held] - (low[held] + t[held] @ pl[:3] + pl[3])[:, None] * pl[:3]  # the held ones set back resting
        return R, t

    columns = m.reshape(-1, 3).T.contiguous()  # (3, O M): the stacked models, as ``grids`` indexes them
    w = p_ok.float()
    exact = min(cfg.exact_steps, cfg.iterations)
    po = p[obj]  # (H, N, 3)
    po, fit = po.transpose(1, 2).contiguous(), _Kabsch(po, w[obj])  # (H, 3, N)
    for _ in range(cfg.iterations - exact):
        R, t = step(_columns(columns, grids.posed(po, R, t, obj)), R)
    if cfg.yaw_step_deg > 0:  # the best few turned about the plane's normal, and fitted on
        normal = np.array([0.0, 0.0, 1.0]) if pl is None else pl[:3].double().numpy()
        keep = _best(_score(R, t, m, m_ok, p, w, obj, dz, K, cfg, pl, grids), obj, cfg.yaw_seeds,
                     face=up_face(R, normal, ups[obj]))
        R, obj, source = _turned(R[keep], obj[keep], normal, cfg.yaw_step_deg, symmetries)
        t, held, low = t[keep][source], held[keep][source], low[keep][source]
        po = p[obj].transpose(1, 2).contiguous()
        fit = _Kabsch(p[obj], w[obj])
        for _ in range(cfg.yaw_iterations):
            R, t = step(_columns(columns, grids.posed(po, R, t, obj)), R)
    if 0 < cfg.polish < int(torch.bincount(obj).max()):  # only each object's best hypotheses by the grid's score go on
        keep = _best(_score(R, t, m, m_ok, p, w, obj, dz, K, cfg, pl, grids), obj, cfg.polish, R)
        R, t, obj, held, low = R[keep], t[keep], obj[keep], held[keep], low[keep]
    po, mo = p[obj], m[obj]
    fit = _Kabsch(po, w[obj])
    for _ in range(exact):  # exact matches for the last steps (a k-d tree of each model's real points)
        nn = grids.exact((po - t[:, None]) @ R, obj)  # (H, N)
        R, t = step(mo[torch.arange(len(obj))[:, None], nn].transpose(1, 2), R)
    score = _score(R, t, m, m_ok, p, w, obj, dz, K, cfg, pl, grids, fine=True)
    steps = ((cfg.yaw_search_deg, 3 * cfg.yaw_search_step_deg), (cfg.yaw_search_step_deg,) * 2)
    normal = torch.tensor([0.0, 0.0, 1.0]) if pl is None else pl[:3]
    for span, by in steps if cfg.yaw_search_deg > 0 else ():  # each object's best fit turned about the normal through
        # its centre by +-by, +-2 by, ... up to span, the best kept: every 3 steps, then one step each side of the best
        best = torch.stack([torch.nonzero(obj == o)[:, 0][score[obj == o].argmin()] for o in obj.unique()])
        angles = np.arange(by, span + 1e-9, by)
        G = turns_about(normal, torch.from_numpy(np.radians(np.concatenate([-angles, angles]))).float())  # (S, 3, 3)
        Rs = (G[None] @ R[best][:, None]).reshape(-1, 3, 3)
        ts, os_ = t[best].repeat_interleave(len(G), 0), obj[best].repeat_interleave(len(G), 0)
        ss = _score(Rs, ts, m, m_ok, p, w, os_, dz, K, cfg, pl, grids, fine=True)
        R, t, obj, score = torch.cat([R, Rs]), torch.cat([t, ts]), torch.cat([obj, os_]), torch.cat([score, ss])
    if cfg.pattern_rounds > 0:
        R, t, obj, score = _pattern_search(
            R, t, obj, score, normal, ups, cfg.pattern_fits, cfg.pattern_rounds,
            lambda Rm, tm, om: _score(Rm, tm, m, m_ok, p, w, om, dz, K, cfg, pl, grids, fine=True))
    out = []
    for o in range(len(estimates)):
        i = torch.nonzero(obj == o)[:, 0]
        best = int(i[score[i].argmin()])
        T_o = np.eye(4)
        T_o[:3, :3], T_o[:3, 3] = R[best].double().numpy(), t[best].double().numpy()
        out.append((T_o, float(score[best])))
    return out


_PATTERN_SCALES = ((0.002, 2.0), (0.001, 1.0), (0.0005, 0.5))  # the pattern search's (shift m, turn deg), in turn


def _pattern_search(R: torch.Tensor, t: torch.Tensor, obj: torch.Tensor, score: torch.Tensor, normal: torch.Tensor,
                    ups: torch.Tensor, fits: int, rounds: int, score_of) -> tuple[torch.Tensor, ...]:
    """Each object's best ``fits`` poses (R (H, 3, 3), t (H, 3) of objects obj (H,), scored ``score`` (H,)) on
    different rests (ups (O, U, 3)) moved by a pattern search on ``score_of(R, t, obj)``: in each of ``rounds``
    rounds per scale of ``_PATTERN_SCALES``, the pose shifted by +-s along two axes of the plane (normal (3,)) and
    turned by +-a about the normal through its centre, the best of the six kept where it scores lower. A block resting
    on the plane keeps resting. Returns R, t, obj and score with the moved poses appended."""
    sel = _best(score, obj, fits, face=up_face(R, normal, ups[obj]))
    Rc, tc, oc, sc = R[sel].clone(), t[sel].clone(), obj[sel], score[sel].clone()
    n = normal.to(R.dtype)
    e1 = torch.linalg.cross(n, torch.eye(3, dtype=n.dtype)[int(n.abs().argmin())])
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(n, e1)
    C = len(Rc)
    for shift, turn in _PATTERN_SCALES:
        moves = torch.stack([shift * e1, -shift * e1, shift * e2, -shift * e2])  # (4, 3)
        G = turns_about(n, torch.tensor(np.radians([turn, -turn]), dtype=n.dtype))  # (2, 3, 3)
        for _ in range(rounds):
            Rm = torch.cat([Rc[:, None].expand(C, 4, 3, 3), G[None] @ Rc[:, None]], 1)  # (C, 6, 3, 3)
            tm = torch.cat([tc[:, None] + moves[None], tc[:, None].expand(C, 2, 3)], 1)  # (C, 6, 3)
            low, k = score_of(Rm.reshape(-1, 3, 3), tm.reshape(-1, 3), oc.repeat_interleave(6)).view(C, 6).min(dim=1)
            better = torch.nonzero(low < sc)[:, 0]
            Rc[better], tc[better], sc[better] = Rm[better, k[better]], tm[better, k[better]], low[better]
    return torch.cat([R, Rc]), torch.cat([t, tc]), torch.cat([obj, oc]), torch.cat([score, sc])


def _stacked(rests: list[Rests]) -> tuple[torch.Tensor, torch.Tensor]:
    """The objects' rests as ups (O, U, 3) float32 and labels (O, U), each padded by repeating its first rest."""
    n = max(len(r.ups) for r in rests)
    pad = [np.concatenate([np.arange(len(r.ups)), np.zeros(n - len(r.ups), dtype=int)]) for r in rests]
    return (torch.from_numpy(np.stack([r.ups[i] for r, i in zip(rests, pad)])).float(),
            torch.from_numpy(np.stack([np.asarray(r.labels)[i] for r, i in zip(rests, pad)])).long())


def _best(score: torch.Tensor, obj: torch.Tensor, n: int, R: torch.Tensor | None = None, apart_deg: float = 10.0,
          face: torch.Tensor | None = None) -> torch.Tensor:
    """Rows of the ``n`` lowest scores (H,) of each object ``obj`` (H,), object by object; given the rotations R
    (H, 3, 3), each kept row turned at least ``apart_deg`` from those kept before it (fits that converged to one
    pose count once); given ``face`` (H,), each kept row with a face label of its own."""
    keep = []
    cos_apart = float(np.cos(np.radians(apart_deg)))
    for o in obj.unique():
        rows = torch.nonzero(obj == o)[:, 0]
        rows = rows[score[rows].argsort()]
        kept = [int(rows[0])]
        for r in rows[1:].tolist():
            if len(kept) == n:
                break
            if face is not None:
                if int(face[r]) not in face[kept].tolist():
                    kept.append(r)
            elif R is None or float(((torch.einsum("kij,ij->k", R[kept], R[r]) - 1) / 2).max()) < cos_apart:
                kept.append(r)  # (the cosines of the angles between R_r and the kept rotations)
        keep.append(torch.tensor(kept))
    return torch.cat(keep)


_AXES = torch.from_numpy(Rests.axes().ups)  # +x, -x, +y, -y, +z, -z


def level(R: torch.Tensor, normal: torch.Tensor, ups: torch.Tensor | None = None) -> torch.Tensor:
    """Each rotation R (H, 3, 3) (object to camera) turned by the least rotation that lays the rest nearest
    ``normal`` (3,, camera frame, unit) onto it: with a = R^T n and e the up of ``ups`` (H, U, 3) (each row's rests,
    ``perception.rests``; None: the six object axes) nearest a, R Q with Q the turn about e x a by the angle between
    e and a (Q e = a, so R Q e = n)."""
    a, e, _ = _nearest_up(R, normal, ups)
    return _turned_onto(R, a, e)


def _turned_onto(R: torch.Tensor, a: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """R (H, 3, 3) Q, Q the least turn that maps the object-frame directions e (H, 3) onto a (H, 3) (``level``)."""
    axis = torch.cross(e, a, dim=1)
    s = axis.norm(dim=1)
    return R @ turns_about(axis / s.clamp(min=1e-12)[:, None], torch.atan2(s, (e * a).sum(dim=1)))


def rest_starts(R: torch.Tensor, obj: torch.Tensor, normal: torch.Tensor, ups: torch.Tensor, labels: torch.Tensor,
                turn_deg: float = 60.0, symmetries: list[tuple[np.ndarray, np.ndarray]] | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """The levelled starts of the hypotheses R (H, 3, 3) of objects obj (H,) with rests ups (O, U, 3) and labels
    (O, U): each ``level``led onto its nearest rest, and for each rest class of an object that none of them reaches
    (an L-block's inverted V lies 45 deg from every object axis), the hypothesis nearest a rest of that class turned
    onto it, and that turned about the normal by every ``turn_deg`` (``yaw_turns``, with the object's symmetries):
    its yaw is a guess. Returns the rotations (H', 3, 3) and the row of R each came from (H',)."""
    a, e, k = _nearest_up(R, normal, ups[obj])
    out, src = [_turned_onto(R, a, e)], [torch.arange(len(R))]
    for o in obj.unique().tolist():
        rows = torch.nonzero(obj == o)[:, 0]
        cos = a[rows] @ ups[o].to(a.dtype).T  # (rows, U)
        disc, axes = symmetries[o] if symmetries is not None else (np.zeros((0, 3, 3)), np.zeros((0, 3)))
        for c in labels[o].unique().tolist():
            in_c = labels[o] == c
            if bool(in_c[k[rows]].any()):
                continue
            best = int(cos[:, in_c].max(dim=1).values.argmax())
            u = int(torch.nonzero(in_c)[:, 0][cos[best, in_c].argmax()])
            Rl = level(R[rows[best]][None], normal, ups[o, u][None, None])
            psi = yaw_turns(Rl[0].double().numpy(), normal.double().numpy(), turn_deg, disc, axes)
            out.append(turns_about(normal.to(R.dtype), torch.from_numpy(psi).to(R.dtype)) @ Rl)
            src.append(rows[best].repeat(len(psi)))
    return torch.cat(out), torch.cat(src)


def _nearest_up(R: torch.Tensor, normal: torch.Tensor, ups: torch.Tensor | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The normal in each object frame, a = R^T n (H, 3), the up of ``ups`` (H, U, 3) nearest it (H, 3) and its
    index (H,) (``level``)."""
    a = R.transpose(1, 2) @ normal.to(R.dtype)  # (H, 3)
    if ups is None:
        ups = _AXES.to(R.dtype).expand(len(R), 6, 3)
    k = (ups.to(R.dtype) @ a[:, :, None])[..., 0].argmax(dim=1)  # (H,)
    return a, ups[torch.arange(len(R)), k].to(R.dtype), k


def resting(R: torch.Tensor, t: torch.Tensor, m: torch.Tensor, m_ok: torch.Tensor, obj: torch.Tensor,
            plane: torch.Tensor) -> torch.Tensor:
    """The translations t (H, 3) moved along the plane's normal until the lowest valid model point (m (O, M, 3),
    m_ok (O, M), of objects obj (H,)) under R (H, 3, 3) lies on the plane (4,: n . x + d = 0, n unit)."""
    height = (m[obj] @ R.transpose(1, 2) + t[:, None]) @ plane[:3] + plane[3]  # (H, M)
    lowest = height.masked_fill(~m_ok[obj], torch.inf).min(dim=1).values  # (H,)
    return t - lowest[:, None] * plane[:3]


def up_face(R: torch.Tensor, normal: np.ndarray, ups: torch.Tensor | None = None) -> torch.Tensor:
    """Which rest (H,) lies nearest ``normal`` (3,, camera frame) under each rotation R (H, 3, 3): the face an object
    resting on a plane with that normal shows the camera. ups (H, U, 3): each row's rests (``perception.rests``), the
    index into them; None: the axes +x, -x, +y, -y, +z, -z, 0-5."""
    return _nearest_up(R, torch.as_tensor(normal), ups)[2]


def yaw_turns(R: np.ndarray, normal: np.ndarray, step_deg: float, discrete: np.ndarray, axes: np.ndarray
              ) -> np.ndarray:
    """The angles (rad) to turn an object at rotation R (3, 3) about ``normal`` (3,, camera frame) by: every
    ``step_deg`` (rounded to divide it evenly) of 360 deg / n, n the number of the object's symmetries about that
    axis (the identity and each discrete rotation D (S, 3, 3) that fixes the axis a = R^T normal, object frame);
    only 0 when a continuous symmetry axis (A, 3) lies along a."""
    a = R.T @ (normal / np.linalg.norm(normal))
    if len(axes) and np.max(np.abs(np.asarray(axes) @ a)) > np.cos(np.radians(2.0)):
        return np.zeros(1)
    n = 1 + int(np.sum(np.linalg.norm(np.asarray(discrete).reshape(-1, 3, 3) @ a - a, axis=1) < 0.02))
    period = 2 * np.pi / n
    k = max(1, int(round(np.degrees(period) / step_deg)))
    return np.arange(k) * (period / k)


def _turned(R: torch.Tensor, obj: torch.Tensor, normal: np.ndarray, step_deg: float,
            symmetries: list[tuple[np.ndarray, np.ndarray]] | None
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each rotation R (H, 3, 3) of object obj (H,) turned about ``normal`` by its ``yaw_turns``: (H', 3, 3), their
    objects (H',) and the row of R each came from (H',)."""
    Rd = R.double()
    psi = []
    for Rh, o in zip(Rd.numpy(), obj.tolist()):
        disc, axes = symmetries[o] if symmetries is not None else (np.zeros((0, 3, 3)), np.zeros((0, 3)))
        psi.append(yaw_turns(Rh, normal, step_deg, disc, axes))
    source = torch.repeat_interleave(torch.tensor([len(x) for x in psi]))
    turned = turns_about(torch.from_numpy(normal).double(), torch.from_numpy(np.concatenate(psi))) @ Rd[source]
    return turned.float(), obj[source], source


def _score(R: torch.Tensor, t: torch.Tensor, m: torch.Tensor, m_ok: torch.Tensor, p: torch.Tensor, w: torch.Tensor,
           obj: torch.Tensor, depth: torch.Tensor, K: np.ndarray, cfg: ICPConfig, plane: torch.Tensor | None,
           grids: _Grids, fine: bool = False) -> torch.Tensor:
    """Score (H,) of the poses (R (H, 3, 3), t (H, 3)) of objects ``obj`` (H,): truncated fit of their observed points
    p (O, N, 3) (weights w (O, N), 0 for padding) to their model points m (O, M, 3) (valid where m_ok) plus the
    weighted shares of model points in free space against ``depth`` (H, W) and beneath the plane (4,) if given, and
    the floating term (``ICPConfig.float_weight``) above it, m.
    The fit's distances are the ``fine`` ones, from the model's surface (the grids' distance fields), or those to the
    grid's matches among the model points (approximate, at most a cell diagonal long); the other terms take all the
    model points when ``fine``, else the first ``cfg.rank_points``."""
    k = m.shape[1] if fine else cfg.rank_points
    ok, wo = m_ok[obj, :k], w[obj]
    # coordinates first, (H, 3, k) and (H, 3, N): batched products with 3-long rows are ~8x slower on a CPU
    mc = torch.baddbmm(t[:, :, None], R, m[:, :k].transpose(1, 2)[obj])  # (H, 3, k), camera frame
    Rt = R.transpose(1, 2)
    local = torch.baddbmm(-(Rt @ t[:, :, None]), Rt, p.transpose(1, 2)[obj])  # (H, 3, N), object frame
    if fine:
        dist = grids.fields(local, obj)
    else:  # (the sum of squares: torch's norm along a 3-long dim of a (H, 3, N) tensor is ~20x slower)
        dist = ((local - _columns(m.reshape(-1, 3).T, grids.local(local, obj))) ** 2).sum(dim=1).sqrt()
    fit = (dist.clamp(max=cfg.truncation) * wo).sum(dim=1) / wo.sum(dim=1)
    z = mc[:, 2].clamp(min=1e-6)
    u = torch.round(mc[:, 0] * float(K[0, 0]) / z + float(K[0, 2])).long()
    v = torch.round(mc[:, 1] * float(K[1, 1]) / z + float(K[1, 2])).long()
    h, w_img = depth.shape
    inside = ok & (u >= 0) & (u < w_img) & (v >= 0) & (v < h)
    dz = torch.take(depth, v.clamp(0, h - 1) * w_img + u.clamp(0, w_img - 1))
    viol = (inside & (dz > 0) & (z < dz - cfg.violation_margin)).sum(dim=1) / inside.sum(dim=1).clamp(min=1)
    score = fit
    if plane is not None:
        height = (mc * plane[:3, None]).sum(dim=1) + plane[3]  # (H, k)
        viol = viol + (ok & (height < -cfg.violation_margin)).sum(dim=1) / ok.sum(dim=1)
        lowest = height.masked_fill(~ok, torch.inf).min(dim=1).values  # (H,)
        score = score + cfg.float_weight * ((lowest - cfg.float_margin) / 0.01).clamp(0, 1)
    return score + cfg.violation_weight * viol
