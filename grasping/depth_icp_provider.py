"""The training-free estimator as a perception provider: ``--perception depth-icp[:SETTINGS.toml]``.

Any object set can be trialled the moment it is imported: the parts are cut out of the hand camera's depth image
against the table (or tote floor) and fitted with the set's own models (``perception.depth_icp``); the set's colours
help tell parts apart. Its settings (``DepthIcpConfig``) come from the table ``[depth_icp]`` of the TOML file after
the colon (the defaults without one).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from posegrasp.catalog import catalog_by_id, set_root
from posegrasp.config import load_toml
from posegrasp.grasping.perception import Estimate, Observation, SetProvider
from posegrasp.perception.depth_icp import DepthIcp, DepthIcpConfig

#: The TOML table holding ``DepthIcpConfig``.
TABLE = "depth_icp"


@functools.lru_cache(maxsize=4)
def load_depth_icp(objects: str, settings: str | None) -> DepthIcp:
    """The estimator of the object set ``objects`` (``""``: the shipped blocks) with the ``[depth_icp]`` settings of
    the TOML file ``settings`` (None: the defaults); built once per process, set and file."""
    cfg = load_toml(DepthIcpConfig, settings, section=TABLE)
    rgb = {o: np.asarray(p.rgba[:3]) for o, p in catalog_by_id(objects).items()}
    return DepthIcp(set_root(objects), rgb, cfg)


@dataclass(frozen=True)
class DepthIcpProvider(SetProvider):
    """Pose estimates of the parts of the set ``objects`` from the depth image and colours alone (module doc)."""

    kind: ClassVar[str] = "depth-icp"

    def estimate(self, obs: Observation, seed: int) -> list[Estimate]:
        """The parts seen in ``obs``, as pose estimates T_cam_obj (m, OpenCV camera frame)."""
        dets = load_depth_icp(self.objects, self.settings)(obs.rgb, obs.depth, obs.K, seed)
        return [Estimate(d.obj_id, d.T_cam_obj, d.score) for d in dets]


def from_spec(args: str | None, objects: str = "") -> DepthIcpProvider:
    """The provider for ``--perception depth-icp[:SETTINGS.toml]`` on the object set ``objects``; builds the
    estimator here, so that a bad settings file or set fails before the campaign starts."""
    settings = DepthIcpProvider.settings_file(args)
    load_depth_icp(objects, settings)
    return DepthIcpProvider(objects, settings)
