"""BOP 2019 metrics (VSD, MSSD, MSPD, matching, AR) on hand-computed cases."""

import numpy as np
import pytest
import trimesh

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.geometry import axis_angle_R, make_T
from posegrasp.perception import bop19 as B
from posegrasp.perception.depth_render import DepthRenderer

K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
HALF = np.array([0.03, 0.015, 0.01])  # a 60 x 30 x 20 mm box
FLIPS = [make_T(axis_angle_R(np.eye(3)[i], np.pi), np.zeros(3)) for i in range(3)]
BOX_INFO = bop.ObjectInfo(1, float(2 * np.linalg.norm(HALF)), symmetries_discrete=FLIPS)
SYMS = B.symmetry_transforms(BOX_INFO)
T_GT = make_T(axis_angle_R([1.0, 2.0, 3.0], 0.7), np.array([0.02, -0.01, 0.5]))


@pytest.fixture(scope="module")
def box_points():
    box = trimesh.creation.box(2 * HALF)
    return bop_models.resample_for_eval(box.vertices, box.faces, 0.004)[0]


def test_resampled_model_keeps_its_surface_with_dense_vertices():
    box = trimesh.creation.box(2 * HALF)
    dense = trimesh.Trimesh(*bop_models.resample_for_eval(box.vertices, box.faces, 0.004), process=False)
    assert dense.edges_unique_length.max() <= 0.004 and len(dense.vertices) > 300
    assert dense.is_watertight and np.isclose(dense.volume, box.volume) and np.isclose(dense.area, box.area)


def test_symmetric_pose_scores_zero(box_points):
    for S in FLIPS:
        assert B.mssd(T_GT @ S, T_GT, box_points, SYMS) < 1e-12
        assert B.mspd(T_GT @ S, T_GT, box_points, SYMS, K) < 1e-9


def test_box_turned_90_deg_scores_its_known_mssd_and_mspd(box_points):
    # about z: (x, y, z) -> (-y, x, z) lies sqrt(2 (x^2 + y^2)) away, largest at a corner; the flips do worse
    turn = make_T(axis_angle_R([0.0, 0.0, 1.0], np.pi / 2), np.zeros(3))
    assert B.mssd(T_GT @ turn, T_GT, box_points, SYMS) == pytest.approx(np.sqrt(2 * (HALF[0] ** 2 + HALF[1] ** 2)))
    # the box faces the camera on the optical axis at 0.5 m, turned about it: each pixel turns 90 deg about the
    # principal point, sqrt(2) x f x rho / z away, largest for the near corners (z = 0.49 m)
    T = make_T(np.eye(3), np.array([0.0, 0.0, 0.5]))
    want = np.sqrt(2) * 600.0 * np.hypot(HALF[0], HALF[1]) / (0.5 - HALF[2])
    assert B.mspd(T @ turn, T, box_points, SYMS, K) == pytest.approx(want)


def test_continuous_symmetry_is_discretised_and_composed():
    info = bop.ObjectInfo(2, 0.064, symmetries_discrete=[FLIPS[0]],
                          symmetries_continuous=[(np.array([0.0, 0.0, 1.0]), np.zeros(3))])
    syms = B.symmetry_transforms(info)
    assert syms.shape == (2 * 315, 4, 4) and np.allclose(syms[0], np.eye(4))
    cyl = trimesh.creation.cylinder(0.02, 0.05, sections=24)
    pts = bop_models.resample_for_eval(cyl.vertices, cyl.faces, 0.004)[0]
    spin = make_T(axis_angle_R([0.0, 0.0, 1.0], 1.234), np.zeros(3))
    # any turn about the axis, also upside down, is within one step: 2 pi / 315 x 20 mm at most
    assert B.mssd(T_GT @ spin @ FLIPS[0], T_GT, pts, syms) <= 2 * np.pi / 315 * 0.02
    # the flip about y is the flip about x and a half turn, which lies half a step from the nearest step
    assert 0 < B.mssd(T_GT @ FLIPS[1], T_GT, pts, syms) <= np.pi / 315 * 0.02 + 1e-12


def test_vsd_by_hand():
    # 4 pixels: the model at the truth covers 3, the estimate 3 (2 shared, one 2 cm away); the test image sees
    # the truth everywhere, the estimate's own pixel lies behind it (hidden: not in V_est)
    z = np.zeros((1, 4), np.float32)
    d_gt, d_est, d_test = z.copy(), z.copy(), z.copy()
    d_gt[0, :3] = d_test[0, :3] = 0.5
    d_est[0, 1:] = [0.5, 0.52, 0.6]
    d_test[0, 3] = 0.5
    # V_gt = {0, 1, 2}; V_est = {1} (0.02 > delta at 2 is still OR'ed in by V_gt & d_est > 0: {1, 2}; 3 hidden)
    e = B.vsd(d_est, d_gt, d_test, diameter=0.1, taus=np.array([0.1, 0.3]))
    # U = {0, 1, 2}, I = {1, 2}: |d_gt - d_est| / diameter = (0, 0.2) -> costs 1 at tau 0.1, 0 at tau 0.3
    assert e == pytest.approx([(1 + 1) / 3, (1 + 0) / 3])


@pytest.mark.parametrize("dx, want", [(0.0, 0.0), (1.0, 1.0)])
def test_vsd_of_rendered_box_identical_is_zero_and_out_of_view_is_one(dx, want):
    box = trimesh.creation.box(2 * HALF)
    render = DepthRenderer({1: box})
    f = B.ray_factor(K, 480, 640)
    d_gt = render(1, T_GT, K, 480, 640) * f
    T_e = T_GT.copy()
    T_e[0, 3] += dx
    d_est = render(1, T_e, K, 480, 640) * f
    assert (d_gt > 0).sum() > 1000
    assert np.all(B.vsd(d_est, d_gt, d_gt.copy(), BOX_INFO.diameter) == want)


def test_matching_takes_estimates_by_score_and_the_lowest_error():
    valid = np.array([True, True, False])
    # rows: estimates best score first; the first takes gt 1 (lowest), the second can only take gt 0
    err = np.array([[0.2, 0.1, 0.0], [0.15, 0.05, 0.0]])
    assert B.matched(err, valid, 0.3) == 2
    assert B.matched(err, valid, 0.12) == 1  # gt 1 taken by the first; 0.15 is not below the threshold
    assert B.matched(err[:, [2]], valid[[2]], 1.0) == 0  # an invalid instance is never matched


def test_scores_average_recall_over_thresholds():
    E, G = 1, 2
    g = B.ObjectErrors(obj_id=1, targets=2, valid=np.ones(G, bool), mssd=np.full((E, G), np.inf),
                       mspd=np.full((E, G), np.inf), vsd=np.ones((E, G, 10)))
    g.mssd[0, 0] = 0.12 * BOX_INFO.diameter  # correct from theta 0.15: 8 of 10 thresholds
    g.mspd[0, 1] = 22.0  # correct from 25 px: 6 of 10
    g.vsd[0, 0, 5:] = 0.0  # correct for half the taus at every theta
    s = B.scores([g], {1: BOX_INFO}, width=640)
    assert s["ar_mssd"] == pytest.approx(0.8 / 2) and s["ar_mspd"] == pytest.approx(0.6 / 2)
    assert s["ar_vsd"] == pytest.approx(0.5 / 2) and s["ar"] == pytest.approx((0.4 + 0.3 + 0.25) / 3)
    assert s["targets"] == 2 and s["per_object"]["1"]["ar"] == s["ar"]
    assert B.scores([g], {1: BOX_INFO}, width=1280)["ar_mspd"] == pytest.approx(0.8 / 2)  # 10 ... 100 px


def test_scores_by_visible_fraction_count_each_bins_instances():
    E, G = 2, 3
    g = B.ObjectErrors(obj_id=1, targets=2, valid=np.array([True, True, False]), mssd=np.full((E, G), np.inf),
                       mspd=np.full((E, G), np.inf), vsd=np.ones((E, G, 10)), visib=np.array([0.2, 1.0, 0.05]))
    g.mssd[1, 1] = g.mspd[1, 1] = 0.0  # the second estimate finds the fully visible instance exactly
    g.vsd[1, 1] = 0.0
    s = B.scores([g], {1: BOX_INFO}, width=640)
    bins = {tuple(b["visib"]): b for b in s["by_visib"]}
    assert [tuple(b["visib"]) for b in s["by_visib"]] == list(B.VISIB_BINS)
    assert bins[(0.1, 0.3)]["targets"] == 1 and bins[(0.1, 0.3)]["ar"] == 0.0
    assert bins[(0.9, 1.0)]["targets"] == 1 and bins[(0.9, 1.0)]["ar"] == pytest.approx(1.0)  # 1.0 is in the last
    assert all(bins[b]["targets"] == 0 for b in B.VISIB_BINS[1:4])
    assert sum(b["targets"] for b in s["by_visib"]) == s["targets"] == 2 and s["ar"] == pytest.approx(0.5)
