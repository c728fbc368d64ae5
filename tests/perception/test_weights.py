"""Loading mismatched or corrupt weights gives a one-line UserError."""

import json
import shutil

import pytest

from posegrasp.perception import checkpoint
from posegrasp.perception.estimator import Estimator
from posegrasp.errors import UserError


def _one_line(excinfo):
    msg = str(excinfo.value)
    assert "\n" not in msg and len(msg) < 400
    return msg


@pytest.fixture()
def run_copy(tiny_run, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(tiny_run, dst)
    return dst


def test_corrupt_safetensors(run_copy):
    p = run_copy / "pose" / "model.safetensors"
    p.write_bytes(p.read_bytes()[:1000])
    with pytest.raises(UserError) as e:
        Estimator(run_copy)
    assert "corrupt" in _one_line(e)


def test_mismatched_config(run_copy):
    cfg_path = run_copy / "seg" / "config.json"
    cfg = json.loads(cfg_path.read_text())
    cfg["model"]["width"] = 0.25
    cfg_path.write_text(json.dumps(cfg))
    with pytest.raises(UserError) as e:
        Estimator(run_copy)
    assert "do not match" in _one_line(e)


def test_wrong_stage_and_missing(run_copy, tmp_path):
    shutil.rmtree(run_copy / "refine")
    shutil.copytree(run_copy / "seg", run_copy / "refine")
    with pytest.raises(UserError) as e:
        Estimator(run_copy)
    assert "expected refine" in _one_line(e)
    with pytest.raises(UserError) as e:
        Estimator(tmp_path / "nothing")
    _one_line(e)
    (run_copy / "pose" / "config.json").write_text("{")
    with pytest.raises(UserError) as e:
        checkpoint.load_model(run_copy / "pose")
    assert "corrupt" in _one_line(e)
