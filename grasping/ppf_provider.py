"""The point-pair-feature estimator as a perception provider: ``--perception ppf[:SETTINGS.toml]``.

Any object set's parts are found from its models alone with OpenCV's PPF detector (``perception.ppf``): no training,
no colours. Its settings (``PpfConfig``) come from the table ``[ppf]`` of the TOML file after the colon (the defaults
without one). The trained detectors are held in memory, per process, object set and settings file: OpenCV cannot save
them, and training the shipped blocks' takes seconds (each worker process trains its own when it builds the
provider).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import ClassVar

from posegrasp.catalog import set_root
from posegrasp.config import load_toml
from posegrasp.grasping.perception import Estimate, Observation, SetProvider
from posegrasp.perception.ppf import Ppf, PpfConfig

#: The TOML table holding ``PpfConfig``.
TABLE = "ppf"


@functools.lru_cache(maxsize=4)
def load_ppf(objects: str, settings: str | None) -> Ppf:
    """The estimator of the object set ``objects`` (``""``: the shipped blocks) with the ``[ppf]`` settings of the
    TOML file ``settings`` (None: the defaults); trained once per process, set and file."""
    return Ppf(set_root(objects), load_toml(PpfConfig, settings, section=TABLE))


@dataclass(frozen=True)
class PpfProvider(SetProvider):
    """Pose estimates of the parts of the set ``objects`` from the depth image alone (module doc)."""

    kind: ClassVar[str] = "ppf"

    def estimate(self, obs: Observation, seed: int) -> list[Estimate]:
        """The parts seen in ``obs``, as pose estimates T_cam_obj (m, OpenCV camera frame)."""
        return [Estimate(d.obj_id, d.T_cam_obj, d.score) for d in load_ppf(self.objects, self.settings)(obs.depth,
                                                                                                        obs.K, seed)]


def from_spec(args: str | None, objects: str = "") -> PpfProvider:
    """The provider for ``--perception ppf[:SETTINGS.toml]`` on the object set ``objects``; trains the detectors
    here, so that a bad settings file or set fails before the campaign starts and no estimate's time limit counts
    the training."""
    settings = PpfProvider.settings_file(args)
    load_ppf(objects, settings)
    return PpfProvider(objects, settings)
