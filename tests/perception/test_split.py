"""Splitting a mask by its fitted model: explained pixels, and the unexplained parts split off."""

import numpy as np

from posegrasp.perception.split import ModelSurface, SplitConfig, unexplained_parts

K = np.array([[500.0, 0.0, 160.0], [0.0, 500.0, 120.0], [0.0, 0.0, 1.0]])


def _square_face(side: float, n: int = 200) -> np.ndarray:
    """Points (n * n, 3) of a square side x side in the object's z = 0 plane, centred on its origin (m)."""
    g = np.linspace(-side / 2, side / 2, n)
    x, y = np.meshgrid(g, g)
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def _two_patches() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Depth (240, 320) m with a patch at 0.50 m and one at 0.52 m beside it (0 elsewhere: invalid), the two
    patch masks and the pose of a 4 cm square facing the camera on the first patch."""
    v, u = np.mgrid[0:240, 0:320]
    a = (abs(u - 140) < 20) & (abs(v - 120) < 20)  # 40 px at 0.5 m: 4 cm, the square's size
    b = (abs(u - 190) < 20) & (abs(v - 120) < 20)
    depth = np.where(a, 0.50, np.where(b, 0.52, 0.0))
    T = np.eye(4)
    T[:3, 3] = [(140 - 160) * 0.5 / 500, 0.0, 0.5]  # the patch centre, back-projected
    return depth, a, b, T


def test_explained_pixels_are_those_on_the_fitted_surface():
    depth, a, b, T = _two_patches()
    surf = ModelSurface(_square_face(0.04))
    e = surf.explained(T, a | b, depth, K, tol=0.004)
    assert e[a].mean() > 0.95 and not e[b].any()  # b lies 2 cm behind the square's plane
    T_far = T.copy()
    T_far[2, 3] += 0.01
    assert not surf.explained(T_far, a | b, depth, K, tol=0.004).any()  # 1 cm off: nothing explained
    assert surf.explained(T_far, a | b, depth, K, tol=0.011)[a].mean() > 0.95


def test_explained_is_the_k_d_trees_answer_on_every_pixel():
    """The grid settles most points without a search and never differently from the k-d tree: a box model at a
    tilted pose against a depth image of points near it (within 1 cm, straddling every tolerance) and far off."""
    from posegrasp.geometry import axis_angle_R, make_T

    rng = np.random.default_rng(0)
    half = np.array([0.03, 0.015, 0.01])
    model = rng.uniform(-1, 1, (20000, 3)) * half
    face = rng.integers(0, 3, 20000)  # each point on one of the box's faces
    model[np.arange(20000), face] = np.sign(rng.normal(size=20000)) * half[face]
    surf = ModelSurface(model)
    T = make_T(axis_angle_R(np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5]), 0.7), np.array([0, 0, 0.5]))
    depth = 0.5 + rng.uniform(-0.04, 0.04, (240, 320))
    depth[rng.random((240, 320)) < 0.1] = 0.0  # invalid pixels
    mask = np.ones((240, 320), dtype=bool)
    for tol in (0.001, 0.004, 0.0075):
        e = surf.explained(T, mask, depth, K, tol)
        v, u = np.nonzero(depth > 0)
        z = depth[v, u]
        P = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
        d = surf.tree.query((P - T[:3, 3]) @ T[:3, :3])[0]
        assert np.array_equal(e[v, u], d < tol) and not e[depth == 0].any()
        assert 0.001 < (d < tol).mean() < 0.9


def test_unexplained_parts_large_enough_are_split_off():
    depth, a, b, T = _two_patches()
    e = ModelSurface(_square_face(0.04)).explained(T, a | b, depth, K, tol=0.004)
    parts = unexplained_parts(a | b, e, depth, SplitConfig())
    assert len(parts) == 1 and (parts[0] == b).mean() > 0.999  # the 3x3 opening leaves the square's pixels
    assert unexplained_parts(a | b, e, depth, SplitConfig(min_pixels=b.sum() + 1)) == []
    assert unexplained_parts(a | b, e, depth, SplitConfig(min_share=0.6)) == []  # b is half of the mask
    assert unexplained_parts(a, e, depth, SplitConfig()) == []  # a mask its model explains
    speck = np.zeros_like(a)
    speck[10:12, 10:12] = True
    assert unexplained_parts(a | speck, e, np.where(speck, 0.3, depth), SplitConfig(min_pixels=1)) == []  # opened away


def test_parts_at_the_image_border_are_the_whole_images():
    """The test runs in the mask's box (widened by a pixel): its parts, at the image's border and at the box's edge,
    are those the opening and the connected components give on the whole image."""
    import cv2

    depth = np.full((240, 320), 0.5)
    mask = np.zeros((240, 320), dtype=bool)
    mask[0:60, 250:320] = True  # at the top and right borders
    unexplained = np.zeros_like(mask)
    unexplained[0:20, 295:320] = True  # in the corner
    unexplained[40:60, 260:280] = True  # at the box's bottom edge
    unexplained[5:30, 250:252] = True  # at its left edge, 2 px wide: the opening removes it
    unexplained[30:33, 280:300] = True  # a strip 3 px wide, which the opening keeps
    explained = mask & ~unexplained
    rest = cv2.morphologyEx(unexplained.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, comp = cv2.connectedComponents(rest, connectivity=8)
    parts = unexplained_parts(mask, explained, depth, SplitConfig(min_pixels=1, min_share=0.0))
    assert len(parts) == n - 1 == 3
    assert all((p == (comp == i)).all() for i, p in enumerate(parts, start=1))


def test_two_poses_are_one_place_when_they_put_the_model_on_its_own_surface():
    """``same_place``: a 4 cm square's points at a pose against its surface at another: the same pose, or one a
    symmetry of the square apart (turned 90 deg about its normal), is one place; 1 cm off its plane it is not, nor 3 cm
    beside it (median distance 1 and 2 cm), while 1 cm beside it, still mostly on the square, is."""
    from posegrasp.geometry import axis_angle_R, make_T
    from posegrasp.perception.split import same_place

    face = _square_face(0.04, 100)
    surface = ModelSurface(face)
    T = make_T(axis_angle_R(np.array([1.0, 0.0, 0.0]), 0.4), np.array([0.02, -0.01, 0.5]))
    turned = T @ make_T(axis_angle_R(np.array([0.0, 0.0, 1.0]), np.pi / 2), np.zeros(3))
    moved = [T @ make_T(np.eye(3), np.array(d)) for d in ([0.0, 0.0, 0.01], [0.03, 0.0, 0.0], [0.01, 0.0, 0.0])]
    points = face[::7]
    assert same_place(points, T, surface, T, 0.001) and same_place(points, turned, surface, T, 0.001)
    assert [same_place(points, M, surface, T, 0.005) for M in moved] == [False, False, True]
    assert same_place(points, moved[0], surface, T, 0.02)  # within a wider tolerance
