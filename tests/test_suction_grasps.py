"""Suction grasps on the estimated model (``grasping.suction_grasps``): where a cup seals, how it comes down and what
it clears, on the shipped blocks; no simulator."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from posegrasp.catalog import load_catalog
from posegrasp.errors import ConfigError
from posegrasp.geometry import axis_angle_R, make_T
from posegrasp.grasping.grasps import _box_distance
from posegrasp.grasping.suction_grasps import (SLIDE_STEPS, CupGeometry, CupSurroundings, cup_spots, plan_suction,
                                               seal_margins, unsealable)
from posegrasp.grasping.tasks.bin_pick.config import BinPickConfig

CUP = CupGeometry(radius=0.0125, body_radius=0.0125)  # 25 mm, on the Jaco's palm with its camera
B = BinPickConfig()
NOTHING = np.zeros((0, 3))
UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def cat():
    return load_catalog("")


def _open(yaw: float = 0.3) -> CupSurroundings:
    return CupSurroundings(NOTHING, NOTHING, 0.0, yaw)


def _on_floor(part, R=np.eye(3), xy=(0.5, 0.0)) -> np.ndarray:
    """The part turned by ``R`` resting on the floor (z = 0) at ``xy``."""
    T = make_T(R, (*xy, 0.0))
    T[2, 3] = -float((part.vertices @ R.T)[:, 2].min())
    return T


def test_a_flat_face_is_gripped_near_its_centre_first(cat):
    cube = cat["cube"]
    T = _on_floor(cube)
    grasps = plan_suction(cube, T, _open(), CUP, B)
    assert len(grasps) >= 3
    best = grasps[0]
    top = T[:3, 3] + [0.0, 0.0, 0.02]
    assert np.linalg.norm(best.T_world_gripper[:3, 3] - top) < 1e-6  # the top face's centre, on the surface
    assert np.allclose(best.T_world_gripper[:3, 2], -UP) and best.tilt_deg < 1e-6
    assert best.edge_margin == SLIDE_STEPS[-1] and best.com_distance < 1e-6
    assert best.turn < 1e-6 and np.isclose(np.arctan2(*best.T_world_gripper[1::-1, 0]), 0.3)  # the wrist as it is
    scores = [g.score for g in grasps]
    assert scores == sorted(scores, reverse=True)
    for g in grasps:  # every cup on the top face, its rim on it
        p = g.T_world_gripper[:3, 3] - top
        assert abs(p[2]) < 1e-9 and np.abs(p[:2]).max() <= 0.02 - CUP.radius + 1e-9
    assert [g.com_distance for g in grasps[:3]] == sorted(g.com_distance for g in grasps[:3])


def test_a_rim_across_an_edge_or_over_studs_does_not_seal(cat):
    cube, brick = cat["cube"], cat["brick_2x4"]
    top = np.array([[0.0, 0.0, 0.02], [0.005, 0.0, 0.02], [0.015, 0.0, 0.02], [0.012, 0.012, 0.02]])
    seal, edge = seal_margins(cube, top, np.tile(UP, (4, 1)), CUP)
    assert seal[0] == pytest.approx(CUP.seal_tol) and edge[0] == SLIDE_STEPS[-1]
    assert seal[1] == pytest.approx(CUP.seal_tol) and edge[1] == 0.002  # 2.5 mm from the edge's reach
    assert np.isnan(seal[2:]).all()  # 5 mm from an edge, near a corner: the rim hangs over
    body_top = brick.extents[2] / 2 - 0.0045
    between = np.array([[0.0, 0.0, body_top], [0.0159, 0.0, body_top], [0.0079, 0.0079, 0.0]])
    between[2, 2] = brick.extents[2] / 2  # a stud's top
    seal, _ = seal_margins(brick, between, np.tile(UP, (3, 1)), CUP)
    assert np.isnan(seal).all()


def test_a_studs_up_brick_gets_no_cup_on_its_studs(cat):
    brick = cat["brick_2x4"]
    assert plan_suction(brick, _on_floor(brick), _open(), CUP, B) == []  # studs up: nothing flat enough faces up
    down = _on_floor(brick, axis_angle_R(np.array([1.0, 0.0, 0.0]), np.pi))
    grasps = plan_suction(brick, down, _open(), CUP, B)  # studs down: its flat bottom
    assert grasps and all(np.isclose(g.T_world_gripper[2, 3], brick.extents[2]) for g in grasps)
    small = CupGeometry(radius=0.003, body_radius=0.004)  # a 6 mm cup fits on a stud's top and between studs ...
    spots = cup_spots(brick, small)
    on_top = spots.points[np.abs(spots.normals @ UP - 1.0) < 1e-9]
    assert len(on_top)
    studs = np.array([[(i + 0.5) * 0.0159 - 0.0318, (j + 0.5) * 0.0159 - 0.0159] for i in range(4) for j in range(2)])
    to_stud = np.linalg.norm(on_top[:, None, :2] - studs[None], axis=2)
    assert np.all(np.abs(to_stud - 0.0047) >= small.radius - 1e-4)  # ... but its rim never crosses a stud's edge


@pytest.mark.parametrize("deg", [20.0, 60.0])
def test_a_tilted_part_is_approached_along_its_face_normal(cat, deg):
    cube = cat["cube"]
    R = axis_angle_R(np.array([1.0, 0.0, 0.0]), np.radians(deg))
    grasps = plan_suction(cube, _on_floor(cube, R), _open(), CUP, B)
    assert grasps
    normals = np.concatenate([R, -R], 1).T  # the cube's face normals in the world
    want = min(deg, 90.0 - deg)  # at 60 deg the face turned 30 deg from up is the one
    for g in grasps:
        z = g.T_world_gripper[:3, 2]
        assert np.isclose(g.tilt_deg, want) and g.tilt_deg <= B.suction_max_tilt_deg
        assert np.isclose((-normals @ z).max(), 1.0)  # along a face's inward normal
        assert np.isclose(np.degrees(np.arccos(-z[2])), g.tilt_deg)
        assert np.isclose(g.T_world_gripper[:3, :3] @ g.T_world_gripper[:3, :3].T, np.eye(3)).all()


def test_the_tool_clears_a_wall_and_a_neighbour(cat):
    cube = cat["cube"]
    T = _on_floor(cube)
    cx = T[0, 3]
    yy, zz = np.meshgrid(np.arange(-0.1, 0.1, 0.003), np.arange(0.0, 0.3, 0.003))
    wall = np.stack([np.full(yy.size, cx + 0.03), yy.ravel(), zz.ravel()], 1)
    slim = CupGeometry(wrist=(((-0.02, -0.02, -1.0), (0.02, 0.02, -0.06)),))
    free = plan_suction(cube, T, _open(), slim, B)
    grasps = plan_suction(cube, T, CupSurroundings(NOTHING, wall, 0.0, 0.0), slim, B)
    assert grasps and len(grasps) < len(free)
    for g in grasps:
        local = (wall - g.T_world_gripper[:3, 3]) @ g.T_world_gripper[:3, :3]
        assert _box_distance(local, *slim.boxes()[0]).min() >= B.suction_wall_clearance
        assert g.T_world_gripper[0, 3] <= cx + 0.03 - 0.02 - B.suction_wall_clearance + 1e-9
    assert plan_suction(cube, T, CupSurroundings(NOTHING, wall, 0.0, 0.0), CUP, B) == []  # a wide wrist: none
    # a neighbour's points: the same, with their own clearance
    grasps = plan_suction(cube, T, CupSurroundings(wall, NOTHING, 0.0, 0.0), slim, B)
    assert grasps and all(g.T_world_gripper[0, 3] <= cx + 0.03 - 0.02 - B.suction_clearance + 1e-9 for g in grasps)


def test_the_wrist_turns_least_to_clear_a_wall(cat):
    cube = cat["cube"]
    T = _on_floor(cube)
    camera = CupGeometry(wrist=(((-0.02, -0.02, -1.0), (0.06, 0.02, -0.06)),))  # a camera out on +x
    wall = np.stack([np.full(50, T[0, 3] + 0.035), np.linspace(-0.1, 0.1, 50), np.full(50, 0.1)], 1)
    grasps = plan_suction(cube, T, CupSurroundings(NOTHING, wall, 0.0, 0.0), camera, B)
    assert grasps and all(np.isclose(g.turn, np.pi / 2) for g in grasps)  # a quarter turn before a half
    assert all(np.isclose(abs(g.T_world_gripper[1, 0]), 1.0) for g in grasps)


def test_a_cup_off_the_floor_and_the_parts_own_faces(cat):
    prism = cat["triangular_prism"]  # lying on a rectangle: its slanted faces 60 deg from up
    assert plan_suction(prism, _on_floor(prism), _open(), CUP, B) == []
    cube = cat["cube"]  # turned 38 deg: a wrist long along the slope would strike the floor below its face ...
    tilted = _on_floor(cube, axis_angle_R(np.array([1.0, 0.0, 0.0]), np.radians(38.0)))
    long = CupGeometry(body_length=0.02, stroke=0.0, wrist=(((-0.02, -0.1, -1.0), (0.02, 0.1, -0.02)),))
    grasps = plan_suction(cube, tilted, _open(0.0), long, B)
    assert grasps and all(np.isclose(g.tilt_deg, 38.0) for g in grasps)  # the face 38 deg from up, not 52
    corners = np.array([[x, y, -0.02] for x in (-0.02, 0.02) for y in (-0.1, 0.1)])
    for g in grasps:
        assert (corners @ g.T_world_gripper[:3, :3].T + g.T_world_gripper[:3, 3])[:, 2].min() >= 0.0
    assert any(np.isclose(g.turn, np.pi / 2) for g in grasps)  # ... so it turns a quarter there, across the slope
    no_floor = CupSurroundings(NOTHING, NOTHING, -1.0, 0.0)
    assert all(g.turn == 0.0 for g in plan_suction(cube, tilted, no_floor, long, B))
    l_block = cat["l_block"]  # the foot's top beside the leg: the cup's body would hit the leg
    spots = cup_spots(l_block, CUP)
    foot_top = spots.points[(np.abs(spots.normals @ UP - 1.0) < 1e-9) & (spots.points[:, 2] < 0.0)]
    assert not len(foot_top)


def test_spots_are_seeded(cat):
    cube = cat["cube"]
    a, b = cup_spots.__wrapped__(cube, CUP, 400, 0), cup_spots.__wrapped__(cube, CUP, 400, 0)
    assert a.points.tobytes() == b.points.tobytes() and a.edge_margin.tobytes() == b.edge_margin.tobytes()
    other = cup_spots.__wrapped__(cube, CUP, 400, 1)
    assert other.points.tobytes() != a.points.tobytes()
    T = _on_floor(cube)
    first = [g.T_world_gripper.tobytes() for g in plan_suction(cube, T, _open(), CUP, B)]
    assert first == [g.T_world_gripper.tobytes() for g in plan_suction(cube, T, _open(), CUP, B)]


def test_which_blocks_a_cup_cannot_seal_on(cat):
    blocks = list(cat.values())
    assert unsealable(blocks, CUP) == []  # 25 mm: every block has a face (the long cuboid's fit it exactly)
    mid = CupGeometry(radius=0.0175, body_radius=0.0195)
    assert set(unsealable(blocks, mid)) == set(cat) - {"cube", "triangular_prism"}
    huge = CupGeometry(radius=0.05, body_radius=0.05)
    assert unsealable(blocks, huge) == list(cat)


def test_a_bad_cup_is_refused():
    with pytest.raises(ConfigError, match="body_radius"):
        CupGeometry(radius=0.02, body_radius=0.01)
    with pytest.raises(ConfigError, match="radius"):
        CupGeometry(radius=0.0)
    with pytest.raises(ConfigError, match="wrist boxes"):  # pressed by the stroke, the palm would reach the rim
        CupGeometry(wrist=(((-0.05, -0.05, -1.0), (0.05, 0.05, -0.005)),))
    pressed = CupGeometry(stroke=0.01).boxes()
    assert np.isclose(pressed[0][1][2], -0.06)  # the palm's face, 70 mm up at rest, 60 mm up with the cup pressed


def test_far_points_are_left_out_of_the_clearance_check_alone(cat, monkeypatch):
    """A seeded heap of estimates: the grasps are those of the check against every point (``_within_reach`` only
    leaves out points no tool could come near)."""
    import posegrasp.grasping.suction_grasps as sg
    from posegrasp.grasping.grasps import surface_points
    from posegrasp.geometry import transform_points

    rng = np.random.default_rng(3)
    parts = [cat[n] for n in ("cube", "triangular_prism", "long_cuboid", "brick_2x4", "cube", "arch", "l_block")]
    poses = []
    for p in parts:
        q = rng.normal(size=4)
        w, x, y, z = q / np.linalg.norm(q)
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        poses.append(make_T(R, (*rng.uniform(-0.07, 0.07, 2) + [0.5, 0.0], rng.uniform(0.02, 0.09))))
    clouds = [transform_points(T, surface_points(p, 300)) for p, T in zip(parts, poses)]
    yy, zz = np.meshgrid(np.arange(-0.15, 0.15, 0.005), np.arange(0.0, 0.1, 0.005))
    wall = np.stack([np.full(yy.size, 0.6), yy.ravel(), zz.ravel()], 1)
    found = 0
    for j, (p, T) in enumerate(zip(parts, poses)):
        around = CupSurroundings(np.concatenate([c for i, c in enumerate(clouds) if i != j]), wall, 0.0, 1.0)
        fast = plan_suction(p, T, around, CUP, B)
        with monkeypatch.context() as m:
            m.setattr(sg, "_within_reach", lambda a, *_: a)
            full = plan_suction(p, T, around, CUP, B)
        assert [g.T_world_gripper.tobytes() for g in fast] == [g.T_world_gripper.tobytes() for g in full]
        assert [g.clearance for g in fast] == [g.clearance for g in full]
        found += bool(fast)
    assert found >= 2


def test_the_wrist_clearance_measures_only_near_points_and_gets_every_distance():
    """``_nearest`` skips the points farther than its cap from the wrist boxes' bounds: the same distances (to the
    last bit) as the distance of every point to every box, capped."""
    import posegrasp.grasping.suction_grasps as sg

    rng = np.random.default_rng(5)
    T = np.stack([make_T(axis_angle_R(rng.normal(size=3), rng.uniform(0, 3)), rng.uniform(-0.05, 0.05, 3))
                  for _ in range(150)])
    pts = rng.normal(scale=0.4, size=(300, 3))
    full = np.array([min(_box_distance((pts - t[:3, 3]) @ t[:3, :3], lo, hi).min() for lo, hi in CUP.boxes())
                     for t in T])
    got = sg._nearest(T, pts, CUP, body=False)
    assert np.array_equal(got, np.minimum(full, sg._CLEAR))
    assert 0 < np.count_nonzero(full < sg._CLEAR) < len(T)  # some poses near a point, some clear of all


def _mesh_part(mesh, name: str):
    """A ``PartType`` of a trimesh solid (m), centred on its bounding box: any imported shape."""
    from posegrasp.catalog import PartType

    v = np.asarray(mesh.vertices) - mesh.bounds.mean(0)
    return PartType(1, name, v, np.asarray(mesh.faces), 0.1, (), float(np.linalg.norm(mesh.extents)),
                    np.asarray(mesh.extents), (), ())


def test_a_curved_part_seals_where_it_is_flat_enough_across_the_rim():
    """A ball's cap under a 25 mm rim sags r - sqrt(r^2 - 12.5^2): 1.3 mm on a 60 mm ball (within the 1.5 mm
    tolerance), 2.0 mm on a 40 mm one."""
    import trimesh

    big, small = (_mesh_part(trimesh.creation.icosphere(subdivisions=4, radius=r), f"ball_{r}") for r in (0.06, 0.04))
    assert unsealable([big, small], CUP) == ["ball_0.04"]
    spots = cup_spots(big, CUP)
    assert np.all(spots.seal_margin > 0.0) and np.all(spots.seal_margin < CUP.seal_tol - 0.001)  # curved: less margin
    flush = dataclasses.replace(B, suction_min_edge_margin=0.0)  # a curved cap has no edge margin to spare
    grasps = plan_suction(big, make_T(np.eye(3), (0.5, 0.0, 0.06)), _open(), CUP, flush)
    assert grasps and grasps[0].tilt_deg < 5.0  # the ball's top first: least tilt, centre of mass under the cup


def _grid(x0: float, x1: float, y0: float, y1: float, z: float, step: float = 0.0015) -> np.ndarray:
    """Depth-image-like points (world, m) every ``step`` over a level patch at height ``z``."""
    x, y = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], 1)


def test_the_depth_image_confirms_a_seal_only_on_a_face_that_is_there(cat):
    from posegrasp.grasping.suction_grasps import seen_seals

    cube = cat["cube"]
    T = _on_floor(cube, xy=(0.5, 0.0))  # its top face, 40 mm across, at z = 40 mm; the floor round it
    floor = _grid(0.44, 0.56, -0.06, 0.06, 0.0)
    seen = np.concatenate([floor[np.abs(floor[:, :2] - [0.5, 0.0]).max(1) > 0.02], _grid(0.48, 0.52, -0.02, 0.02, 0.04)])
    grasps = plan_suction(cube, T, _open(), CUP, B)
    poses = np.stack([g.T_world_gripper for g in grasps])
    assert seen_seals(poses, seen, CUP.radius, 0.003).all()  # the estimate is right: every grasp confirmed
    off = poses.copy()
    off[:, 0, 3] += 0.015  # the estimate 15 mm off: a rim that then reaches past the face's edge, over the floor
    past = off[:, 0, 3] + CUP.radius > 0.52 + 0.002
    assert past.any() and not seen_seals(off[past], seen, CUP.radius, 0.003).any()
    stud = np.concatenate([seen, [[0.5, 0.0, 0.046]]])  # something rises into the cup over the face's centre
    centre = poses[:1]
    assert not seen_seals(centre, stud, CUP.radius, 0.003)[0]
    half = seen[seen[:, 0] < 0.5]  # nothing seen on one side of the rim: no seal confirmed
    assert not seen_seals(centre, half, CUP.radius, 0.003)[0]
    assert not seen_seals(centre, NOTHING, CUP.radius, 0.003)[0]
    # in the planner: with what the camera sees, the 15 mm-off estimate keeps no grasp; without it, all of them
    T_off = T.copy()
    T_off[0, 3] += 0.015
    looks = dataclasses.replace(_open(), seen=seen)
    assert plan_suction(cube, T_off, looks, CUP, B) == [] and len(plan_suction(cube, T_off, _open(), CUP, B)) > 0
    assert len(plan_suction(cube, T, looks, CUP, B)) == len(grasps)
