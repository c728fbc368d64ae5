"""The guided filter: a linear model of the guide in every window; class-map outlines snapped to colour edges."""

import numpy as np
import pytest

from posegrasp.perception.guided import GuidedConfig, guided_filter, snap_labels


def _textured_scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 120 x 160 RGB image: a textured grey table with a red 30 x 40 block and a blue 20 x 20 block, and its
    true class map (0 table, 3 red block, 5 blue block)."""
    rng = np.random.default_rng(seed)
    rgb = np.clip(rng.normal(120, 12, (120, 160, 3)), 0, 255)
    labels = np.zeros((120, 160), np.int64)
    labels[40:70, 30:70], labels[50:70, 100:120] = 3, 5
    rgb[labels == 3] = (200, 40, 30)
    rgb[labels == 5] = (30, 50, 190)
    return rgb.astype(np.uint8), labels


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_the_guide_itself_passes_through():
    """p = a channel of the guide is exactly linear in the guide: q = p up to eps (subsample 1)."""
    guide = np.random.default_rng(1).uniform(0, 1, (40, 50, 3)).astype(np.float32)
    q = guided_filter(guide, guide[..., 1:2].copy(), radius=3, eps=1e-8)
    assert q.shape == (40, 50, 1)
    np.testing.assert_allclose(q[..., 0], guide[..., 1], atol=1e-3)


def test_a_constant_stays_constant():
    guide = np.random.default_rng(2).uniform(0, 1, (64, 64, 3)).astype(np.float32)
    q = guided_filter(guide, np.full((64, 64, 2), 0.25, np.float32), radius=8, eps=1e-4, subsample=4)
    np.testing.assert_allclose(q, 0.25, atol=1e-4)


@pytest.mark.parametrize("shift", [(3, 0), (-2, 3)])
def test_misplaced_outlines_snap_to_the_blocks(shift):
    """A class map that misses the blocks' edges by a few pixels (eroded, dilated, shifted) is put back on them."""
    rgb, truth = _textured_scene()
    coarse = np.roll(truth, shift, axis=(0, 1))
    refined = snap_labels(coarse, rgb, GuidedConfig(radius=8, eps=1e-4, subsample=2))
    for c in (3, 5):
        before, after = _iou(coarse == c, truth == c), _iou(refined == c, truth == c)
        assert before < 0.9 and after > 0.95, (c, before, after)
    assert set(np.unique(refined)) == {0, 3, 5}


def test_nothing_to_snap():
    rgb, truth = _textured_scene()
    empty = np.zeros_like(truth)
    assert snap_labels(empty, rgb) is empty
    assert snap_labels(truth, rgb, GuidedConfig(radius=0)) is truth
    with pytest.raises(ValueError, match=r"GuidedConfig\.eps = 0\.0 is out of range"):
        GuidedConfig(eps=0.0)


def test_argmax_planes_is_numpys_argmax_first_on_ties():
    from posegrasp.perception.guided import argmax_planes

    x = np.random.default_rng(0).integers(0, 4, (7, 30, 40)).astype(np.float32)  # many ties
    assert argmax_planes(x).dtype == np.uint16
    np.testing.assert_array_equal(argmax_planes(x), x.argmax(axis=0))
