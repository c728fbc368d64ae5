"""``posegrasp scene`` end to end, and its one-line errors on bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from helpers import refused
from posegrasp.cli import main
from posegrasp.io import read_image


def test_scene_writes_labelled_capture(tmp_path):
    out = tmp_path / "scene"
    assert main(["scene", "--seed", "2", "--blocks", "3", "--resolution", "320x240", "--out", str(out)]) == 0
    rgb, depth, mask = (read_image(out / f) for f in ("rgb.png", "depth.png", "mask.png"))
    assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
    assert depth.dtype == np.uint16 and 150 < np.median(depth[depth > 0]) < 2000  # millimetres
    assert read_image(out / "overview.png").ndim == 3
    meta = json.loads((out / "scene.json").read_text())
    assert len(meta["blocks"]) == 3 and np.asarray(meta["K"]).shape == (3, 3)
    for b in meta["blocks"]:
        assert np.asarray(b["T_cam_obj"]).shape == (4, 4)
        assert b["visible_px"] == int((mask == b["instance"]).sum())
    assert set(np.unique(mask)) <= {0, 1, 2, 3}


@pytest.mark.parametrize("args, words", [
    (["--types", "cube,dodecahedron"], "unknown block type"),
    (["--blocks", "500"], "do not fit"),
    (["--blocks", "0"], "positive"),
    (["--resolution", "0x0"], "out of range"),
    (["--resolution", "wide"], "WIDTHxHEIGHT"),
    (["--config", "/nonexistent.toml"], "does not exist"),
])
def test_bad_input_is_one_line(capsys, tmp_path, args, words):
    refused(capsys, ["scene", "--out", tmp_path / "o", *args], words)
    assert not (tmp_path / "o").exists()


def test_unwritable_output_folder(capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    refused(capsys, ["scene", "--out", blocker / "sub"], "output folder")


def test_unknown_toml_key(capsys, tmp_path):
    cfg = tmp_path / "w.toml"
    cfg.write_text("look_hieght = 0.4\n")
    refused(capsys, ["scene", "--out", tmp_path / "o", "--config", cfg], "look_hieght")
