"""Datasets over the tiny BOP dataset: geometry consistency, determinism, augmentation, skipping."""

import json
import shutil

import numpy as np
import pytest
import torch

from posegrasp.perception.classifier import ClassifierConfig
from posegrasp.perception.data import ClsDataset, CropSource, DataConfig, PoseDataset, SegDataset, collate
from posegrasp.perception.inputs import segment_components
from posegrasp.perception.metrics import nearest_distances
from posegrasp.perception.pose_net import PoseNetConfig


def _pose(obj_ids: list[int], num_points: int, crop_size: int) -> PoseNetConfig:
    """A pose net's settings for the tiny dataset's objects ``obj_ids``."""
    return PoseNetConfig(obj_ids=obj_ids, symmetric=[o != 1 for o in obj_ids], num_points=num_points,
                         crop_size=crop_size)


def _cls(obj_ids: list[int], side: float = 0.16) -> ClassifierConfig:
    """An instance classifier's settings: 32 px crops of ``side`` m."""
    return ClassifierConfig(obj_ids=obj_ids, crop_size=32, crop_side=side, depth_range=0.05)


def test_pose_samples_are_consistent(tiny_bop):
    ds = PoseDataset(tiny_bop, "train", _pose([1, 2, 3], 100, 48))
    assert len(ds) >= 20
    s = ds.get(0)
    assert s["image"].shape == (3, 48, 48) and s["choose"].shape == (100,) and int(s["choose"].max()) < 48 * 48
    assert s["points"].shape == (100, 3) and s["model_points"].shape == (128, 3)
    # the depth cloud lies on the model under the ground truth (metres, within sampling density)
    d = nearest_distances(s["points"].numpy(), s["target"].numpy())
    assert d.mean() < 0.005
    T = s["T"].numpy()
    np.testing.assert_allclose(s["model_points"].numpy() @ T[:3, :3].T + T[:3, 3], s["target"].numpy(), atol=1e-6)
    assert s["symmetric"] == (s["obj_id"] != 1)
    # the target under each discrete symmetry covers the same surface (box: 3 flips -> 4 copies)
    assert ds.num_sym == 4 and s["sym_targets"].shape == (4, 128, 3)
    box = next(ds.get(i) for i in range(len(ds)) if ds.get(i)["obj_id"] == 3)
    assert torch.equal(box["sym_targets"][0], box["target"]) and not box["continuous"]
    for k in range(1, 4):
        assert nearest_distances(box["sym_targets"][k].numpy(), box["target"].numpy()).mean() < 0.004
        assert (box["sym_targets"][k] - box["target"]).norm(dim=-1).mean() > 0.005
    b = collate([ds.get(i) for i in range(3)])
    assert b["points"].shape == (3, 100, 3) and b["obj"].dtype == torch.int64


def test_augmentation_is_seeded(tiny_bop):
    ds = PoseDataset(tiny_bop, "train", _pose([1, 2, 3], 64, 32), augment=True, seed=3)
    a, b, c = ds.get(2, key=11), ds.get(2, key=11), ds.get(2, key=12)
    assert torch.equal(a["points"], b["points"]) and torch.equal(a["image"], b["image"])
    assert not torch.equal(a["points"], c["points"])
    plain = ds.get(2)
    # translation noise moves cloud and target together
    shift = (a["target"] - a["model_points"] @ a["T"][:3, :3].T.float()).mean(0)
    assert torch.allclose(shift, a["T"][:3, 3].float(), atol=1e-5)
    assert not torch.equal(plain["image"], a["image"])


def test_instances_are_filtered(tiny_bop):
    all_ = PoseDataset(tiny_bop, "train", _pose([1, 2, 3], 64, 32))
    strict = PoseDataset(tiny_bop, "train", _pose([1, 2, 3], 64, 32), DataConfig(min_visib_fract=0.99, min_points=150))
    assert 0 < len(strict) < len(all_)
    only1 = PoseDataset(tiny_bop, "train", _pose([1], 64, 32))
    assert all(only1.get(i)["obj_id"] == 1 for i in range(len(only1)))


def test_seg_samples(tiny_bop):
    ds = SegDataset(tiny_bop, "train", (96, 128), num_classes=4, augment=True, seed=0)
    s = ds.get(0)
    assert s["image"].shape == (3, 96, 128) and s["label"].shape == (96, 128)
    assert set(s["label"].unique().tolist()) <= {0, 1, 2, 3} and len(s["label"].unique()) >= 3
    assert torch.equal(ds.get(1, key=5)["label"], ds.get(1, key=5)["label"])
    from posegrasp.errors import UserError

    with pytest.raises(UserError, match="classes"):
        SegDataset(tiny_bop, "train", (96, 128), num_classes=3).get(0)


def test_cls_samples_from_gt_and_from_segments(tiny_bop):
    from posegrasp.perception.data import label_map, load_records

    gt_only = ClsDataset(tiny_bop, "train", _cls([1, 2, 3]),
                         source=CropSource(segmenter=lambda rgb: []))
    by_rgb = {r.load_rgb().tobytes(): r for r in load_records(tiny_bop, "train")}

    def perfect(rgb):  # a segmenter that returns the ground truth's segments
        return segment_components(label_map(by_rgb[rgb.tobytes()], rgb.shape[:2]), 1)

    both = ClsDataset(tiny_bop, "train", _cls([1, 2, 3]), augment=True, seed=1, source=CropSource(perfect))
    assert len(gt_only) >= 20 and len(both) > len(gt_only)
    assert sorted(set(both.labels.tolist())) == [0, 1, 2]
    a, b, c = both.get(3, key=7), both.get(3, key=7), both.get(3, key=8)
    assert a["image"].shape == (6, 32, 32) and torch.equal(a["image"], b["image"])
    assert not torch.equal(a["image"], c["image"]) and a["label"] == both.get(3)["label"]


def test_cls_crops_are_cached_for_the_same_segmenter_and_settings(tiny_bop, tmp_path):
    calls = []
    perfect = ground_truth_segmenter(tiny_bop, calls)

    def unusable(rgb):
        raise AssertionError("the segmenter ran although its crops are cached")

    cache = tmp_path / "c" / "crops.npy"
    model = _cls([0, 1, 2, 3])
    first = ClsDataset(tiny_bop, "train", model, source=CropSource(perfect, "a", cache))
    assert len(calls) == 8 and sorted(p.name for p in (tmp_path / "c").iterdir()) == ["crops.json", "crops.npy"]
    again = ClsDataset(tiny_bop, "train", model, augment=True, source=CropSource(unusable, "a", cache))
    assert np.array_equal(np.asarray(again.crops), np.stack(first.crops)) and np.array_equal(again.labels, first.labels)
    assert torch.equal(again.get(2)["image"], first.get(2)["image"])
    with pytest.raises(AssertionError, match="cached"):  # another segmenter: computed anew
        ClsDataset(tiny_bop, "train", model, source=CropSource(unusable, "b", cache))
    with pytest.raises(AssertionError, match="cached"):  # other crop settings: computed anew
        ClsDataset(tiny_bop, "train", _cls([0, 1, 2, 3], side=0.2), source=CropSource(unusable, "a", cache))
    assert len(ClsDataset(tiny_bop, "train", model, source=CropSource(unusable, "a", cache))) == len(first)
    ds = shutil.copytree(tiny_bop, tmp_path / "ds")  # a dataset generated anew in the same place: computed anew
    ClsDataset(ds, "train", model, source=CropSource(ground_truth_segmenter(ds, calls), "a", cache))
    gt_file = ds / "train" / "000000" / "scene_gt.json"
    gt = json.loads(gt_file.read_text())
    gt["0"][0]["cam_t_m2c"][0] += 1.0  # mm
    gt_file.write_text(json.dumps(gt))
    with pytest.raises(AssertionError, match="cached"):
        ClsDataset(ds, "train", model, source=CropSource(unusable, "a", cache))


def ground_truth_segmenter(root, calls):
    """A segmenter returning the ground truth of the dataset at ``root`` (calls counted in ``calls``)."""
    from posegrasp.perception.data import label_map, load_records

    by_rgb = {r.load_rgb().tobytes(): r for r in load_records(root, "train")}

    def seg(rgb):
        calls.append(1)
        return segment_components(label_map(by_rgb[rgb.tobytes()], rgb.shape[:2]), 1)
    return seg


def test_cls_background_samples_are_segments_mostly_off_the_objects(tiny_bop):
    from posegrasp.perception.data import label_map, load_records

    by_rgb = {r.load_rgb().tobytes(): r for r in load_records(tiny_bop, "train")}
    placed = []

    def with_blobs(rgb):
        """The ground truth plus two 10x10 segments over an object's edge (the tiny set has no depth off the
        objects): one with 10-20 of its pixels on the object (a background sample), one with 30-45 (left out)."""
        gt = label_map(by_rgb[rgb.tobytes()], rgb.shape[:2])
        lab, taken = gt.copy(), np.zeros(gt.shape, bool)
        for lo, hi in ((10, 20), (30, 45)):
            for y in range(1, gt.shape[0] - 11, 3):
                x = next((x for x in range(1, gt.shape[1] - 11, 3) if lo <= (gt[y:y + 10, x:x + 10] > 0).sum() <= hi
                          and not taken[y - 1:y + 11, x - 1:x + 11].any()), None)
                free = set(range(1, 4)) - set(np.unique(gt[y - 1:y + 11, x - 1:x + 11]).tolist()) if x else ()
                if free:  # a class of its own among its neighbours: its own segment
                    lab[y:y + 10, x:x + 10], taken[y:y + 10, x:x + 10] = min(free), True
                    placed.append(lo)
                    break
        return segment_components(lab, 1)

    plain = ClsDataset(tiny_bop, "train", _cls([1, 2, 3]), source=CropSource(with_blobs))
    n_off = placed.count(10)
    with_bg = ClsDataset(tiny_bop, "train", _cls([0, 1, 2, 3]), source=CropSource(with_blobs))
    assert n_off >= 4 and placed.count(30) >= 4
    assert len(with_bg) == len(plain) + n_off and int((with_bg.labels == 0).sum()) == n_off
