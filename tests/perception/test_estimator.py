"""The estimator on the tiny run: its result, its stages called alone, its settings and its classifier ensemble."""

import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch

from posegrasp import bop
from posegrasp.errors import UserError
from posegrasp.perception.data import label_map
from posegrasp.perception.estimator import STAGES, Detection, EstimateResult, Estimator, EstimatorConfig
from posegrasp.perception.inputs import normalize_cls_input, prepare_cls_input
from posegrasp.perception.plane import fit_support_plane
from posegrasp.perception.segmenter import ClassProbabilities
from posegrasp.perception.split import SplitConfig
from posegrasp.perception.train_cls import train_cls


def _frame(tiny_bop):
    rec = next(bop.iter_scene_images(tiny_bop, "test"))
    return rec, rec.load_rgb(), rec.load_depth(), rec.camera.K


@pytest.mark.slow
def test_estimator_api(tiny_bop, tiny_run):
    rec, rgb, depth, K = _frame(tiny_bop)
    est = Estimator(tiny_run)
    res = est(rgb, depth, K)
    assert isinstance(res, EstimateResult) and all(isinstance(d, Detection) for d in res.detections)
    assert res.labels.shape == depth.shape and res.labels.dtype == np.int64
    assert list(res.timings) == list(STAGES) and all(v >= 0 for v in res.timings.values())
    again = est(rgb, depth, K)  # no state kept between calls
    assert np.array_equal(again.labels, res.labels) and len(again.detections) == len(res.detections)
    assert est.classifier is not None and len(est.classifier.models) == 1
    assert Estimator(tiny_run, EstimatorConfig(classify=False)).classifier is None
    # every connected segment of the class map gets one label from the classifier
    labels, _ = est.segment(rgb)
    new, conf = est.classify(rgb, depth, K, labels)
    assert np.array_equal(new == 0, labels == 0) and set(np.unique(new)) <= {0, 1, 2, 3}
    assert np.all((conf > 0) <= (labels > 0)) and conf.max() <= 1.0
    masks = [(g.obj_id, rec.load_mask(g.gt_index)) for g in rec.instances]
    dets, timings = est.estimate(rgb, depth, K, masks)
    assert [d.obj_id for d in dets] == [1, 2, 3] and list(timings) == ["pose", "refiner", "depth_fit"]
    for d in dets:
        assert d.T_cam_obj.shape == (4, 4) and np.allclose(d.T_cam_obj[:3, :3] @ d.T_cam_obj[:3, :3].T, np.eye(3),
                                                           atol=1e-5)
        assert 0 <= d.score <= 1 and d.mask.shape == depth.shape
    again, _ = est.estimate(rgb, depth, K, masks)
    assert np.array_equal(again[0].T_cam_obj, dets[0].T_cam_obj)  # deterministic
    # the pose net sees pose_points points per object and pose_crop px crops (None: as trained, smaller with the
    # depth fit)
    seen = []
    for n, s in ((7, 24), (None, None)):
        e = Estimator(tiny_run, EstimatorConfig(pose_points=n, pose_crop=s))
        parts = e.pose.feat.parts_last  # (B, N, 3) points in
        e.pose.feat.parts_last = lambda x, emb, parts=parts: (seen.append(x.shape[1]), parts(x, emb))[1]
        e.pose.cnn.register_forward_hook(lambda m, x, y: seen.append(y.shape[-1]))
        e.estimate(rgb, depth, K, masks)
    assert seen == [24, 7, est.pose_cfg.crop_size, est.pose_cfg.num_points]
    fitted = Estimator(tiny_run, EstimatorConfig(models=tiny_bop))
    assert (fitted.pose_points, fitted.pose_crop) == (250, 48) != (est.pose_cfg.num_points, est.pose_cfg.crop_size)
    with pytest.raises(UserError, match=r"EstimatorConfig\.pose_points = 0 is out of range: use 1 to"):
        EstimatorConfig(pose_points=0)
    with pytest.raises(UserError, match="pose_crop = 20: use a multiple of 8 px"):
        EstimatorConfig(pose_crop=20)
    # an object whose mask has too few valid depth pixels is skipped
    holes = depth.copy()
    holes[masks[0][1]] = 0.0
    assert [d.obj_id for d in est.estimate(rgb, holes, K, masks)[0]] == [2, 3]


@pytest.mark.slow
def test_duplicates_of_one_block_are_dropped(tiny_bop, tiny_run):
    """Two detections of one type whose centres are closer than half the block's smallest side are one block: the one
    with the smaller mask goes; detections of another type, or farther apart, stay."""
    est = Estimator(tiny_run, EstimatorConfig(models=tiny_bop))
    side = est.objects[1].smallest_side

    def det(obj_id: int, x: float, pixels: int) -> Detection:
        T = np.eye(4)
        T[:3, 3] = [x, 0.0, 0.5]
        mask = np.zeros((40, 40), dtype=bool)
        mask.flat[:pixels] = True
        return Detection(obj_id=obj_id, T_cam_obj=T, score=0.5, mask=mask)

    small, large = det(1, 0.0, 100), det(1, 0.45 * side, 300)
    others = [det(2, 0.0, 50), det(1, -0.6 * side, 10)]  # another type; the same type farther off
    dets = [small, *others, large]
    kept = est.drop_duplicates(dets)
    assert len(kept) == 3 and kept[0] is others[0] and kept[2] is large  # the order is kept
    assert not any(d is small for d in kept)
    no_drop = Estimator(tiny_run, EstimatorConfig(models=tiny_bop, split=SplitConfig(duplicate=0.0)))
    assert len(no_drop.drop_duplicates(dets)) == 4


def test_estimator_runs_numpy_blas_on_one_thread(tiny_bop, tiny_run, monkeypatch):
    """Inside the estimator's methods numpy's BLAS has one thread (its spinning threads would slow torch down);
    outside, the process's setting is left as it was."""
    from threadpoolctl import threadpool_info

    import posegrasp.perception.estimator as estimator

    def blas_threads() -> set[int]:
        return {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}

    _, rgb, depth, K = _frame(tiny_bop)
    est = Estimator(tiny_run)
    before, seen = blas_threads(), []
    real = estimator.clear_plane
    monkeypatch.setattr(estimator, "clear_plane", lambda *a, **k: (seen.append(blas_threads()), real(*a, **k))[1])
    est(rgb, depth, K)
    assert seen == [{1}] and blas_threads() == before


@pytest.mark.slow
def test_segments_the_classifier_calls_not_a_block_are_dropped(tiny_bop, tiny_run, tiny_cls_config, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(tiny_run / "pose", run / "pose")
    cfg = dataclasses.replace(tiny_cls_config, background=True)
    with pytest.raises(UserError, match="background = true"):
        train_cls(tiny_bop, run, cfg, steps=2, progress=False)  # no seg/ net whose segments it learns from
    shutil.copytree(tiny_run / "seg", run / "seg")
    train_cls(tiny_bop, run, cfg, steps=2, progress=False)
    est = Estimator(run)
    assert est.classifier.cfg.obj_ids == [0, 1, 2, 3]
    rec, rgb, depth, K = _frame(tiny_bop)
    labels = label_map(rec, depth.shape)  # the ground truth as the class map (the tiny seg net finds little)
    with torch.no_grad():
        est.classifier.models[0].fc.bias[0] = 1e4  # every segment is "not a block"
    new, _ = est.classify(rgb, depth, K, labels)
    assert labels.any() and not new.any()
    parts = [labels == o for o in (1, 2, 3)]
    assert [o for o, _ in est.classifier(rgb, depth, K, parts, None)] == [0, 0, 0]
    # split off parts the classifier calls "not a block" become background
    prob = ClassProbabilities(np.zeros((4, *depth.shape), np.float32), depth.shape)
    assert [o for o, _ in est._part_types(rgb, depth, K, parts, prob, None)] == [0, 0, 0]


@pytest.mark.slow
def test_classifier_with_the_height_channel_and_an_ensemble(tiny_bop, tiny_run, tiny_cls_config, tmp_path):
    """A classifier trained on crops with the height above the plane: its 7-channel crops reach it through the
    estimator's classify and split paths, and a checkpoint without the setting loads as 6 channels; both as the
    members of an ensemble (``cls/``, ``cls_<name>/``), which must share their crop settings."""
    run = tmp_path / "run"
    for stage in ("seg", "pose"):
        shutil.copytree(tiny_run / stage, run / stage)
    model = dataclasses.replace(tiny_cls_config.model, height_range=0.06)
    train_cls(tiny_bop, run, dataclasses.replace(tiny_cls_config, model=model), steps=2, progress=False)
    est = Estimator(run)
    assert est.classifier.cfg.height_range == 0.06 and est.classifier.models[0].features[0][0].in_channels == 7
    assert Estimator(tiny_run).classifier.models[0].features[0][0].in_channels == 6
    rec, rgb, depth, K = _frame(tiny_bop)
    labels = label_map(rec, depth.shape)
    new, conf = est.classify(rgb, depth, K, labels)
    assert np.array_equal(new == 0, labels == 0) and conf.max() > 0
    parts = [labels == o for o in (1, 2, 3)]
    zero = ClassProbabilities(np.zeros((4, *depth.shape)), depth.shape)
    assert len(est._part_types(rgb, depth, K, parts, zero, None)) == 3
    # with the 6-channel classifier as a second member, the class probabilities are the members' mean
    shutil.copytree(tiny_run / "cls", run / "cls_plain")
    ens, cfg = Estimator(run).classifier, est.classifier.cfg
    assert [m.features[0][0].in_channels for m in ens.models] == [7, 6]
    plane = fit_support_plane(depth, K, est.seed, est.plane_cfg)
    x = torch.from_numpy(np.stack([normalize_cls_input(prepare_cls_input(
        rgb, depth, K, m, dataclasses.replace(cfg, height_range=0.06), plane)) for m in parts]))
    with torch.no_grad():
        p = (torch.softmax(ens.models[0](x), 1) + torch.softmax(ens.models[1](x[:, :6]), 1)) / 2
    got = ens(rgb, depth, K, parts, plane)
    assert [o for o, _ in got] == [cfg.obj_ids[k] for k in p.argmax(1)]
    np.testing.assert_allclose([pp for _, pp in got], p.max(1).values, rtol=1e-5)
    meta = json.loads((run / "cls_plain" / "config.json").read_text())
    meta["model"]["crop_size"] = 64
    (run / "cls_plain" / "config.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="cls_plain differs from .* crop settings"):
        Estimator(run)


def test_a_seg_net_with_a_seam_head_cuts_its_segments_along_the_seams(tiny_bop, tiny_run, tmp_path):
    """The tiny run's seg net made to call every pixel object 1, with a seam head: seams seen nowhere, the estimator
    finds what the net without the head finds (one part: the whole frame); seen everywhere, no part is left."""
    from posegrasp.perception import checkpoint
    from posegrasp.perception.seg_net import build_seg_net

    rec, rgb, depth, K = _frame(tiny_bop)
    trained, cfg, _ = checkpoint.load_model(tiny_run / "seg", "seg")
    found = {}
    for seams in (None, -1e4, 1e4):
        net_cfg = dataclasses.replace(cfg, seams=seams is not None)
        net = build_seg_net(net_cfg)
        net.load_state_dict({**net.state_dict(), **trained.state_dict()})
        with torch.no_grad():
            net.classifier.weight.zero_()
            net.classifier.bias.copy_(torch.tensor([0.0, 10.0, 0.0, 0.0]))
            if seams is not None:
                net.seam.bias.fill_(seams)
        run = tmp_path / str(seams)
        shutil.copytree(tiny_run / "pose", run / "pose")
        checkpoint.save(run / "seg", "seg", net, net_cfg, None, {"step": 0})
        found[seams] = [(d.obj_id, d.mask.tobytes()) for d in
                        Estimator(run, EstimatorConfig(classify=False))(rgb, depth, K).detections]
    assert len(found[None]) == 1 and found[-1e4] == found[None] and found[1e4] == []


@pytest.mark.slow
def test_the_type_check_corrects_a_classifier_that_is_unsure_and_wrong(tiny_bop, tiny_run):
    """Each true mask offered as the wrong type at p 0.6 and its own at 0.4: the fits of the two types tell the
    parts apart (a cylinder against an L or a box), so the check keeps the true types; with the classifier's belief
    weighed beyond any fit it keeps the wrong ones. The class map follows the chosen types."""
    from posegrasp.perception.type_check import TypeCheckConfig

    rec, rgb, depth, K = _frame(tiny_bop)
    parts = [(g.obj_id, rec.load_mask(g.gt_index)) for g in rec.instances]
    wrong = {1: 2, 2: 3, 3: 2}
    cands = [[(wrong[o], 0.6), (o, 0.4)] for o, _ in parts]
    prob = ClassProbabilities(np.zeros((4, *depth.shape), np.float32), depth.shape)
    labels = np.zeros(depth.shape, dtype=np.int64)
    chosen = {}
    for weight in (0.001, 1.0):
        est = Estimator(tiny_run, EstimatorConfig(models=tiny_bop, type_check=TypeCheckConfig(weight=weight)))
        dets, stages, new = est.check_types(rgb, depth, K, parts, cands, prob, None, labels)
        assert list(stages) == ["pose", "refiner", "depth_fit"] and len(dets) == len(parts)
        assert all(np.all(new[d.mask] == d.obj_id) for d in dets) and not labels.any()
        chosen[weight] = [d.obj_id for d in dets]
    assert chosen[0.001] == [o for o, _ in parts]
    assert chosen[1.0] == [wrong[o] for o, _ in parts]
