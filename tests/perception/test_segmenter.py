"""The segmentation stage's class map and class probabilities at the image size."""

import cv2
import numpy as np
import torch

from posegrasp.perception.segmenter import ClassProbabilities, upsampled_argmax


def test_class_probabilities_are_cv2_resize_bit_for_bit():
    """Read at any pixels, the probabilities are OpenCV's bilinear resize's own float32 numbers, up, down and at odd
    factors, for every channel count (those OpenCV resizes by other code through its own resize)."""
    rng = np.random.default_rng(0)
    for C, (h, w), (H, W) in [(9, (240, 320), (480, 640)), (9, (240, 320), (720, 1280)), (2, (48, 64), (101, 150)),
                              (5, (48, 64), (30, 40)), (12, (37, 29), (513, 999)), (3, (48, 64), (96, 128)),
                              (1, (48, 64), (97, 129)), (4, (48, 64), (48, 64))]:
        small = rng.random((C, h, w), dtype=np.float32)
        ref = cv2.resize(np.ascontiguousarray(small.transpose(1, 2, 0)), (W, H), interpolation=cv2.INTER_LINEAR)
        ref = ref.reshape(H, W, C)
        prob = ClassProbabilities(small, (H, W))
        assert prob.shape == (H, W, C)
        mask = rng.random((H, W)) < 0.3
        mask[0], mask[-1], mask[:, 0], mask[:, -1] = True, True, True, True  # the borders' clamped taps
        assert np.array_equal(prob.at(mask), ref[mask]), (C, h, w, H, W)
        assert np.array_equal(prob.at(mask, C - 1), ref[..., C - 1][mask])
        assert np.array_equal(np.asarray(prob), ref)


def test_upsampled_argmax_is_the_argmax_of_the_resized_probabilities():
    """Smooth class probabilities with boundaries, resized up (by 2 and by odd factors) and down: the class map
    from the low-resolution arg-max and the exact one near its boundaries is the full arg-max."""
    logits = cv2.GaussianBlur(np.random.default_rng(1).normal(0, 4, (48, 64, 6)).astype(np.float32), (9, 9), 3)
    small = torch.softmax(torch.from_numpy(logits), dim=-1).numpy()  # (h, w, C)
    planes = np.ascontiguousarray(small.transpose(2, 0, 1))
    for W, H in [(128, 96), (150, 101), (64, 48), (40, 30)]:
        prob = cv2.resize(small, (W, H), interpolation=cv2.INTER_LINEAR)
        out = upsampled_argmax(planes, ClassProbabilities(planes, (H, W)))
        assert out.dtype == np.int64 and out.shape == (H, W)
        assert len(np.unique(out)) > 2
        np.testing.assert_array_equal(out, prob.argmax(axis=-1))


def test_nearest_pixels_are_those_of_opencvs_nearest_resize():
    """The pixels set in a mask resized by INTER_NEAREST_EXACT, up, down and at odd factors, found from its own."""
    from posegrasp.perception.segmenter import _nearest_of

    m = (np.random.default_rng(2).random((48, 64)) < 0.1).astype(np.uint8)
    for H, W in [(96, 128), (101, 150), (30, 40), (48, 64)]:
        got = np.zeros((H, W), dtype=bool)
        got[_nearest_of(m, H, W)] = True
        np.testing.assert_array_equal(got, cv2.resize(m, (W, H), interpolation=cv2.INTER_NEAREST_EXACT) > 0)
