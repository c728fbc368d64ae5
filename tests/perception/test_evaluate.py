"""Evaluation runs end to end on the tiny dataset."""

import json

import numpy as np
import pytest
from bop_helpers import read_results_csv

from posegrasp import bop

from posegrasp.perception import bop19 as B
from posegrasp.perception.evaluate import EvalConfig, evaluate


@pytest.mark.slow
def test_evaluate_writes_reports(tiny_bop, tiny_run, tmp_path):
    rep = evaluate(tiny_bop, tiny_run, tmp_path / "ev", progress=False)
    for name in ("metrics.json", "per_object.csv", "instances.csv", "curves.png", f"posegrasp_{tiny_bop.name}-test.csv",
                 "scores_bop19.json"):
        assert (tmp_path / "ev" / name).exists(), name
    bop19 = json.loads((tmp_path / "ev" / "scores_bop19.json").read_text())
    # no test_targets_bop19.json: the targets are the instances at least 10 % visible
    n_targets = sum(g.info.visib_fract >= 0.1 for r in bop.iter_scene_images(tiny_bop, "test") for g in r.instances)
    assert bop19["targets"] == rep["bop19"]["targets"] == n_targets
    for k in ("ar", "ar_vsd", "ar_mssd", "ar_mspd"):
        assert 0 <= bop19[k] <= 1 and bop19[k] == rep["bop19"][k]
    assert bop19["ar"] == pytest.approx((bop19["ar_vsd"] + bop19["ar_mssd"] + bop19["ar_mspd"]) / 3)
    assert set(bop19["per_object"]) == {"1", "2", "3"}
    assert sum(b["targets"] for b in rep["bop19"]["ar_by_visib"]) == n_targets
    assert [b["visib"] for b in rep["bop19"]["ar_by_visib"]] == [list(b) for b in B.VISIB_BINS]
    o = rep["overall"]
    assert 0 <= o["re_sym_<15deg"] <= 100
    assert o["detected"] == 0 or o["re_sym_<15deg"] <= o["re_sym_<15deg_of_detected"]
    on_disk = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert on_disk["overall"]["n"] == rep["overall"]["n"] == 9
    assert 0 <= on_disk["segmentation"]["mIoU"] <= 100
    inst = on_disk["instances"]
    assert inst["parts"] == 9 and 0 <= inst["recall"] <= inst["recall_any_type"] <= 100
    assert (0 <= inst["precision"] <= 100 if inst["detections"] else inst["precision"] is None)
    assert inst["iou_above"] == 0.5
    assert "mask_iou" in (tmp_path / "ev" / "instances.csv").read_text().splitlines()[0].split(",")
    assert list(rep["time_per_image_s"]) == ["seg", "cls", "guided", "pose", "refiner", "depth_fit", "split", "total"]
    assert rep["ablation"]["refiner_iterations"] == 2 and rep["ablation"]["classifier"]
    assert rep["time_per_image_s"]["cls"] > 0 and rep["ablation"]["depth_fit"] and rep["ablation"]["plane"]
    assert rep["ablation"]["split_merged"] and rep["ablation"]["guided"] and rep["time_per_image_s"]["guided"] > 0


@pytest.mark.slow
def test_evaluate_without_classifier(tiny_bop, tiny_run, tmp_path):
    rep = evaluate(tiny_bop, tiny_run, tmp_path / "ev",
                   EvalConfig(classify=False, depth_fit=False, plane=False, guided=False), progress=False)
    assert not rep["ablation"]["classifier"] and rep["time_per_image_s"]["cls"] == 0.0
    assert not rep["ablation"]["plane"] and not rep["ablation"]["split_merged"] and not rep["ablation"]["guided"]
    assert rep["time_per_image_s"]["guided"] == 0.0
    assert not rep["ablation"]["depth_fit"] and rep["time_per_image_s"]["depth_fit"] == 0.0
    assert 0 <= rep["segmentation"]["mIoU"] <= 100


@pytest.mark.slow
def test_evaluate_gt_masks_without_the_refiner(tiny_bop, tiny_run, tmp_path):
    rep = evaluate(tiny_bop, tiny_run, tmp_path / "ev", EvalConfig(masks="gt", refiner_iterations=0), progress=False)
    assert rep["overall"]["detected"] == 100.0 and rep["segmentation"] is None and "instances" not in rep
    assert rep["ablation"]["refiner_iterations"] == 0 and rep["time_per_image_s"]["refiner"] == 0.0
    assert rep["time_per_image_s"]["depth_fit"] > 0  # every estimate fitted to the depth image
    assert np.isfinite(rep["overall"]["mean_ADD-S"])
    res = read_results_csv(tmp_path / "ev" / f"posegrasp_{tiny_bop.name}-test.csv")
    assert len(res) == 9


def test_evaluate_scores_the_listed_bop19_targets(tiny_bop, tiny_run, tmp_path):
    """With ``test_targets_bop19.json`` only the listed images and objects count, each with its inst_count."""
    import shutil

    data = tmp_path / "ds"
    shutil.copytree(tiny_bop, data)
    bop.write_test_targets(data, [bop.EvalTarget(1, 0, 3, 1), bop.EvalTarget(1, 2, 1, 1)])
    rep = evaluate(data, tiny_run, tmp_path / "ev", EvalConfig(masks="gt", depth_fit=False), progress=False)
    assert rep["bop19"]["targets"] == 2
    scores = json.loads((tmp_path / "ev" / "scores_bop19.json").read_text())
    assert sorted(scores["per_object"]) == ["1", "3"] and scores["per_object"]["3"]["targets"] == 1
