"""ADD, ADD-S and AUC test vectors (Hinterstoisser et al. 2012, Xiang et al. 2018) and the segmentation scores."""

import numpy as np
import pytest

from posegrasp.perception import metrics as m
from posegrasp.geometry import axis_angle_R, quat_to_R


@pytest.fixture(scope="module")
def poses():
    pts = np.random.default_rng(0).uniform(-0.05, 0.05, (500, 3))
    q = np.array([0.9, 0.1, -0.3, 0.2])
    R_g = quat_to_R(q / np.linalg.norm(q))
    t_g = np.array([0.05, -0.02, 0.70])
    R_e = R_g @ axis_angle_R(np.array([0.0, 0.0, 1.0]), np.radians(10.0))
    t_e = t_g + np.array([0.01, 0.0, -0.005])
    return R_e, t_e, R_g, t_g, pts


def test_add(poses):
    assert m.add(*poses) == pytest.approx(0.0128078935, abs=1e-10)


def test_adds_both_directions(poses):
    assert m.adds(*poses) == pytest.approx(0.0079248684, abs=1e-10)
    assert m.adds(*poses, direction="gt_to_est") == pytest.approx(0.0079248684, abs=1e-10)
    assert m.adds(*poses, direction="est_to_gt") == pytest.approx(0.0078858577, abs=1e-10)


def test_re_te(poses):
    R_e, t_e, R_g, t_g, _ = poses
    assert m.rotation_error_deg(R_e, R_g) == pytest.approx(10.0, abs=1e-9)
    assert m.translation_error(t_e, t_g) == pytest.approx(0.0111803399, abs=1e-10)


def test_nearest_distances_matches_naive():
    rng = np.random.default_rng(1)
    q, r = rng.normal(size=(300, 3)), rng.normal(size=(200, 3))
    naive = np.linalg.norm(q[:, None] - r[None], axis=2).min(axis=1)
    np.testing.assert_allclose(m.nearest_distances(q, r), naive, rtol=0, atol=1e-12)


@pytest.mark.parametrize("d, auc", [
    ([0.001, 0.005, 0.005, 0.02, 0.05, 0.099, 0.1, 0.2, np.inf, 0.0], 62.0),
    ([0.0, 0.0, 0.0, 0.0], 100.0),
    ([0.05], 100.0),
    ([0.2], 0.0),
])
def test_ycb_auc(d, auc):
    assert m.ycb_auc(d) == pytest.approx(auc, abs=1e-9)


def test_accuracies_strict():
    d = [0.0, 0.0199, 0.02, 0.05]
    assert m.accuracy_below(d) == 0.5
    assert m.accuracy_at_diameter([0.049, 0.05], diameter=0.5) == 0.5  # 0.1 * d is excluded


def test_segmentation_scores():
    label = np.array([[0, 0, 1, 1], [0, 2, 2, 2]])
    pred = np.array([[0, 1, 1, 1], [0, 2, 2, 0]])
    conf = m.confusion_matrix(pred, label, 4)
    assert conf.sum() == 8 and conf[0, 1] == 1 and conf[2, 0] == 1
    s = m.segmentation_scores(conf)
    np.testing.assert_allclose(s["pa"][:3], [200 / 3, 100.0, 200 / 3])
    assert np.isnan(s["pa"][3])
    np.testing.assert_allclose(s["iou"][:3], [50.0, 200 / 3, 200 / 3])
    assert s["mPA"] == pytest.approx((200 / 3 + 100 + 200 / 3) / 3)
    assert s["mIoU"] == pytest.approx((50 + 400 / 3) / 3)


def test_rotation_error_up_to_symmetry():
    R_g = quat_to_R(np.array([0.9, 0.1, -0.3, 0.2]))
    flip_z = np.diag([-1.0, -1.0, 1.0, 1.0])
    R_e = R_g @ flip_z[:3, :3]  # the box's 180 deg symmetry about z
    assert m.rotation_error_deg(R_e, R_g) == pytest.approx(180.0)
    assert m.rotation_error_sym_deg(R_e, R_g, [flip_z]) == pytest.approx(0.0, abs=1e-6)
    spun = R_g @ axis_angle_R(np.array([0.0, 0.0, 1.0]), 1.0) @ axis_angle_R(np.array([1.0, 0.0, 0.0]), np.radians(5))
    assert m.rotation_error_sym_deg(spun, R_g, [], [np.array([0.0, 0.0, 1.0])]) == pytest.approx(5.0, abs=1e-6)


def test_instance_masks_match_one_to_one_above_half_iou():
    parts = np.zeros((4, 6), dtype=np.int64)
    parts[:, :3], parts[:, 3:] = 1, 2  # two parts of 12 px side by side
    whole_1 = parts == 1
    most_2 = np.zeros_like(whole_1)
    most_2[:3, 3:] = True  # 9 of part 2's 12 px
    merged = parts > 0  # both parts as one mask: IoU 0.5 with each, no match
    ious = m.mask_ious(parts, 2, [whole_1, most_2, merged])
    np.testing.assert_allclose(ious, [[1.0, 0.0], [0.0, 0.75], [0.5, 0.5]])
    same = np.array([[True, False], [False, False], [True, True]])  # most_2 has part 2's pixels, another type
    assert m.instance_scores(ious, same) == (1, 1, 2)
