"""The learned two-stage network as a perception provider: ``--perception model[:RUN_OR_WEIGHTS]``.

The hand camera's RGB-D frame goes through segmentation, instance classification, pose estimation and
depth refinement against the catalogue's block models, then merged segments split by the fitted models
(``perception.estimator.Estimator``); only the resulting ``T_cam_obj`` estimates reach the planner.
Without an argument the shipped model in ``assets/perception/model`` is used.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from posegrasp.grasping.perception import Estimate, visible_enough
from posegrasp import ASSETS
from posegrasp.errors import UserError
from posegrasp.sim.camera import Frame

if TYPE_CHECKING:  # torch is imported only when a model is asked for
    from posegrasp.perception.estimator import EstimateResult, Estimator

#: The shipped weights (seg/, pose/ and optionally refine/ checkpoints: safetensors + JSON).
SHIPPED_MODEL = ASSETS / "perception" / "model"


@functools.lru_cache(maxsize=2)
def load_estimator(weights: str) -> Estimator:
    """The trials' estimator of the run ``weights``: one torch thread, ICP against the catalogue's block meshes;
    loaded once per process and run."""
    from posegrasp.perception.estimator import Estimator, EstimatorConfig

    return Estimator(weights, EstimatorConfig(threads=1, models=ASSETS / "blocks"))


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

    def perceive(self, frame: Frame) -> EstimateResult:
        """The estimator's whole result on the hand camera's ``frame``: detections, class map and stage timings."""
        return load_estimator(self.weights)(frame.rgb, frame.depth, frame.K)

    def estimate(self, frame: Frame, seed: int) -> list[Estimate]:
        """The detections of blocks seen well enough (``min_px``) as pose estimates T_cam_obj; ``seed`` is unused
        (the estimator is deterministic)."""
        return [Estimate(d.obj_id, d.T_cam_obj, d.score) for d in self.perceive(frame).detections
                if visible_enough(int(d.mask.sum()), d.mask.shape, self.min_px)]


def from_spec(args: str | None) -> ModelProvider:
    """The provider for ``--perception model[:RUN]`` (``args``: RUN, a run folder; None: the shipped weights)."""
    path = Path(args) if args else SHIPPED_MODEL
    if not (path / "seg").is_dir() or not (path / "pose").is_dir():
        raise UserError(f"model weights {path} must hold seg/ and pose/ checkpoints (a 'posegrasp train' run folder)")
    load_estimator(str(path))  # fail early, in this process, on corrupt or mismatched weights
    return ModelProvider(str(path))
