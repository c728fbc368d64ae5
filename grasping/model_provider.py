"""The learned two-stage network as a perception provider: ``--perception model[:RUN_OR_WEIGHTS]``.

The hand camera's RGB-D frame goes through segmentation, instance classification, pose estimation and
depth fit against the catalogue's block models, then merged segments split by the fitted models
(``perception.estimator.Estimator``); only the resulting ``T_cam_obj`` estimates reach the planner.
Without an argument the shipped model in ``assets/perception/model`` is used.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from posegrasp.grasping.perception import Estimate, Observation, visible_enough
from posegrasp import ASSETS
from posegrasp.catalog import set_root
from posegrasp.errors import WeightsError

if TYPE_CHECKING:  # torch is imported only when a model is asked for
    from posegrasp.perception.estimator import EstimateResult, Estimator

#: The shipped weights (seg/, pose/ and optionally refiner/ checkpoints: safetensors + JSON).
SHIPPED_MODEL = ASSETS / "perception" / "model"


@functools.lru_cache(maxsize=2)
def load_estimator(weights: str, objects: str = "") -> Estimator:
    """The trials' estimator of the run ``weights``: one torch thread, ICP against the models of the object set
    ``objects`` (``""``: the shipped blocks); loaded once per process, run and set."""
    from posegrasp.perception.estimator import Estimator, EstimatorConfig

    return Estimator(weights, EstimatorConfig(threads=1, models=set_root(objects)))


@dataclass(frozen=True)
class ModelProvider:
    """Pose estimates from a trained run directory; one estimator per worker process, loaded on first use.
    Like the oracle, it reports no block from a mask of fewer than ``min_px`` pixels at 640x480: a sliver
    cut off a block's edge gives an unreliable class and pose."""

    weights: str
    min_px: int = 150
    objects: str = ""  # the object set whose models the ICP fits (``""``: the shipped blocks)

    @property
    def name(self) -> str:
        return f"model:{self.weights}"

    def perceive(self, obs: Observation) -> EstimateResult:
        """The estimator's whole result on the hand camera's ``obs``: detections, class map and stage timings."""
        return load_estimator(self.weights, self.objects)(obs.rgb, obs.depth, obs.K)

    def estimate(self, obs: Observation, seed: int) -> list[Estimate]:
        """The detections of blocks seen well enough (``min_px``) as pose estimates T_cam_obj; ``seed`` is unused
        (the estimator is deterministic)."""
        return self.select(self.perceive(obs))

    def select(self, result: EstimateResult) -> list[Estimate]:
        """The detections of ``result`` seen well enough (``min_px``), as pose estimates T_cam_obj."""
        return [Estimate(d.obj_id, d.T_cam_obj, d.score) for d in result.detections
                if visible_enough(int(d.mask.sum()), d.mask.shape, self.min_px)]


def from_spec(args: str | None, objects: str = "") -> ModelProvider:
    """The provider for ``--perception model[:RUN]`` (``args``: RUN, a run folder; None: the shipped weights) on
    the object set ``objects``."""
    path = Path(args) if args else SHIPPED_MODEL
    if not (path / "seg").is_dir() or not (path / "pose").is_dir():
        raise WeightsError(f"model weights {path} must hold seg/ and pose/ checkpoints "
                           "(a 'posegrasp train' run folder)")
    load_estimator(str(path), objects)  # fail early, in this process, on corrupt or mismatched weights
    return ModelProvider(str(path), objects=objects)
