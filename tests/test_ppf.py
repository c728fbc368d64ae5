"""The point-pair-feature estimator (``--perception ppf``) on the real simulator's rendered tabletop, and ``posegrasp
eval --perception SPEC`` on a small rendered test split."""

from __future__ import annotations

import json

import numpy as np
import pytest

from helpers import refused, run_cli
from test_depth_icp import _look_frame
from posegrasp import bop
from posegrasp.bop.results import read_results_csv
from posegrasp.catalog import catalog_by_id, symmetry_transforms
from posegrasp.datagen.config import load_datagen_config
from posegrasp.datagen.generate import generate_dataset
from posegrasp.errors import UserError
from posegrasp.geometry import rotation_angle
from posegrasp.grasping.bop_csv import from_spec as bop_csv
from posegrasp.grasping.perception import OracleProvider, observation
from posegrasp.grasping.ppf_provider import PpfProvider
from posegrasp.grasping.provider_registry import make_provider

#: Settings that train and refine faster than the defaults (coarser sampling, OpenCV's ICP): for the CLI's paths.
FAST = "[ppf]\nsampling = 0.1\nrefine = \"icp\"\n"


def _error(truth, estimate) -> tuple[float, float]:
    """Translation (m) and rotation (deg) error of ``estimate`` from ``truth`` under the part's symmetries."""
    T = estimate.T_cam_obj
    poses = truth.T_cam_obj @ symmetry_transforms(catalog_by_id()[truth.obj_id])
    return min((float(np.linalg.norm(P[:3, 3] - T[:3, 3])), float(np.degrees(rotation_angle(P[:3, :3], T[:3, :3]))))
               for P in poses)


@pytest.mark.slow
def test_ppf_finds_one_block_within_5_mm_and_5_deg():
    frame = _look_frame(0, 1)  # one arch, alone in the pick area
    (truth,) = OracleProvider(min_px=500).estimate_truth(frame, 0)
    provider = make_provider("ppf")
    assert isinstance(provider, PpfProvider) and provider.name == "ppf"
    found = provider.estimate(observation(frame), seed=0)
    assert found and found[0].obj_id == truth.obj_id, [e.obj_id for e in found]
    dist, deg = _error(truth, found[0])
    assert dist < 0.005 and deg < 5.0, (dist, deg)
    assert all(np.linalg.norm(e.T_cam_obj[:3, 3] - truth.T_cam_obj[:3, 3]) < 0.03 for e in found)  # no other part


def test_ppf_settings_come_from_their_table(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[ppf]\nsample = 0.1\n")
    with pytest.raises(UserError, match="unknown key.*sample"):
        make_provider(f"ppf:{bad}")
    bad.write_text("[ppf]\nsampling = 0\n")
    with pytest.raises(UserError, match="sampling = 0.0 is out of range"):
        make_provider(f"ppf:{bad}")


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    """A test split of one scene, two views, of a brick and a cylinder at 320x240, and a fast ppf settings file."""
    root = tmp_path_factory.mktemp("ppf")
    (root / "small.toml").write_text("blocks = [3, 5]\n[workcell.hand_camera]\nwidth = 320\nheight = 240\n")
    (root / "fast.toml").write_text(FAST)
    generate_dataset(root / "data", 1, 2, 3, load_datagen_config(root / "small.toml"), split="test", workers=1)
    return root


@pytest.mark.slow
def test_eval_scores_a_provider_into_a_results_csv_bop_csv_reads(split, tmp_path):
    out = tmp_path / "eval"
    res = run_cli("eval", "--data", str(split / "data"), "--perception", f"ppf:{split / 'fast.toml'}", "--out",
                  str(out), "--no-progress")
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout.splitlines()[-1])
    assert 0.0 <= summary["bop19"]["ar"] <= 1.0 and summary["segmentation"] is None
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["perception"] == f"ppf:{split / 'fast.toml'}" and metrics["images"] == 2
    assert set(metrics["time_per_image_s"]) == {"provider", "total"}
    assert {"per_object.csv", "instances.csv", "curves.png", "scores_bop19.json"} <= {p.name for p in out.iterdir()}
    (csv,) = out.glob("posegrasp_data-test.csv")
    rows = read_results_csv(csv)
    assert rows and {(r.scene_id, r.im_id) for r in rows} <= {(0, 0), (0, 1)}
    assert len(bop_csv(str(csv)).rows()) == len(rows)  # the replay provider's checks take it
    again = run_cli("eval", "--data", str(split / "data"), "--perception", f"bop-csv:{csv}", "--out",
                    str(tmp_path / "replay"), "--no-progress")
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout.splitlines()[-1])["bop19"]["ar"] == summary["bop19"]["ar"]


@pytest.mark.parametrize("args, says", [
    (["--perception", "nope"], "unknown perception 'nope'"),
    (["--perception", "oracle"], "reads the simulator's labels"),
    (["--perception", "ppf:missing.toml"], "does not exist"),
    (["--perception", "ppf", "--no-refiner"], "--no-refiner chooses the network's stages"),
    (["--perception", "ppf", "--weights", "."], "not both"),
])
def test_eval_refuses_a_bad_provider_in_one_line_writing_nothing(capsys, split, tmp_path, args, says):
    out = tmp_path / "eval"
    refused(capsys, ["eval", "--data", split / "data", "--out", out, "--no-progress", *args], says)
    assert not out.exists()


def test_eval_refuses_a_dataset_of_another_object_set(capsys, split, tmp_path):
    other = tmp_path / "data"
    other.mkdir()
    (other / "models").mkdir()
    (other / "models" / "models_info.json").write_text("{}")
    refused(capsys, ["eval", "--data", other, "--perception", "ppf", "--out", tmp_path / "eval"], "--objects SET")
    assert not (tmp_path / "eval").exists()
    assert bop.models_info_path(split / "data").is_file()
