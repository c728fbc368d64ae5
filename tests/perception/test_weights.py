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
    shutil.rmtree(run_copy / "refiner")
    shutil.copytree(run_copy / "seg", run_copy / "refiner")
    with pytest.raises(UserError) as e:
        Estimator(run_copy)
    assert "expected refiner" in _one_line(e)
    with pytest.raises(UserError) as e:
        Estimator(tmp_path / "nothing")
    _one_line(e)
    (run_copy / "pose" / "config.json").write_text("{")
    with pytest.raises(UserError) as e:
        checkpoint.load_model(run_copy / "pose")
    assert "corrupt" in _one_line(e)


def test_a_run_with_the_refiner_under_its_old_folder_name_loads(run_copy, capsys):
    """A run folder written before the refiner's folder was named ``refiner/`` holds it as ``refine/``: it loads as
    it is, with a notice naming the new name; the checkpoint's files carry the stage tag ``refine`` either way."""
    assert json.loads((run_copy / "refiner" / "config.json").read_text())["stage"] == "refine"
    new = Estimator(run_copy)
    (run_copy / "refiner").rename(run_copy / "refine")
    capsys.readouterr()
    old = Estimator(run_copy)
    assert old.refiner is not None and old.refiner_iterations == new.refiner_iterations == 2
    assert all((a == b).all() for a, b in zip(old.refiner.state_dict().values(), new.refiner.state_dict().values()))
    assert capsys.readouterr().err == (f"posegrasp: note: {run_copy / 'refine'} is read as the refiner checkpoint: "
                                       "its folder is now named refiner/\n")
