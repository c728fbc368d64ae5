"""The supporting plane: RANSAC recovers a table under a block; pixels on it; ICP hypotheses sunk into it lose."""

import numpy as np
import pytest

from posegrasp.perception.depth_fit import FitConfig, ObjectModel, DepthFitConfig, fit_pose
from posegrasp.perception.plane import clear_plane, fit_support_plane, plane_pixels

K = np.array([[500.0, 0.0, 160.0], [0.0, 500.0, 120.0], [0.0, 0.0, 1.0]])


def _table_with_box(n: np.ndarray, d: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth (240, 320) of the plane n . x + d = 0 with a patch 3 cm nearer the camera, and the patch mask."""
    v, u = np.mgrid[0:240, 0:320]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], axis=-1)
    depth = -d / (rays @ n)
    box = (abs(u - 160) < 30) & (abs(v - 120) < 20)
    depth[box] -= 0.03
    depth[:5] = 0.0  # invalid rows
    return depth, box


def test_ransac_finds_the_table_and_its_pixels():
    n = np.array([0.0, -0.6, -0.8])  # a table seen obliquely, its normal towards the camera
    depth, box = _table_with_box(n, 0.5)
    plane = fit_support_plane(depth, K, seed=0)
    assert plane is not None and plane[3] > 0
    np.testing.assert_allclose(plane, np.append(n, 0.5), atol=1e-6)
    on = plane_pixels(plane, depth, K, np.ones(depth.shape, bool), 0.002)
    assert not on[box].any() and on[~box & (depth > 0)].all() and not on[:5].any()
    assert fit_support_plane(np.zeros((240, 320)), K) is None
    labels = np.where(np.roll(box, 8, axis=1), 3, 0)  # a segment that bleeds 8 px onto the table
    cleared, p = clear_plane(labels, depth, K)
    np.testing.assert_array_equal(p, plane)
    np.testing.assert_array_equal(cleared, np.where(box, labels, 0))
    flat = np.zeros((240, 320))
    assert clear_plane(labels, flat, K)[1] is None and clear_plane(labels, flat, K)[0] is labels


@pytest.mark.slow
def test_icp_scores_a_pose_sunk_into_the_table_worse():
    """Score of a fixed pose (no ICP steps): a 4 cm cube on the table 0.5 m below the camera; the same cube
    1 cm lower (a quarter of it beneath the table) pays the plane term, the one on the table does not."""
    rng = np.random.default_rng(0)
    plane = np.array([0.0, 0.0, -1.0, 0.5])  # normal up the optical axis, towards the camera
    model = rng.uniform(-0.02, 0.02, (2000, 3))
    depth = np.zeros((240, 320))  # no depth: the free-space term stays 0
    cfg = DepthFitConfig(fit=FitConfig(iterations=0))
    fixed = ObjectModel.of_points(model, cfg, np.eye(3)[None])
    for dz, share in ((0.0, 0.0), (0.01, 0.25)):  # the cube's bottom 0 or 1 cm beneath the table
        T = np.eye(4)
        T[2, 3] = 0.48 + dz
        obs = model[:300] @ T[:3, :3].T + T[:3, 3]
        s_free = fit_pose(T, fixed, obs, depth, K, cfg)[1]
        s_plane = fit_pose(T, fixed, obs, depth, K, cfg, plane)[1]
        below = np.mean(model[:, 2] + T[2, 3] > 0.5 + cfg.score.violation_margin)
        assert abs(below - share / 2) < 0.03  # points more than the 5 mm margin beneath: half the sunk part
        assert s_plane - s_free == pytest.approx(cfg.score.violation_weight * below, abs=1e-6)


def test_no_plane_without_a_table(tiny_bop):
    """The tiny set has no table (background depth 0): its blocks' faces are no supporting plane."""
    from posegrasp import bop

    rec = next(bop.iter_scene_images(tiny_bop, "train"))
    depth, K = rec.load_depth(), rec.camera.K
    assert fit_support_plane(depth, K) is None
    table = np.where(depth > 0, depth, depth.max() + 0.01)  # a table 1 cm behind the objects
    np.testing.assert_allclose(fit_support_plane(table, K), [0.0, 0.0, -1.0, depth.max() + 0.01], atol=1e-5)


def test_objects_in_a_tote_rest_on_its_floor_not_on_the_table():
    """A tote's floor 1 cm above the table fills a quarter of the view, the table the rest: the dominant plane is the
    table, but the block in the tote rests on the floor, which the band around its pixels finds."""
    v, u = np.mgrid[0:240, 0:320]
    depth = np.full((240, 320), 0.5)  # the table, 0.5 m below the camera looking straight down
    depth[(abs(u - 160) < 90) & (abs(v - 120) < 60)] = 0.49  # the tote's floor
    block = (abs(u - 160) < 20) & (abs(v - 120) < 15)
    depth[block] = 0.46
    np.testing.assert_allclose(fit_support_plane(depth, K), [0.0, 0.0, -1.0, 0.5], atol=1e-6)
    np.testing.assert_allclose(fit_support_plane(depth, K, objects=block), [0.0, 0.0, -1.0, 0.49], atol=1e-6)
    strip = (abs(u - 60) < 5) & (abs(v - 30) < 5)  # a bit of the table, wrongly segmented
    labels = np.where(block | strip, 2, 0)
    cleared, p = clear_plane(labels, depth, K)  # the band's median height: the floor's
    np.testing.assert_allclose(p, [0.0, 0.0, -1.0, 0.49], atol=1e-6)
    np.testing.assert_array_equal(cleared > 0, block | strip)  # the table is not on that plane
    table_only = np.full((240, 320), 0.5)
    table_only[block] = 0.46
    np.testing.assert_array_equal(fit_support_plane(table_only, K, objects=block), fit_support_plane(table_only, K))


def test_parts_filling_a_tote_rest_on_its_floor_seen_in_the_gaps():
    """A full tote: its floor, 1 cm above the table, shows only in the gaps between the parts (under 3 % of the view),
    its walls around them. The parts rest on that floor, not on the table."""
    v, u = np.mgrid[0:240, 0:320]
    depth = np.full((240, 320), 0.5)  # the table, 0.5 m below the camera looking straight down
    tote = (abs(u - 160) < 90) & (abs(v - 120) < 60)
    gaps = tote & ((u - 71) % 20 == 0)  # 1 px of floor every 20 px
    parts = tote & ~gaps
    depth[gaps], depth[parts] = 0.49, 0.46
    for k in range(1, 6):  # the walls' inner faces seen aslant, 3 to 6 cm high
        depth[(abs(u - 160) < 90 + k) & (abs(v - 120) < 60 + k) & (depth == 0.5)] = 0.47 - 0.006 * (k - 1)
    assert 0.01 < gaps.mean() < 0.02
    np.testing.assert_allclose(fit_support_plane(depth, K, objects=parts), [0.0, 0.0, -1.0, 0.49], atol=1e-6)


def test_a_block_lying_on_another_does_not_float():
    """Two 4 cm cubes stacked on the table 0.5 m below the camera: the upper one's pose pays the floating term when
    it is alone in the frame, not beside the cube it lies on (whose seen points support it); the lower one's score
    is the same either way."""
    import torch

    from posegrasp.perception.depth_fit.context import FitContext
    from posegrasp.perception.depth_fit.score import score

    rng = np.random.default_rng(0)
    plane = np.array([0.0, 0.0, -1.0, 0.5])
    model = rng.uniform(-0.02, 0.02, (2000, 3))
    cfg = DepthFitConfig()
    cube = ObjectModel.of_points(model, cfg, np.eye(3)[None])
    poses = [np.eye(4), np.eye(4)]
    poses[0][2, 3], poses[1][2, 3] = 0.48, 0.44  # the lower cube on the table, the upper one on it
    obs = [model[:300] @ T[:3, :3].T + T[:3, 3] for T in poses]
    depth = np.zeros((240, 320))

    def scores(objs: list[int]) -> np.ndarray:
        frame = FitContext.of([cube] * len(objs), [obs[i] for i in objs], depth, K, plane)
        R = torch.eye(3).expand(len(objs), 3, 3)
        t = torch.tensor(np.array([poses[i][:3, 3] for i in objs]), dtype=torch.float32)
        return score(frame, cfg.score, R, t, torch.arange(len(objs)), fine=True).numpy()

    both, upper, lower = scores([0, 1]), scores([1]), scores([0])
    assert upper[0] - both[1] == pytest.approx(cfg.score.float_weight, abs=1e-6)
    assert both[0] == pytest.approx(lower[0], abs=1e-7)
