"""The ways a block rests on a plane, from its convex hull and centre of mass."""

import numpy as np
import pytest
import trimesh

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.perception.depth_fit.rests import Rests, up_classes
from posegrasp.perception.depth_fit.starts import cube_rotations


def _symmetries(obj_id: int) -> tuple[np.ndarray, np.ndarray]:
    return bop.load_models_info("assets/blocks")[obj_id].symmetry_rotations()


def test_a_box_rests_on_its_six_faces():
    rests = Rests.of_mesh(trimesh.creation.box((0.08, 0.025, 0.025)), np.zeros((0, 3, 3)), np.zeros((0, 3)))
    assert sorted(map(tuple, np.round(rests.ups).astype(int))) == sorted(map(tuple, Rests.axes().ups.astype(int)))
    assert len(set(rests.labels.tolist())) == 6  # no symmetry given: six classes
    cube = Rests.of_mesh(trimesh.creation.box((0.04,) * 3), cube_rotations()[1:], np.zeros((0, 3)))
    assert set(cube.labels.tolist()) == {0}  # the cube's rotations map every face onto every other


def test_the_l_block_also_stands_as_an_inverted_v():
    """The shipped L-block (an upright L in the x-z plane, bars 50 x 25 x 25 mm) rests on a side face (+-y), on
    either bar (+z, +x), on either bar's end (-x, -z), and on the ends of both bars, corner up: (-1, 0, -1) / sqrt 2;
    its half turn about (1, 0, 1) maps each pair onto itself, so these are 4 classes."""
    rests = Rests.of_mesh(bop_models.load_model("assets/blocks", 8), *_symmetries(8))
    ups = np.round(rests.ups, 3)
    assert len(ups) == 7 and [-0.707, 0.0, -0.707] in ups.tolist()
    label = {tuple(u): int(c) for u, c in zip(ups.tolist(), rests.labels)}
    assert label[(0.0, 0.0, 1.0)] == label[(1.0, 0.0, 0.0)] != label[(0.0, 0.0, -1.0)]
    assert len(set(rests.labels.tolist())) == 4


def test_a_lying_cylinders_hull_sides_are_one_rest_class():
    rests = Rests.of_mesh(bop_models.load_model("assets/blocks", 5), *_symmetries(5))
    side = np.abs(rests.ups[:, 2]) < 1e-6
    assert side.sum() == 48 and len(set(rests.labels[side].tolist())) == 1
    assert len(set(rests.labels.tolist())) == 2  # standing on either cap (the flip about x), lying


def test_up_classes_and_rests_name_bad_input():
    ups = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    half_turn_x = np.diag([1.0, -1.0, -1.0])[None]
    assert up_classes(ups, half_turn_x, np.zeros((0, 3))).tolist() == [0, 0]
    assert up_classes(ups, np.zeros((0, 3, 3)), np.zeros((0, 3))).tolist() == [0, 1]
    with pytest.raises(ValueError, match="unit vectors"):
        Rests(2 * ups, np.arange(2))
    with pytest.raises(ValueError, match=r"ups \(U, 3\)"):
        Rests(ups[:, :2], np.arange(2))
