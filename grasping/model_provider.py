"""The learned two-stage network as a perception provider: ``--perception model[:RUN_OR_WEIGHTS]``.

The hand camera's RGB-D frame goes through segmentation, instance classification, pose estimation and
depth refinement against the catalogue's block models, then merged segments split by the fitted models
(``perception.inference.Estimator``); only the resulting ``T_cam_obj`` estimates reach the planner.
Without an argument the shipped model in ``assets/perception/model`` is used.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

from posegrasp.grasping.perception import Estimate, register, visible_enough
from posegrasp import ASSETS
from posegrasp.errors import UserError
from posegrasp.sim.camera import Frame

#: The shipped weights (seg/, pose/ and optionally refine/ checkpoints: safetensors + JSON).
SHIPPED_MODEL = ASSETS / "perception" / "model"


@functools.lru_cache(maxsize=2)
def _estimator(weights: str):
    from posegrasp.perception.inference import Estimator

    return Estimator(weights, threads=1, models=ASSETS / "blocks")  # the catalogue's meshes, for ICP


@dataclass(frozen=True)
class ModelProvider:
    """Pose estimates from a trained run directory; one estimator per worker process, loaded on first use.
    Like the oracle, it reports no block from a mask of fewer than ``min_px`` pixels at 640x480: a sliver
    cut off a block's edge gives an unreliable class and pose."""

    weights: str
    min_px: int = 150

    @property
    def name(self) -> str:
        return f"model:{self.weights}"

    def estimate(self, frame: Frame, seed: int) -> list[Estimate]:
        dets = _estimator(self.weights)(frame.rgb, frame.depth, frame.K)
        return [Estimate(d.obj_id, d.T_cam_obj, d.score) for d in dets
                if visible_enough(int(d.mask.sum()), d.mask.shape, self.min_px)]


def _model(args: str | None) -> ModelProvider:
    path = Path(args) if args else SHIPPED_MODEL
    if not (path / "seg").is_dir() or not (path / "pose").is_dir():
        raise UserError(f"model weights {path} must hold seg/ and pose/ checkpoints (a 'posegrasp train' run folder)")
    _estimator(str(path))  # fail early, in this process, on corrupt or mismatched weights
    return ModelProvider(str(path))


register("model", _model)
