"""Run-time inputs: the connected segments of a class map and the instance classifier's metric crops."""

import cv2
import numpy as np

from posegrasp.perception.classifier import ClassifierConfig
from posegrasp.perception.data import seam_map
from posegrasp.perception.inputs import prepare_cls_input, seam_components, segment_components
from posegrasp.perception.plane import fit_support_plane

#: 64 px crops of 0.16 m, relative depths within 0.05 m; with the height channel up to 0.08 m.
CROP = ClassifierConfig(crop_size=64, crop_side=0.16, depth_range=0.05)
HEIGHT_CROP = ClassifierConfig(crop_size=64, crop_side=0.16, depth_range=0.05, height_range=0.08)


def test_segment_components_split_separated_blocks_of_one_type():
    m = np.zeros((40, 60), np.int64)
    m[5:15, 5:15] = 4  # block A
    m[20:30, 30:45] = 4  # block B of the same type
    m[38:40, 0:2] = 4  # 4-pixel speck: dropped
    inst = [c for o, c in segment_components(m, min_pixels=50) if o == 4]
    assert sorted(int(i.sum()) for i in inst) == [100, 150]
    assert not np.any(inst[0] & inst[1])
    m[15:20, 10:35] = 4  # a bridge joins them: one instance
    assert len(segment_components(m, min_pixels=50)) == 1


def test_segment_components_are_each_classes_instances_in_raster_order():
    """Found region by region (in each foreground region's box), the components are each class's 8-connected components
    in the whole image: by class, then by the raster position of their first pixel; a region that fills its box,
    regions whose boxes overlap and a class in several regions included."""
    labels = np.zeros((40, 60), np.int64)
    labels[2:6, 50:54] = 3  # a region that fills its box
    labels[10:30, 5:10] = 2  # an L-shaped region of classes 2 and 5
    labels[25:30, 5:25] = 5
    labels[12:18, 15:22] = 5  # a region inside the L's box, apart from it ...
    labels[14:16, 16:18] = 2  # ... holding a class-2 island
    labels[0, 0] = 3  # one pixel at the corner
    found = segment_components(labels, 1)
    expected = [(c, comp == i) for c in (2, 3, 5)
                for n, comp in [cv2.connectedComponents((labels == c).astype(np.uint8), connectivity=8)]
                for i in range(1, n)]
    first = [int(np.flatnonzero(m.ravel())[0]) for _, m in expected]
    expected = [e for _, e in sorted(zip(first, expected), key=lambda x: (x[1][0], x[0]))]
    assert [c for c, _ in found] == [c for c, _ in expected] == [2, 2, 3, 3, 5, 5]
    assert all((a == b).all() for (_, a), (_, b) in zip(found, expected))
    assert [c for c, _ in segment_components(labels, 17)] == [2, 5, 5]  # the island, the 16-px region, the pixel: out
    big = np.zeros((60, 90), np.int64)  # the same away from the image's corner (found in the foreground's box)
    big[7:47, 11:71] = labels
    moved = segment_components(big, 1)
    assert [c for c, _ in moved] == [c for c, _ in found]
    assert all((m[7:47, 11:71] == f).all() and m.sum() == f.sum() for (_, m), (_, f) in zip(moved, found))
    assert segment_components(np.zeros((4, 4), np.int64), 1) == []


def test_the_crops_median_depth_is_numpys():
    """The crops' median (``inputs._median``) is ``np.median``'s, odd and even counts, ties, in float32."""
    from posegrasp.perception.inputs import _median

    rng = np.random.default_rng(3)
    for n in [1, 2, 3, 4, 7, 10, 999, 1000]:
        x = rng.random(n).astype(np.float32)
        x[rng.random(n) < 0.3] = x[0]
        assert _median(x) == np.median(x) and _median(x).dtype == np.median(x).dtype


def test_seams_cut_touching_parts_of_one_type_apart():
    """Two blocks of one type side by side are one component of the class map; the seam between them (the pixels of
    each next to the other) cuts them apart, and each part grows back over its side of the seam."""
    parts = np.zeros((40, 60), np.int64)
    parts[5:25, 5:20] = 1
    parts[5:25, 20:40] = 2  # touching the first along column 19 | 20
    parts[30:35, 45:50] = 3  # apart from both: no seam
    seams = seam_map(parts)
    assert set(np.argwhere(seams)[:, 1]) == {19, 20} and seams.sum() == 2 * 20
    labels = np.where(parts > 0, 4, 0)  # one type: the class map merges the two blocks
    assert len(segment_components(labels, 10)) == 2
    found = seam_components(labels, seams, 10)
    assert [c for c, _ in found] == [4, 4, 4]
    for (_, m), k in zip(found, (1, 2, 3)):
        assert (m == (parts == k)).all()
    labels[10:14, 8:12] = 5  # a patch of another class: the part is still one, of its pixels' most common class
    assert [(c, (m == (parts == k)).all()) for (c, m), k in zip(seam_components(labels, seams, 10), (1, 2, 3))] == \
        [(4, True)] * 3
    labels[labels == 5] = 4
    wide = seams | np.roll(seams, 1, axis=1) | np.roll(seams, -1, axis=1)  # a wider seam takes more passes
    assert [int(m.sum()) for _, m in seam_components(labels, wide, 10, passes=1)] == [280, 380, 25]
    assert all((m == (parts == k)).all() for (_, m), k in zip(seam_components(labels, wide, 10), (1, 2, 3)))


def test_cls_crop_has_a_fixed_metric_size():
    K = np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]])
    for z in (0.3, 0.6):  # a 0.08 m square face, fronto-parallel, at two distances
        side_px = int(round(0.08 * 150.0 / z))
        depth = np.full((120, 160), z + 0.05, np.float32)
        mask = np.zeros((120, 160), bool)
        mask[30:30 + side_px, 40:40 + side_px] = True
        depth[mask] = z
        rgb = np.zeros((120, 160, 3), np.uint8)
        x = prepare_cls_input(rgb, depth, K, mask, CROP)
        assert x.shape == (6, 64, 64) and x.dtype == np.float32
        # half the crop's side: ~32 x 32 px of mask, centred, whatever the distance
        assert abs(x[3].sum() - 32 * 32) < 0.1 * 32 * 32 and x[3, 32, 32] == 1.0
        rel = x[4][x[5] > 0]
        np.testing.assert_allclose(sorted(set(np.round(rel, 4))), [0.0, 1.0])  # object 0, table +0.05 m
    assert prepare_cls_input(rgb, np.zeros_like(depth), K, mask, CROP) is None


def test_cls_crop_height_channel_is_the_height_above_the_plane():
    """A 3 cm plateau on a table seen by a camera tilted 35 deg: the relative depth ramps across the plateau, its
    height above the plane does not; the plane the crop uses is the one RANSAC finds in the depth image."""
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    a = np.radians(35.0)
    n = -np.array([0.0, np.sin(a), np.cos(a)])  # the table's normal, towards the camera
    plane = np.array([*n, 0.45 * np.cos(a)])  # n . X + d = 0 through (0, 0, 0.45) m
    vs, us = np.mgrid[:240, :320]
    rays = np.stack([(us - K[0, 2]) / K[0, 0], (vs - K[1, 2]) / K[1, 1], np.ones(us.shape)], -1) @ n  # n . ray
    mask = np.zeros((240, 320), bool)
    mask[100:140, 130:190] = True
    depth = (-(plane[3] - np.where(mask, 0.03, 0.0)) / rays).astype(np.float32)  # n . X + d = 0.03 on the top
    rgb = np.zeros((240, 320, 3), np.uint8)
    found = fit_support_plane(depth, K)
    np.testing.assert_allclose(found, plane, atol=1e-4)
    x = prepare_cls_input(rgb, depth, K, mask, HEIGHT_CROP, found)
    assert x.shape == (7, 64, 64)
    top, table = x[3] > 0, (x[3] == 0) & (x[5] > 0)
    np.testing.assert_allclose(x[6][top], 0.03 / 0.08, atol=0.01)
    np.testing.assert_allclose(x[6][table], 0.0, atol=0.01)
    assert np.ptp(x[4][top]) > 0.2  # the relative depth ramps by > 1 cm across the 3 cm-high top
    no_plane = prepare_cls_input(rgb, depth, K, mask, HEIGHT_CROP)
    assert not no_plane[6].any() and np.array_equal(no_plane[:6], x[:6])
    assert np.array_equal(prepare_cls_input(rgb, depth, K, mask, CROP), x[:6])
