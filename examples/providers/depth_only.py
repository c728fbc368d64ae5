"""How a perception plug-in is written, on a depth-only pose estimator: no learning, no colour.

    posegrasp trials --perception py:examples/providers/depth_only.py:make_provider --episodes 20 --out runs/depth

A plug-in is a factory that posegrasp calls once per process with ARGS (the text after the factory's name, or None)
and, when it has a parameter named ``objects``, the object set's folder; it returns any object with a ``name`` and an
``estimate(obs, seed)`` method (``docs/estimators.md``). ``estimate`` gets the hand camera's ``Observation`` (RGB
uint8, depth in metres, K) and a seed, and returns ``Estimate(obj_id, T_cam_obj, score)`` with ``T_cam_obj`` in metres
in the OpenCV camera frame.

This one wraps the built-in training-free estimator (``--perception depth-icp``, ``posegrasp.perception.depth_icp``)
with its colour cuts turned off: the table plane, blobs standing on it cut at depth edges, and each blob fitted by ICP
with every model of the set whose size can explain it; the best score wins. ARGS (optional):
``MIN_HEIGHT_MM,MAX_POINTS``, e.g. ``make_provider:5,200``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from posegrasp.errors import UserError
from posegrasp.grasping.perception import Estimate, Observation
from posegrasp.perception.depth_icp import DepthIcp, DepthIcpConfig


@dataclass
class DepthOnlyProvider:
    """Pose estimates from the depth image alone (module doc)."""

    estimator: DepthIcp
    name: str = "depth-only"

    def estimate(self, obs: Observation, seed: int) -> list[Estimate]:
        """The parts seen in ``obs``, as pose estimates T_cam_obj (m, OpenCV camera frame)."""
        return [Estimate(d.obj_id, d.T_cam_obj, d.score) for d in self.estimator(obs.rgb, obs.depth, obs.K, seed)]


def make_provider(args: str | None, objects: str) -> DepthOnlyProvider:
    """The plug-in's factory: ``py:examples/providers/depth_only.py:make_provider[:MIN_HEIGHT_MM,MAX_POINTS]``;
    ``objects`` is the object set's folder (posegrasp passes it)."""
    cfg = DepthIcpConfig(colour_edge=0.0)
    if args:
        try:
            mm, n = args.split(",")
            min_height, max_points = float(mm) / 1000, int(n)
        except ValueError:
            raise UserError(f"depth-only ARGS {args!r} are not MIN_HEIGHT_MM,MAX_POINTS, e.g. 5,200") from None
        fit = dataclasses.replace(cfg.depth_fit.fit, max_points=max_points)
        cfg = dataclasses.replace(cfg, min_height=min_height, depth_fit=dataclasses.replace(cfg.depth_fit, fit=fit))
    return DepthOnlyProvider(DepthIcp(objects, cfg=cfg))
