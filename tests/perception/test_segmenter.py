"""The segmentation stage's class map at the image size."""

import cv2
import numpy as np
import torch

from posegrasp.perception.segmenter import upsampled_argmax


def test_upsampled_argmax_is_the_argmax_of_the_resized_probabilities():
    """Smooth class probabilities with boundaries, resized up (by 2 and by odd factors) and down: the class map
    from the low-resolution arg-max and the exact one near its boundaries is the full arg-max."""
    logits = cv2.GaussianBlur(np.random.default_rng(1).normal(0, 4, (48, 64, 6)).astype(np.float32), (9, 9), 3)
    small = torch.softmax(torch.from_numpy(logits), dim=-1).numpy()  # (h, w, C)
    planes = np.ascontiguousarray(small.transpose(2, 0, 1))
    for W, H in [(128, 96), (150, 101), (64, 48), (40, 30)]:
        prob = cv2.resize(small, (W, H), interpolation=cv2.INTER_LINEAR)
        out = upsampled_argmax(planes, prob)
        assert out.dtype == np.int64 and out.shape == (H, W)
        assert len(np.unique(out)) > 2
        np.testing.assert_array_equal(out, prob.argmax(axis=-1))
