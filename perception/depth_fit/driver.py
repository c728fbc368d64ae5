"""``fit_poses``: the depth fit's stages, in order, for all the objects of one frame in one batch."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch

from posegrasp.errors import ConfigError
from posegrasp.perception.depth_fit.config import DepthFitConfig, TurnConfig
from posegrasp.perception.depth_fit import icp
from posegrasp.perception.depth_fit.context import FitContext
from posegrasp.perception.depth_fit.model import ObjectModel
from posegrasp.perception.depth_fit.rivals import Rivals
from posegrasp.perception.depth_fit.score import Scored, best_rows, score
from posegrasp.perception.depth_fit.search import pattern_search, yaw_search
from posegrasp.perception.depth_fit.starts import rest_starts, resting, turned, up_face


def fit_pose(T_cam_obj: np.ndarray, model: ObjectModel, observed: np.ndarray, depth: np.ndarray, K: np.ndarray,
             cfg: DepthFitConfig | None = None, plane: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """``fit_poses`` of one object: its estimate T_cam_obj (4, 4), model and observed points (N, 3)."""
    return fit_poses([T_cam_obj], [model], [observed], depth, K, cfg, plane)[0]


def fit_poses(estimates: list[np.ndarray], models: list[ObjectModel], observed: list[np.ndarray],
              depth: np.ndarray, K: np.ndarray, cfg: DepthFitConfig | None = None,
              plane: np.ndarray | None = None, rivals: Rivals | None = None) -> list[tuple[np.ndarray, float]]:
    """The best-scoring fit of each object of a frame (``perception.depth_fit``): from its estimate T_cam_obj (4, 4),
    its ``ObjectModel`` and its observed points (N_o, 3) (camera frame, m), against the depth image (H, W) (m) seen
    through intrinsics K (3, 3), given the supporting plane (4,: n . x + d = 0, camera frame; ``perception.plane``)
    or None. Returns (T_cam_obj fitted, its score in m) per object. The objects' fits run as one batch, its rows
    shared out over torch's threads (``kernels``); each result is the one the object gets alone. Given
    ``rivals`` (``perception.depth_fit.rivals``: objects that are one part posed as several types), a type that trails
    its part's best is dropped along the way and returns its estimate with score inf."""
    if not estimates:
        return []
    cfg = cfg or DepthFitConfig()
    short = [x.grid.field.margin for x in models if x.grid.field.margin < cfg.score.truncation]
    if short:  # beyond its grid a field gives its margin: the fit term would stop short of the truncation
        raise ConfigError(f"depth_fit score.truncation ({cfg.score.truncation} m) exceeds a model's distance field "
                          f"margin ({min(short)} m); build the fields with margin >= truncation")
    frame = FitContext.of(models, observed, depth, K, plane)
    fits = _starts(frame, estimates, [x.hypotheses for x in models], cfg.starts.level_rests)
    done = _fit(frame, cfg, rivals, fits)
    best = done.bests()
    return [best.get(o, (estimates[o], float("inf"))) for o in range(len(estimates))]


def _fit(frame: FitContext, cfg: DepthFitConfig, rivals: Rivals | None, fits: _Fits) -> Scored:
    """The fits from their starts on: grid steps, turns, exact steps and searches (``perception.depth_fit``), with
    their objects' rivals dropped along the way; each object's final candidates and their scores."""
    rank = partial(score, frame, cfg.score)
    exact_steps = min(cfg.fit.exact_steps, cfg.fit.iterations)
    fits = _steps(frame, fits, cfg.fit.iterations - exact_steps)
    ranked = rank(fits.R, fits.t, fits.obj)
    if rivals is not None:  # types of a part that trail its best by far are fitted no further
        fits, ranked = _winners(fits, ranked, rivals, rivals.steps_margin)
    if cfg.turns.step_deg > 0:
        fits = _turns(frame, fits, cfg.turns, ranked)
        ranked = rank(fits.R, fits.t, fits.obj)
        if rivals is not None:
            fits, ranked = _winners(fits, ranked, rivals, rivals.turns_margin)
    if 0 < cfg.fit.polish < int(torch.bincount(fits.obj).max()):  # each object's best by the grid's score go on
        fits = fits.rows(best_rows(ranked, fits.obj, cfg.fit.polish, fits.R))
    fits = _steps(frame, fits, exact_steps, exact=True)
    fine = partial(score, frame, cfg.score, fine=True)
    poses = yaw_search(Scored(fits.R, fits.t, fits.obj, fine(fits.R, fits.t, fits.obj)), frame.normal, cfg.search,
                       fine)
    if cfg.search.pattern_rounds > 0:
        poses = pattern_search(poses, frame.normal, frame.ups, cfg.search, fine)
    return poses


@dataclass(frozen=True)
class _Fits:
    """The fits in progress: rotations R (H, 3, 3) and translations t (H, 3) (object to camera) of objects obj (H,);
    ``held`` (H,): fitted as turns about the plane's normal n and shifts along the plane, resting on it; for those,
    ``low`` (H,) = min_j m_j . (R^T n), the lowest model point's height less n . t + d, which such a step keeps."""

    R: torch.Tensor
    t: torch.Tensor
    obj: torch.Tensor
    held: torch.Tensor
    low: torch.Tensor

    def rows(self, i: torch.Tensor) -> _Fits:
        """The fits of rows i."""
        return _Fits(self.R[i], self.t[i], self.obj[i], self.held[i], self.low[i])


def _starts(frame: FitContext, estimates: list[np.ndarray], hypotheses: list[np.ndarray], level_rests: bool) -> _Fits:
    """The fits' starts: each estimate R, t turned by each of its object's hypotheses (R Q, t), and given the plane
    each of these also moved to rest on it, and with ``level_rests`` laid on its nearest rest and held
    (``perception.depth_fit.starts``)."""
    T = torch.from_numpy(np.stack(estimates).astype(np.float32))  # (O, 4, 4)
    obj = torch.cat([torch.full((len(Q),), o) for o, Q in enumerate(hypotheses)])  # (H,): each hypothesis' object
    R = T[obj, :3, :3] @ torch.from_numpy(np.concatenate(hypotheses)).float()  # (H, 3, 3)
    t = T[obj, :3, 3]  # (H, 3)
    held, low = torch.zeros(len(R), dtype=torch.bool), torch.zeros(len(R))  # low: a held row's only
    pl = frame.plane
    if pl is not None:
        R2, src = (rest_starts(R, obj, pl[:3], frame.ups, frame.rest_labels, frame.symmetries) if level_rests
                   else (R, torch.arange(len(R))))
        t2, low2 = resting(R2, t[src], frame.hulls, obj[src], pl)
        R, t, low = torch.cat([R, R2]), torch.cat([t, t2]), torch.cat([low, low2])
        obj, held = torch.cat([obj, obj[src]]), torch.cat([held, torch.full((len(R2),), level_rests)])
    return _Fits(R, t, obj, held, low)


def _winners(fits: _Fits, ranked: torch.Tensor, rivals: Rivals, margin: float) -> tuple[_Fits, torch.Tensor]:
    """The fits and their ranking scores (H,) without the rows of the rivals that trail by more than ``margin``."""
    keep = rivals.rows(ranked, fits.obj, margin)
    return fits.rows(keep), ranked[keep]


def _turns(frame: FitContext, fits: _Fits, cfg: TurnConfig, ranked: torch.Tensor) -> _Fits:
    """The best fit of each of an object's ``cfg.seeds`` best-ranked rests facing up, turned about the normal by every
    ``cfg.step_deg`` of its period about it (``perception.depth_fit.starts.turned``), each fitted ``cfg.iterations``
    grid steps."""
    normal = frame.normal.double().numpy()
    fits = fits.rows(best_rows(ranked, fits.obj, cfg.seeds,
                               face=up_face(fits.R, normal, frame.ups[fits.obj])))
    R, obj, source = turned(fits.R, fits.obj, normal, cfg.step_deg, frame.symmetries)
    return _steps(frame, _Fits(R, fits.t[source], obj, fits.held[source], fits.low[source]), cfg.iterations)


def _steps(frame: FitContext, fits: _Fits, n: int, exact: bool = False) -> _Fits:
    """``n`` ICP steps (``icp``), each observed point matched to the grid's nearest model point, or with ``exact`` to
    its exact nearest one."""
    R, t = icp.steps(frame, fits.R, fits.t, fits.obj, fits.held, fits.low, n, exact)
    return dataclasses.replace(fits, R=R, t=t)
