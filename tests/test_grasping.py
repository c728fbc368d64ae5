"""Controller, grasp candidates and perception providers on the real simulator and renderer."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from posegrasp.grasping.config import ControlConfig, GraspConfig
from posegrasp.grasping.controller import ArmController, finger_angle_for_opening, open_finger_points
from posegrasp.grasping.hand import KG2, KG3
from posegrasp.grasping.grasps import object_candidates, plan_grasps, squeeze_axes, surface_points
from posegrasp.grasping.support import RestConfig, rest_on_table
from posegrasp.grasping.perception import NoisyOracleProvider, OracleProvider, observation, visible_enough
from posegrasp.grasping.provider_registry import make_provider
from posegrasp.catalog import load_catalog, symmetry_transforms
from posegrasp.errors import UserError
from posegrasp.geometry import axis_angle_R, make_T, rotation_angle, transform_points
from posegrasp.sim.camera import CameraRenderer, Frame
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.scene import make_scene
from posegrasp.sim.workcell import HAND_CAMERA, Workcell

DOWN = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # gripper z down, x along -y


@pytest.fixture(scope="module")
def arm():
    wc = Workcell(WorkcellConfig())
    wc.reset(wc.look_q)
    return wc


def test_straight_segment_within_joint_speed_limits(arm):
    ctl = ArmController(arm, ControlConfig(), arm.look_q)
    start = make_T(DOWN, (0.40, 0.05, 0.15))
    assert ctl.move(start)
    goal = make_T(DOWN, (0.50, -0.10, 0.10))
    line = goal[:3, 3] - start[:3, 3]
    dev, speed = [], []

    def watch():
        p = arm.gripper_pose()[:3, 3] - start[:3, 3]
        dev.append(np.linalg.norm(p - np.clip(p @ line / (line @ line), 0, 1) * line))
        speed.append(np.abs(arm.data.qvel[arm.arm_dadr]) / arm.arm_velocity_limits())

    ctl.monitor = watch
    assert ctl.move(goal)
    dp, dr = ctl.pose_error(goal)
    assert dp < ctl.cfg.pos_tol and np.degrees(dr) < ctl.cfg.rot_tol_deg
    assert max(dev) < 0.015  # stays on the straight line
    assert np.max(speed) <= 1.02  # the Jaco2's joint velocity limits hold (measured)
    assert np.max(speed) > 0.5  # and the move is not needlessly slow


def test_a_hand_held_off_its_goal_by_the_posture_term_is_brought_on(arm, monkeypatch):
    """A posture pull 3x the default holds the hand 5.8 mm short of this goal; the integral action of
    ``wait_reached`` brings it within the tolerance."""
    import posegrasp.grasping.controller as C

    goal = make_T(DOWN, (0.55, -0.15, 0.08))
    reached = []
    for gain in (0.0, C.REACH_GAIN):
        monkeypatch.setattr(C, "REACH_GAIN", gain)
        arm.reset(arm.look_q)
        ctl = ArmController(arm, ControlConfig(posture_cost=0.03), arm.look_q)
        reached.append(ctl.move(goal))
    assert reached == [False, True]


def test_null_offset_takes_up_what_the_arm_lacks_at_a_goal(arm):
    """The arm stops millimetres off a goal it counts as reached (within ``pos_tol``); ``null_offset`` moves the
    tracked target on until the hand is on it, and says by how much."""
    arm.reset(arm.look_q)
    ctl = ArmController(arm, ControlConfig(posture_cost=0.03), arm.look_q)
    goal = make_T(DOWN, (0.55, -0.15, 0.08))
    assert ctl.move(goal)
    before = np.linalg.norm(arm.gripper_pose()[:2, 3] - goal[:2, 3])
    off = ctl.null_offset(goal, 0.005, 1.0)
    after = np.linalg.norm(arm.gripper_pose()[:2, 3] - goal[:2, 3])
    assert before > 0.002 and after < 0.25 * before, (before, after)
    assert np.allclose(ctl.target[:2, 3], goal[:2, 3] + off) and np.linalg.norm(off) > 0.5 * before


def test_reposture_reaches_a_tilted_goal_the_posture_term_holds_off():
    """A goal tilted 38 deg far from the look pose: the posture term holds the hand millimetres off it (the move
    times out); with ``reposture`` it points the posture at the goal's IK angles and gets there; ``pose_toward(None)``
    points it back at the look pose."""
    wc = Workcell(WorkcellConfig(hand="hybrid"))
    goal = make_T(axis_angle_R(np.array([0.0, -1.0, 0.0]), np.radians(38.0)) @ DOWN, (0.45, 0.15, 0.16))
    runs = []
    for reposture in (False, True):
        wc.reset(wc.look_q)
        ctl = ArmController(wc, ControlConfig(), wc.look_q)
        look = ctl.posture.target_q.copy()
        runs.append((ctl.move(goal, reposture=reposture), ctl.pose_error(goal)[0]))
    assert runs[0][0] is False and 0.004 < runs[0][1] < 0.01, runs  # held off, not blocked
    assert runs[1][0] is True and runs[1][1] < 0.004, runs
    assert not np.allclose(ctl.posture.target_q, look)
    ctl.pose_toward(None)
    assert np.array_equal(ctl.posture.target_q, look)


def test_a_wrist_wound_whole_turns_moves_as_an_unwound_one():
    """The arm's endless joints are not wrapped: a wrist wound four turns (as set-downs in a tray leave it) is the
    same arm pose, and the posture term, kept within half a turn of it, lets the hand make the same move in the same
    time (pulled back by four turns, the hand stopped 8 mm short of the goal and the move timed out)."""
    wc = Workcell(WorkcellConfig(hand="hybrid"))
    wrist = wc.arm_joint_names.index("jaco_arm/joint_6")
    moves = []
    for turns in (0, -4):
        q = wc.look_q.copy()
        q[wrist] += 2.0 * np.pi * turns
        wc.reset(q)
        ctl = ArmController(wc, ControlConfig(), wc.look_q)
        goal = wc.gripper_pose()
        goal[:3, 3] += (0.05, 0.0, -0.12)
        moves.append((ctl.move(goal, speed=0.25), round(wc.data.time, 6), ctl.pose_error(goal)[0]))
    assert moves[0][:2] == moves[1][:2] and moves[0][0], moves
    assert abs(moves[1][2] - moves[0][2]) < 1e-4, moves


def test_table_collision_avoidance_stops_the_fingers(arm):
    ctl = ArmController(arm, ControlConfig(), arm.look_q)
    assert ctl.move(make_T(DOWN, (0.45, 0.0, 0.06)))
    assert not ctl.move(make_T(DOWN, (0.45, 0.0, -0.05)))  # the open fingertips would be in the table
    table = arm.model.geom("table").id
    hand = [i for i in range(arm.model.ngeom) if ctl.robot_geom[i] and arm.model.geom_contype[i]
            and "jaco_hand" in arm.model.geom(i).name]
    gap = min(mujoco.mj_geomDistance(arm.model, arm.data, g, table, 0.05, None) for g in hand)
    assert 0.0 < gap < 0.01, gap  # held just above the table, not in it


@pytest.mark.parametrize("hand", ["3-finger", "2-finger"])
def test_fingers_preshape_to_an_opening(arm, hand):
    wc = Workcell(WorkcellConfig(hand=hand))
    wc.reset(wc.look_q)
    ctl = ArmController(wc, ControlConfig(), wc.look_q)
    for opening in (0.08, 0.05):
        ctl.preshape(opening)
        ctl.hold(0.8)
        q = finger_angle_for_opening(wc.cfg, opening)
        assert np.allclose(wc.data.qpos[wc.finger_qadr], q, atol=0.03)
    assert finger_angle_for_opening(wc.cfg, 0.08) < finger_angle_for_opening(wc.cfg, 0.05)


def test_the_2_finger_hands_fingers_face_each_other_centred_on_the_pinch_point():
    cfg = WorkcellConfig(hand="2-finger")
    assert Workcell(cfg).finger_numbers.tolist() == [1, 3]
    for mm in (30, 60, 90):
        pts = open_finger_points(cfg, mm)
        x, y = pts[:, 0], pts[:, 1]
        assert abs(x[x > 0].min() + x[x < 0].max()) < 5e-4  # mirror images across the pinch point
        for side in (x > 0, x < 0):  # each finger 23 mm wide, centred on the gripper's xz plane
            assert abs(y[side].min() + y[side].max()) < 5e-4 and 0.011 < y[side].max() <= KG2.finger1_y[0][1]


def test_candidates_are_closed_under_symmetry():
    for block in load_catalog().values():
        C = object_candidates(block)
        for S in symmetry_transforms(block)[:6]:
            for T in C[:10]:
                moved = S @ T
                d = np.linalg.norm(C[:, :3, 3] - moved[:3, 3], axis=1) + np.abs(C[:, :3, :3] - moved[:3, :3]).sum((1, 2))
                assert d.min() < 5e-3, block.name


def test_squeeze_axes_skip_studs_and_round_ends():
    cat = load_catalog()
    assert squeeze_axes(cat["brick_2x4"]) == [0, 1]  # not across the studs (z)
    assert squeeze_axes(cat["cylinder"]) == [0, 1]  # not along the axis of the round ends
    assert squeeze_axes(cat["cube"]) == [0, 1, 2]
    assert squeeze_axes(cat["brick_2x4"], all_axes=True) == squeeze_axes(cat["cylinder"], all_axes=True) == [0, 1, 2]


@pytest.mark.parametrize("name", ["brick_2x4", "cylinder"])
def test_only_the_2_finger_hand_squeezes_across_studs_and_round_ends(name):
    """A brick lying on its side (studs facing along world x) and a lying cylinder (its axis along world x): the
    3-finger hand never squeezes along that axis, the 2-finger hand does."""
    block = load_catalog()[name]
    T = make_T(axis_angle_R(np.array([0.0, 1.0, 0.0]), np.pi / 2), (0.45, 0.0, 0.04))
    along = {}
    for hand in (KG3, KG2):
        grasps = plan_grasps(block, T, np.zeros((0, 3)), GraspConfig(), 0.0, hand=hand)
        assert grasps
        along[hand] = [g for g in grasps if abs(g.T_world_gripper[0, 0]) > 0.99]
    assert not along[KG3] and along[KG2]


def test_grasps_avoid_a_neighbour():
    block = load_catalog()["long_cuboid"]
    T = make_T(np.eye(3), (0.45, 0.0, 0.0125))
    free = plan_grasps(block, T, np.zeros((0, 3)), GraspConfig(), yaw_now=0.0)
    narrow_middle = [g for g in free if g.width < 0.03 and abs(g.T_world_gripper[0, 3] - 0.45) < 0.01]
    assert narrow_middle and {round(g.width, 3) for g in free} == {0.025, 0.08}
    # A cube right beside the cuboid's middle, where the fingers would go for a centred pinch.
    cube = load_catalog()["cube"]
    nb = transform_points(make_T(np.eye(3), (0.45, 0.045, 0.02)), surface_points(cube, 300))
    crowded = plan_grasps(block, T, nb, GraspConfig(), yaw_now=0.0)
    assert len(crowded) < len(free)
    assert all(g.clearance >= GraspConfig().clearance_min for g in crowded)
    assert crowded and not [g for g in crowded if g.width < 0.03 and abs(g.T_world_gripper[0, 3] - 0.45) < 0.01]


@pytest.fixture(scope="module")
def look_frame():
    scene = make_scene(5, 4)
    wc = scene.workcell
    assert wc.drive_arm(wc.look_q)
    wc.set_block_pose(4, make_T(np.eye(3), (-0.4, -0.4, 0.02)))  # out of the camera's view
    mujoco.mj_forward(wc.model, wc.data)
    c = wc.cfg.hand_camera
    cam = CameraRenderer(wc, HAND_CAMERA, c)
    frame = cam.capture()
    cam.close()
    return frame


def test_oracle_reports_only_visible_blocks(look_frame):
    est = OracleProvider().estimate_truth(look_frame, seed=0)
    assert len(est) == 3
    for e, k in zip(est, (1, 2, 3)):
        assert e.obj_id == look_frame.obj_ids[k - 1]
        np.testing.assert_array_equal(e.T_cam_obj, look_frame.T_cam_obj[k - 1])


@pytest.mark.slow  # the shipped network on a full look frame
def test_model_provider_drops_slivers_like_the_oracle(look_frame):
    from posegrasp.grasping.model_provider import SHIPPED_MODEL, ModelProvider

    assert visible_enough(150, (480, 640), 150) and not visible_enough(149, (480, 640), 150)
    assert visible_enough(38, (240, 320), 150) and not visible_enough(37, (240, 320), 150)
    dets = ModelProvider(str(SHIPPED_MODEL)).perceive(observation(look_frame)).detections
    sizes = [int(d.mask.sum()) for d in dets]
    assert len(dets) >= 2
    cut = max(sizes)  # a threshold that drops all but the largest mask
    kept = ModelProvider(str(SHIPPED_MODEL), min_px=cut).estimate(observation(look_frame), seed=0)
    assert len(kept) == sum(n >= cut for n in sizes) < len(dets)


@pytest.mark.slow
def test_shipped_estimator_drops_segmented_table_pixels(look_frame):
    """The plane step clears the seg net's bleed onto the table before classification; the outline snapping after
    the fits may label pixels within the plane's tolerance again, but they are the blocks' own bottom edges."""
    from posegrasp import ASSETS
    from posegrasp.grasping.model_provider import SHIPPED_MODEL, load_estimator
    from posegrasp.perception.estimator import Estimator, EstimatorConfig
    from posegrasp.perception.guided import GuidedConfig
    from posegrasp.perception.plane import fit_support_plane, plane_pixels

    f = look_frame
    plane = fit_support_plane(f.depth, f.K)
    assert plane is not None and abs(plane[2]) > 0.9  # the table, seen from above
    unsnapped = GuidedConfig(radius=0)
    without = Estimator(SHIPPED_MODEL, EstimatorConfig(threads=1, support_plane=False, guided=unsnapped))
    plain = Estimator(SHIPPED_MODEL, EstimatorConfig(threads=1, models=ASSETS / "blocks", guided=unsnapped))
    tol = plain.plane_cfg.mask_tol
    bleed, cleared = (e(f.rgb, f.depth, f.K).labels > 0 for e in (without, plain))
    assert plane_pixels(plane, f.depth, f.K, bleed, tol).sum() > 20  # the seg net bleeds ...
    assert not plane_pixels(plane, f.depth, f.K, cleared, tol).any()  # ... onto the table
    est = load_estimator(str(SHIPPED_MODEL))  # the trials' estimator: as ``plain``, its outlines snapped
    on = plane_pixels(plane, f.depth, f.K, est(f.rgb, f.depth, f.K).labels > 0, tol)
    assert (on & (f.mask > 0)).sum() >= 0.8 * on.sum()


def test_noisy_oracle_is_seeded_and_has_the_requested_noise():
    rng = np.random.default_rng(0)
    K = 400
    mask = np.repeat(np.arange(1, K + 1, dtype=np.uint16), 200).reshape(400, 200)
    T = np.tile(np.eye(4), (K, 1, 1))
    T[:, :3, 3] = rng.normal(size=(K, 3))
    frame = Frame(np.zeros((0, 0, 3), np.uint8), np.zeros((0, 0), np.float32), mask, np.eye(3), np.eye(4), T,
                  np.ones(K, int))
    p = make_provider("noisy-oracle:0.01,5")
    a, b = p.estimate_truth(frame, seed=7), p.estimate_truth(frame, seed=7)
    assert all(np.array_equal(x.T_cam_obj, y.T_cam_obj) for x, y in zip(a, b))
    dt = np.array([e.T_cam_obj[:3, 3] - T[i, :3, 3] for i, e in enumerate(a)])
    assert np.std(dt) == pytest.approx(0.01, rel=0.1)
    angles = np.degrees([rotation_angle(e.T_cam_obj[:3, :3], np.eye(3)) for e in a])
    assert np.mean(angles) == pytest.approx(5 * np.sqrt(2 / np.pi), rel=0.1)  # E|N(0, 5)|
    assert isinstance(p, NoisyOracleProvider)


@pytest.mark.parametrize("spec", ["lidar", "oracle:1", "noisy-oracle:1", "noisy-oracle:-1,2"])
def test_bad_provider_specs(spec):
    with pytest.raises(UserError):
        make_provider(spec)


def test_rest_prior_levels_near_resting_estimates_only():
    cat = load_catalog()
    cube, cyl = cat["cube"], cat["cylinder"]
    R_true = axis_angle_R(np.array([0.0, 0.0, 1.0]), 0.7)  # lying on a face, turned about z
    T = make_T(axis_angle_R(np.array([1.0, 1.0, 0.0]), np.radians(5)) @ R_true, np.array([0.3, 0.0, 0.024]))
    T_rest = rest_on_table(cube, T)
    assert np.degrees(rotation_angle(T_rest[:3, :3], R_true)) < 1e-6  # levelled, the yaw kept
    assert abs(transform_points(T_rest, cube.vertices)[:, 2].min()) < 1e-9  # set onto the table
    assert np.allclose(T_rest[:2, 3], T[:2, 3])
    steep = make_T(axis_angle_R(np.array([1.0, 0.0, 0.0]), np.radians(20)) @ R_true, T[:3, 3])
    assert np.allclose(rest_on_table(cube, steep), steep)  # leaning on something: kept
    high = T.copy()
    high[2, 3] += 0.05  # on top of another block: levelled, not moved down
    assert abs(rest_on_table(cube, high)[2, 3] - high[2, 3]) < 1e-3
    assert np.allclose(rest_on_table(cube, T, RestConfig(enabled=False)), T)
    # a lying cylinder: its symmetry axis is made horizontal, whatever the spin about it
    R_lying = (axis_angle_R(np.array([1.0, 0.0, 0.0]), np.pi / 2 + np.radians(4))
               @ axis_angle_R(np.array([0.0, 0.0, 1.0]), 1.0))
    T_c = rest_on_table(cyl, make_T(R_lying, np.array([0.3, 0.0, 0.02])))
    assert abs(T_c[:3, :3][2, 2]) < 1e-9


@pytest.mark.slow  # the shipped network on a full look frame
def test_shipped_estimator_splits_a_mask_holding_two_blocks(look_frame):
    """A detection fitted to block 1 whose mask also holds block 2 (two touching blocks segmented as one) is
    split: block 1 is fitted again to its own pixels, block 2 becomes a detection of its own, typed by the
    classifier and fitted by the pose net and ICP."""
    from posegrasp.grasping.model_provider import SHIPPED_MODEL, load_estimator
    from posegrasp.perception.estimator import Detection
    from posegrasp.perception.plane import fit_support_plane

    f = look_frame
    est = load_estimator(str(SHIPPED_MODEL))
    cat = {b.obj_id: b for b in load_catalog().values()}
    a, b = f.mask == 1, f.mask == 2
    merged = Detection(int(f.obj_ids[0]), f.T_cam_obj[0], 1.0, a | b)
    _, prob = est.segment(f.rgb)
    labels = np.where(a | b, merged.obj_id, 0)
    before = labels.copy()
    dets, split_labels = est.split_merged(f.rgb, f.depth, f.K, [merged], prob, fit_support_plane(f.depth, f.K),
                                          labels)
    assert len(dets) == 2
    for k, m in ((1, a), (2, b)):
        d = next(d for d in dets if (d.mask & m).sum() > 0.8 * m.sum())
        assert (d.mask & ~m).sum() < 0.05 * m.sum()
        assert d.obj_id == f.obj_ids[k - 1]
        block = cat[d.obj_id]
        pts = surface_points(block, 500)
        est_pts, gt_pts = transform_points(d.T_cam_obj, pts), transform_points(f.T_cam_obj[k - 1], pts)
        adds = np.linalg.norm(est_pts[:, None] - gt_pts[None], axis=2).min(axis=0).mean()
        assert adds < 0.1 * block.diameter, (block.name, adds)
    assert (split_labels[b] == f.obj_ids[1]).mean() > 0.9 and np.array_equal(labels, before)  # a new class map
    whole = Detection(merged.obj_id, f.T_cam_obj[0], 1.0, a)
    dets, same = est.split_merged(f.rgb, f.depth, f.K, [whole], prob, None, labels)
    assert len(dets) == 1 and same is labels
