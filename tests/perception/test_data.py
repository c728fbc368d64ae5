"""Datasets over the tiny BOP dataset: geometry consistency, determinism, augmentation, skipping."""

import numpy as np
import pytest
import torch

from perception.data import DataConfig, PoseDataset, SegDataset, collate
from perception.metrics import nearest_distances


def test_pose_samples_are_consistent(tiny_bop):
    ds = PoseDataset(tiny_bop, "train", [1, 2, 3], num_points=100, crop_size=48)
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
    b = collate([ds.get(i) for i in range(3)])
    assert b["points"].shape == (3, 100, 3) and b["obj"].dtype == torch.int64


def test_augmentation_is_seeded(tiny_bop):
    ds = PoseDataset(tiny_bop, "train", [1, 2, 3], 64, 32, augment=True, seed=3)
    a, b, c = ds.get(2, key=11), ds.get(2, key=11), ds.get(2, key=12)
    assert torch.equal(a["points"], b["points"]) and torch.equal(a["image"], b["image"])
    assert not torch.equal(a["points"], c["points"])
    plain = ds.get(2)
    # translation noise moves cloud and target together
    shift = (a["target"] - a["model_points"] @ a["T"][:3, :3].T.float()).mean(0)
    assert torch.allclose(shift, a["T"][:3, 3].float(), atol=1e-5)
    assert not torch.equal(plain["image"], a["image"])


def test_instances_are_filtered(tiny_bop):
    all_ = PoseDataset(tiny_bop, "train", [1, 2, 3], 64, 32)
    strict = PoseDataset(tiny_bop, "train", [1, 2, 3], 64, 32, DataConfig(min_visib_fract=0.99, min_points=150))
    assert 0 < len(strict) < len(all_)
    only1 = PoseDataset(tiny_bop, "train", [1], 64, 32)
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
