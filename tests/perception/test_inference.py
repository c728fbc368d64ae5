

def test_segment_components_split_separated_blocks_of_one_type():
    import numpy as np

    from posegrasp.perception.data import segment_components

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
    import cv2
    import numpy as np

    from posegrasp.perception.data import segment_components

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


def test_argmax_planes_is_numpys_argmax_first_on_ties():
    import numpy as np

    from posegrasp.perception.guided import argmax_planes

    x = np.random.default_rng(0).integers(0, 4, (7, 30, 40)).astype(np.float32)  # many ties
    assert argmax_planes(x).dtype == np.uint16
    np.testing.assert_array_equal(argmax_planes(x), x.argmax(axis=0))


def test_upsampled_argmax_is_the_argmax_of_the_resized_probabilities():
    """Smooth class probabilities with boundaries, resized up (by 2 and by odd factors) and down: the class map
    from the low-resolution arg-max and the exact one near its boundaries is the full arg-max."""
    import cv2
    import numpy as np
    import torch

    from posegrasp.perception.inference import upsampled_argmax

    logits = cv2.GaussianBlur(np.random.default_rng(1).normal(0, 4, (48, 64, 6)).astype(np.float32), (9, 9), 3)
    small = torch.softmax(torch.from_numpy(logits), dim=-1).numpy()  # (h, w, C)
    planes = np.ascontiguousarray(small.transpose(2, 0, 1))
    for W, H in [(128, 96), (150, 101), (64, 48), (40, 30)]:
        prob = cv2.resize(small, (W, H), interpolation=cv2.INTER_LINEAR)
        out = upsampled_argmax(planes, prob)
        assert out.dtype == np.int64 and out.shape == (H, W)
        assert len(np.unique(out)) > 2
        np.testing.assert_array_equal(out, prob.argmax(axis=-1))
