"""DenseFusion crop rule (its worked examples) and point sampling."""

import numpy as np
import pytest

from posegrasp.perception.crop import backproject, crop_box, remap_choose, sample_choose


def _mask(r0, r1, c0, c1, shape=(480, 640)):
    m = np.zeros(shape, bool)
    m[r0:r1 + 1, c0:c1 + 1] = True
    return m


@pytest.mark.parametrize("rows, cols, box", [
    ((100, 149), (200, 229), (85, 165, 195, 235)),
    ((0, 39), (0, 39), (0, 40, 0, 40)),
    ((0, 479), (0, 639), (0, 480, 0, 640)),
])
def test_crop_examples(rows, cols, box):
    assert crop_box(_mask(*rows, *cols)) == box


def test_crop_shifted_inside_small_image():
    m = _mask(100, 115, 150, 159, shape=(120, 160))
    rmin, rmax, cmin, cmax = crop_box(m)
    assert (rmin, rmax, cmin, cmax) == (80, 120, 120, 160)


def test_sample_subsample_and_wrap():
    valid = np.zeros((10, 10), bool)
    valid[2:5, 3:8] = True  # 15 candidates
    a = sample_choose(valid, 8, np.random.default_rng(0))
    b = sample_choose(valid, 8, np.random.default_rng(0))
    np.testing.assert_array_equal(a, b)
    assert len(set(a.tolist())) == 8 and np.all(valid.ravel()[a]) and np.all(np.diff(a) > 0)
    w = sample_choose(valid, 20, np.random.default_rng(0))
    idx = np.flatnonzero(valid.ravel())
    np.testing.assert_array_equal(w, np.concatenate([idx, idx[:5]]))
    with pytest.raises(ValueError):
        sample_choose(np.zeros((3, 3), bool), 4, np.random.default_rng(0))


def test_remap_and_backproject():
    choose = np.array([0, 9, 90, 99])  # corners of a 10 x 10 crop
    np.testing.assert_array_equal(remap_choose(choose, (10, 10), 20), [21, 39, 381, 399])  # pixel centres
    np.testing.assert_array_equal(remap_choose(choose, (10, 10), 5), [0, 4, 20, 24])
    depth = np.full((20, 30), 0.5)
    K = np.array([[100.0, 0, 15.0], [0, 100.0, 10.0], [0, 0, 1]])
    p = backproject(depth, K, (5, 15, 10, 20), np.array([0, 99]))
    np.testing.assert_allclose(p, [[-0.025, -0.025, 0.5], [0.02, 0.02, 0.5]])
