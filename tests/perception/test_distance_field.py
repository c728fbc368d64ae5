import numpy as np
import pytest
import torch
import trimesh

from posegrasp.perception.depth_fit.distance_field import DistanceField, Fields

SIZE = np.array([0.06, 0.03, 0.02])  # a 60 x 30 x 20 mm box about its centre


def box_distance(p: np.ndarray) -> np.ndarray:
    """Exact unsigned distance (N,) of points (N, 3) from the box's surface."""
    q = np.abs(p) - SIZE / 2
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    return np.abs(outside + np.minimum(q.max(axis=1), 0))


@pytest.fixture(scope="module")
def field() -> DistanceField:
    return DistanceField.of_mesh(trimesh.creation.box(SIZE), samples=20000, seed=0)


def test_the_field_gives_a_box_its_distances(field):
    """Near the surface, outside and inside, the trilinear field is within 0.05 mm of the exact distance on average
    (the nearest of 1500 surface points: tenths of a mm); on a face's plane it is 0 but by its edges (the nodes next to the
    face take the distance to its plane, and the signed field is linear across it), and beyond the grid it is the
    margin."""
    rng = np.random.default_rng(0)
    s, _ = trimesh.sample.sample_surface(trimesh.creation.box(SIZE), 3000, seed=1)
    p = s + rng.normal(size=s.shape) * 0.002
    err = np.abs(field(torch.from_numpy(p).float()).numpy() - box_distance(p))
    assert err.mean() < 5e-5 and np.percentile(err, 95) < 2e-4
    face = np.column_stack([rng.uniform(-0.02, 0.02, 200), rng.uniform(-0.01, 0.01, 200), np.full(200, 0.01)])
    assert np.percentile(field(torch.from_numpy(face).float()).numpy(), 95) < 1e-5
    far = torch.tensor([[0.2, 0.0, 0.0], [0.0, -0.05, 0.0]])
    np.testing.assert_allclose(field(far).numpy(), 0.01)


def test_fields_look_up_each_row_in_its_own_object(field):
    """Two fields as one lookup give each row what its own field gives it."""
    other = DistanceField(np.random.default_rng(2).uniform(-0.02, 0.02, (400, 3)))  # unsigned, of points
    fields = Fields([field, other])
    p = torch.from_numpy(np.random.default_rng(3).uniform(-0.04, 0.04, (4, 100, 3))).float()
    obj = torch.tensor([1, 0, 0, 1])
    d = fields(p.transpose(1, 2), obj)
    for h, o in enumerate(obj.tolist()):
        torch.testing.assert_close(d[h], (field, other)[o](p[h]))


def test_distance_field_rejects_bad_input():
    with pytest.raises(ValueError, match="cell"):
        DistanceField(np.zeros((4, 3)), cell=0.0)
    with pytest.raises(ValueError, match="shape"):
        DistanceField(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="samples"):
        DistanceField.of_mesh(trimesh.creation.box(SIZE), samples=0)
