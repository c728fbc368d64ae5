"""Parts too large for many to lie apart in the pick area (a cereal box, 150 x 100 x 30 mm): a scene holds only as
many as fit (``sim.scene.fitting``), so datagen and trials scenes settle instead of failing to."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import trimesh

from helpers import refused

from posegrasp.cli import main
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.scene import SceneConfig, make_scene


@pytest.fixture(scope="module")
def boxes(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("large")
    trimesh.creation.box([0.15, 0.10, 0.03]).export(d / "cereal.stl")
    assert main(["objects", "import", str(d / "cereal.stl"), "--out", str(d / "set"), "--no-progress"]) == 0
    return d / "set"


def test_datagen_scene_holds_the_parts_that_fit(boxes: Path, tmp_path: Path) -> None:
    out = tmp_path / "ds"
    assert main(["datagen", "--objects", str(boxes), "--scenes", "1", "--views", "1", "--blocks", "6",
                 "--workers", "1", "--out", str(out), "--no-progress"]) == 0
    gt = json.loads((out / "train_pbr" / "000000" / "scene_gt.json").read_text())
    assert 1 <= len(gt["0"]) <= 2  # 2 x 0.015 m^2 is half of the 0.24 x 0.30 m pick area
    assert main(["dataset", "check", str(out)]) == 0


def test_trial_scene_holds_the_parts_that_fit(boxes: Path) -> None:
    cfg = SceneConfig(workcell=dataclasses.replace(WorkcellConfig(), objects=str(boxes)))
    scene = make_scene(3, 5, cfg)
    assert 1 <= len(scene.blocks) <= 2
    assert scene.in_pick_area().all()


def test_datagen_scene_that_does_not_settle_is_one_line(capsys, tmp_path: Path) -> None:
    toml = tmp_path / "datagen.toml"
    toml.write_text("area_margin = -0.5\n")  # no part can rest that far inside the pick area
    refused(capsys, ["datagen", "--scenes", "1", "--views", "1", "--blocks", "1", "--workers", "1", "--config", toml,
                     "--out", tmp_path / "ds", "--no-progress"], "did not come to rest inside the pick area")
