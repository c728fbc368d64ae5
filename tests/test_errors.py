"""posegrasp's exception family: one root, kinds that stand in for the builtins they replace, and a scene that
never settles recognised by its type (real MuJoCo scenes, settled with no time to settle)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from posegrasp.errors import (ConfigError, DatasetError, PerceptionError, PosegraspError, ProviderError,
                              SceneUnsettled, SimulationError, UserError, WeightsError)
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.episode import EpisodeJob, run_episode
from posegrasp.grasping.tasks import get_task
from posegrasp.perception.seg_net import SegNetConfig
from posegrasp.sim.scene import SceneConfig, make_scene


@pytest.mark.parametrize("kind, parents", [
    (UserError, (PosegraspError,)),
    (ConfigError, (UserError, ValueError)),
    (DatasetError, (UserError,)),
    (WeightsError, (UserError,)),
    (ProviderError, (UserError,)),
    (SimulationError, (PosegraspError, RuntimeError)),
    (SceneUnsettled, (SimulationError, RuntimeError)),
    (PerceptionError, (PosegraspError,)),
])
def test_every_kind_derives_from_the_root_and_the_builtin_it_replaces(kind, parents):
    assert all(issubclass(kind, p) for p in parents)
    assert not issubclass(PerceptionError, UserError) and not issubclass(SimulationError, UserError)


def test_an_unusable_model_setting_is_a_config_error_and_a_value_error():
    with pytest.raises(ConfigError, match="input_size"):
        SegNetConfig(input_size=(16, 16)).validate()
    with pytest.raises(ValueError):
        SegNetConfig(num_classes=1).validate()


def test_a_scene_that_never_settles_raises_scene_unsettled():
    with pytest.raises(SceneUnsettled, match="did not come to rest"):
        make_scene(0, 3, SceneConfig(settle_timeout=0.0), max_drops=2)


@pytest.mark.parametrize("task", ["pick-place", "stack"])
def test_an_episode_records_an_unsettled_scene_as_a_simulation_error(task):
    cfg = dataclasses.replace(TrialConfig(), task=task, scene=SceneConfig(settle_timeout=0.0))
    mount = tuple(tuple(row) for row in np.eye(4).tolist())
    rec, _ = run_episode(EpisodeJob(get_task(cfg.task), 0, 0, "oracle", cfg, mount))
    assert rec.failure == "simulation error"
