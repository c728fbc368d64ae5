"""Evaluation runs end to end on the tiny dataset."""

import json

import numpy as np
from bop_helpers import read_results_csv

from posegrasp.perception.evaluate import EvalConfig, evaluate


def test_evaluate_writes_reports(tiny_bop, tiny_run, tmp_path):
    rep = evaluate(tiny_bop, tiny_run, tmp_path / "ev", progress=False)
    for name in ("metrics.json", "per_object.csv", "instances.csv", "curves.png", "posegrasp_tiny_bop0-test.csv"):
        assert (tmp_path / "ev" / name).exists(), name
    on_disk = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert on_disk["overall"]["n"] == rep["overall"]["n"] == 9
    assert 0 <= on_disk["segmentation"]["mIoU"] <= 100
    assert list(rep["time_per_image_s"]) == ["seg", "cls", "guided", "pose", "refine", "icp", "split", "total"]
    assert rep["ablation"]["refine_iterations"] == 2 and rep["ablation"]["classifier"]
    assert rep["time_per_image_s"]["cls"] > 0 and rep["ablation"]["icp"] and rep["ablation"]["plane"]
    assert rep["ablation"]["split_merged"] and rep["ablation"]["guided"] and rep["time_per_image_s"]["guided"] > 0


def test_evaluate_without_classifier(tiny_bop, tiny_run, tmp_path):
    rep = evaluate(tiny_bop, tiny_run, tmp_path / "ev",
                   EvalConfig(classify=False, icp=False, plane=False, guided=False), progress=False)
    assert not rep["ablation"]["classifier"] and rep["time_per_image_s"]["cls"] == 0.0
    assert not rep["ablation"]["plane"] and not rep["ablation"]["split_merged"] and not rep["ablation"]["guided"]
    assert rep["time_per_image_s"]["guided"] == 0.0
    assert not rep["ablation"]["icp"] and rep["time_per_image_s"]["icp"] == 0.0
    assert 0 <= rep["segmentation"]["mIoU"] <= 100


def test_evaluate_gt_masks_without_refinement(tiny_bop, tiny_run, tmp_path):
    rep = evaluate(tiny_bop, tiny_run, tmp_path / "ev", EvalConfig(masks="gt", refine_iterations=0), progress=False)
    assert rep["overall"]["detected"] == 100.0 and rep["segmentation"] is None
    assert rep["ablation"]["refine_iterations"] == 0 and rep["time_per_image_s"]["refine"] == 0.0
    assert rep["time_per_image_s"]["icp"] > 0  # every estimate refined against the depth image
    assert np.isfinite(rep["overall"]["mean_ADD-S"])
    res = read_results_csv(tmp_path / "ev" / "posegrasp_tiny_bop0-test.csv")
    assert len(res) == 9
