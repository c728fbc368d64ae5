"""Bin picking: its verdicts (a wall hit, two parts lifted, a part thrown out) on hand-made scenes with real physics,
each way an episode ends, determinism, a short oracle run, the comparison of two runs and bad input."""

from __future__ import annotations

import dataclasses
import io
import json

import numpy as np
import pytest
from rich.console import Console

from helpers import refused, run_cli, success_floor
from posegrasp.catalog import load_catalog
from posegrasp.config import from_dict
from posegrasp.errors import ConfigError
from posegrasp.geometry import axis_angle_R, make_T, transform_points
from posegrasp.grasping.tasks.bin_pick.attempt import _look, _same_view, empty_tote, tally
from posegrasp.grasping.tasks.bin_pick.pick import Hybrid, OutBox, _Contacts, _stopped_near, pick_and_drop
from posegrasp.grasping.tasks.bin_pick.planner import _clear_of, choose_cup, choose_part
from posegrasp.grasping.tasks.bin_pick.squeeze import OFF_WALL, Squeeze
from posegrasp.grasping.calibration import load_hand_eye
from posegrasp.grasping.compare import compare_runs, is_worse, print_comparison
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.controller import ArmController
from posegrasp.grasping.episode import Episode, EpisodeJob, _Log, run_episode, trial_physics
from posegrasp.grasping.targets import Plan
from posegrasp.grasping.grasps import plan_grasps, surface_points
from posegrasp.grasping.hand import KG3
from posegrasp.grasping.perception import Estimate
from posegrasp.grasping.record import EpisodeRecord, Failure
from posegrasp.grasping.runfolder import EPISODES, SUMMARY
from posegrasp.grasping.tasks.base import EpisodeFailed
from posegrasp.grasping.tasks import get_task, with_set
from posegrasp.grasping.tasks.bin_pick import BinPickConfig
from posegrasp.grasping.tasks.bin_pick.metrics import bin_metrics
from posegrasp.grasping.tasks.bin_pick.record import Attempt, BinPickRecord
from posegrasp.grasping.tasks.bin_pick.scene import area_of, bin_workcell, outbox_of
from posegrasp.grasping.tasks.bin_pick.shake import shake_direction
from posegrasp.grasping.trials import Display, run_trials
from posegrasp.sim.clutter import ClutterConfig, settle_heap
from posegrasp.sim.shaker import Shaker
from posegrasp.sim.tote import WALLS
from posegrasp.sim.workcell import BlockInstance

CAT = load_catalog()
Z = np.array([0.0, 0.0, 1.0])


def _cfg(parts: int = 3, hand: str = "3-finger", **bin_pick) -> TrialConfig:
    b = BinPickConfig(clutter=ClutterConfig(parts=(parts, parts)), **bin_pick)
    cfg = dataclasses.replace(TrialConfig(), task="bin-pick", bin_pick=b)
    scene = dataclasses.replace(cfg.scene, workcell=dataclasses.replace(cfg.scene.workcell, hand=hand))
    return with_set(dataclasses.replace(cfg, scene=scene))


def _episode(cfg: TrialConfig, names: list[str], poses: list[np.ndarray]) -> Episode:
    """A bin-picking episode on a hand-made scene: the parts ``names`` set at ``poses`` in the tote and settled,
    the trial's physics (``trial_physics``: as a campaign's episodes), the arm at the look."""
    wc = bin_workcell(cfg, [BlockInstance(CAT[n], (0.8, 0.3, 0.2, 1.0)) for n in names])
    for k, T in enumerate(poses, start=1):
        wc.set_block_pose(k, T)
        wc.model.body_gravcomp[wc.block_body[k - 1]] = 0.0
    assert settle_heap(wc, cfg.bin_pick.clutter)
    trial_physics(wc, cfg)
    mount = tuple(tuple(float(v) for v in r) for r in load_hand_eye(cfg.hand_eye))
    task = EpisodeJob(get_task("bin-pick"), 0, 0, "oracle", cfg, mount)
    ctl = ArmController(wc, cfg.control, wc.look_q)
    ep = Episode(task, wc, ctl, BinPickRecord(0, 0, 0, len(names), "oracle", task="bin-pick"), _Log(), 0, np.zeros(2))
    _look(ep, area_of(wc, cfg.bin_pick))
    return ep


def _flat(name: str, xy, yaw_deg: float = 0.0, z: float | None = None) -> np.ndarray:
    b = CAT[name]
    floor = 0.01  # the tote's floor
    return make_T(axis_angle_R(Z, np.radians(yaw_deg)), (xy[0], xy[1], (z or floor) - b.vertices[:, 2].min() + 0.001))


def _plan(ep: Episode, k: int, pick) -> Plan:
    """A plan for part ``k`` at its true pose: the grasp ``pick`` chooses among its grasps (no obstacles)."""
    wc, cfg = ep.wc, ep.cfg
    block, T = wc.blocks[k - 1].block, wc.block_poses()[k - 1]
    g_cfg = dataclasses.replace(cfg.grasp, min_pinch_height=0.01 + cfg.grasp.min_pinch_height,
                                finger_margin=cfg.bin_pick.finger_margin)
    grasps = plan_grasps(block, T, np.zeros((0, 3)), g_cfg, 0.0)
    return Plan(k, block, pick(grasps), T, block)


def test_a_hand_driven_into_the_wall_stops_with_a_wall_hit():
    cfg = _cfg()
    lo, hi = area_of(bin_workcell(cfg, []), cfg.bin_pick).tote.inner_bounds()
    ep = _episode(cfg, ["long_cuboid"], [_flat("long_cuboid", (0.5 * (lo[0] + hi[0]), hi[1] - 0.02))])
    # squeezing across the wall: a finger comes down on the wall
    plan = _plan(ep, 1, lambda gs: max(gs, key=lambda g: abs(g.T_world_gripper[1, 0])))
    with pytest.raises(EpisodeFailed) as e:
        pick_and_drop(ep, plan, area_of(ep.wc, cfg.bin_pick), OutBox(ep, outbox_of(ep.wc.cfg, cfg.bin_pick)),
                      Attempt(0))
    assert e.value.reason == Failure.WALL_HIT


def test_a_part_riding_on_the_target_is_two_parts_lifted():
    cfg = _cfg()
    c = area_of(bin_workcell(cfg, []), cfg.bin_pick).tote.center
    T_long = _flat("long_cuboid", c)
    T_cube = _flat("brick_2x2", (c[0] + 0.025, c[1]), z=0.01 + 0.025)  # on the long cuboid's +x end
    ep = _episode(cfg, ["long_cuboid", "brick_2x2"], [T_long, T_cube])
    assert ep.wc.block_poses()[1][2, 3] > 0.04  # still on top after settling
    plan = _plan(ep, 1, lambda gs: min(gs, key=lambda g: g.T_world_gripper[0, 3]))  # pinched at the -x end
    with pytest.raises(EpisodeFailed) as e:
        pick_and_drop(ep, plan, area_of(ep.wc, cfg.bin_pick), OutBox(ep, outbox_of(ep.wc.cfg, cfg.bin_pick)),
                      Attempt(0))
    assert e.value.reason == Failure.DOUBLE_PICK


def test_a_hand_that_contacts_turn_from_its_approach_is_a_protective_stop():
    cfg = _cfg()
    c = area_of(bin_workcell(cfg, []), cfg.bin_pick).tote.center
    ep = _episode(cfg, ["cube"], [_flat("cube", c)])
    m, wc = ep.wc.model, ep.wc
    watch = _Contacts(ep, np.array([m.geom(f"tote/{w}").id for w in WALLS]), np.array([m.geom("table").id]), 1)
    watch()  # at the look the camera points down and the hand is turned 12 deg: not a stop before the pre-grasp
    down = make_T(np.diag([1.0, -1.0, -1.0]), (c[0], c[1], 0.15))
    watch.approach = down[:3, 2]
    for tilt_deg, stops in ((cfg.bin_pick.tilt_stop_deg - 3.0, False), (cfg.bin_pick.tilt_stop_deg + 3.0, True)):
        T = down.copy()
        T[:3, :3] = axis_angle_R(np.array([1.0, 0.0, 0.0]), np.radians(tilt_deg)) @ down[:3, :3]
        q, dp, _ = wc.solve_gripper_ik(T, wc.arm_q)
        assert dp < 1e-3
        wc.reset(q)
        if stops:
            with pytest.raises(EpisodeFailed) as e:
                watch()
            assert e.value.reason == Failure.COLLISION
        else:
            watch()


def test_a_looser_part_clearance_is_tried_only_when_no_part_has_a_grasp_at_the_stricter():
    cfg = _cfg(1)
    c = area_of(bin_workcell(cfg, []), cfg.bin_pick).tote.center
    ep = _episode(cfg, ["cube"], [_flat("cube", c)])
    T_world_cam, T = ep.T_world_cam(), ep.wc.block_poses()[0]
    ests = [Estimate(CAT["cube"].obj_id, np.linalg.inv(T_world_cam) @ T, 1.0)]
    half = 0.5 * float(np.ptp(CAT["cube"].vertices[:, 0])) + 0.012  # a ring of depth points 12 mm from its faces
    u = np.arange(-half, half + 1e-9, 0.003)
    side = np.concatenate([np.stack([u, np.full_like(u, s)], 1) for s in (-half, half)]
                          + [np.stack([np.full_like(u, s), u], 1) for s in (-half, half)])
    ring = np.concatenate([np.column_stack([side + T[:2, 3], np.full(len(side), z)]) for z in (0.015, 0.025, 0.035)])
    g_cfg = dataclasses.replace(cfg.grasp, min_pinch_height=0.01 + cfg.grasp.min_pinch_height,
                                finger_margin=cfg.bin_pick.finger_margin, clearance_min=-0.05)
    tight = max(g.clearance for g in plan_grasps(CAT["cube"], T, ring, g_cfg, 0.0))
    assert tight < 0.0  # every grasp's open fingers reach into the ring
    strict = _cfg(1, part_clearance=(tight + 0.002,))
    with pytest.raises(EpisodeFailed) as e:
        choose_part(ep.wc, strict, ests, T_world_cam, ring, 0.0)
    assert e.value.reason == Failure.NOTHING_GRASPABLE
    tiers = _cfg(1, part_clearance=(tight + 0.002, tight - 0.002))
    assert choose_part(ep.wc, tiers, ests, T_world_cam, ring, 0.0)[1].clearance >= tight - 0.002


def test_the_hand_closes_where_a_neighbour_stopped_it_only_just_above_the_grasp():
    b = BinPickConfig()
    T_grasp = make_T(np.diag([1.0, -1.0, -1.0]), (0.45, 0.0, 0.03))
    at = lambda dx, dz: make_T(T_grasp[:3, :3], T_grasp[:3, 3] + (dx, 0.0, dz))  # noqa: E731
    assert _stopped_near(at(0.008, 0.014), T_grasp, b)  # on a neighbour's edge, beside and above the grasp
    assert not _stopped_near(at(0.0, b.close_slack + 0.005), T_grasp, b)  # on a neighbour's top: too high
    assert not _stopped_near(at(b.close_slack_side + 0.005, 0.0), T_grasp, b)  # shoved aside
    assert not _stopped_near(at(0.0, 0.014), T_grasp, BinPickConfig(close_slack=0.0))  # switched off


def test_the_open_fingers_keep_off_the_targets_own_surface():
    cfg = _cfg(1)
    c = np.asarray(area_of(bin_workcell(cfg, []), cfg.bin_pick).tote.center)
    R = axis_angle_R(Z, np.pi / 2) @ axis_angle_R(np.array([1.0, 0.0, 0.0]), -np.pi / 2)  # the L seen from above
    z = 0.011 - (CAT["l_block"].vertices @ R.T)[:, 2].min()
    ep = _episode(cfg, ["l_block"], [make_T(R, (c[0], c[1], z))])
    block, T = ep.wc.blocks[0].block, ep.wc.block_poses()[0]
    own = transform_points(T, surface_points(block))
    fingers = lambda g: KG3.boxes((g.width + cfg.bin_pick.finger_margin) / 2)[:-1]  # noqa: E731
    assert not all(_clear_of(g, own, fingers(g), 0.0) for g in _plan(ep, 1, list).grasp)  # some land on the L's leg
    T_world_cam = ep.T_world_cam()
    est = Estimate(block.obj_id, np.linalg.inv(T_world_cam) @ T, 1.0)
    _, grasp, _ = choose_part(ep.wc, cfg, [est], T_world_cam, np.zeros((0, 3)), 0.0)
    assert _clear_of(grasp, own, fingers(grasp), 0.0)


def _alone(name: str, xy, hand: str = "3-finger", T: np.ndarray | None = None
           ) -> tuple[Episode, list[Estimate], np.ndarray]:
    """Part ``name`` lying alone at ``xy`` (m, world) in the tote (or at pose ``T``), picked by ``hand``: the
    episode, the oracle's estimate and ``T_world_cam``."""
    ep = _episode(_cfg(1, hand), [name], [_flat(name, xy) if T is None else T])
    T_world_cam = ep.T_world_cam()
    return ep, [Estimate(CAT[name].obj_id, np.linalg.inv(T_world_cam) @ ep.wc.block_poses()[0], 1.0)], T_world_cam


def _inner_bounds() -> tuple[np.ndarray, np.ndarray]:
    cfg = _cfg(1)
    return area_of(bin_workcell(cfg, []), cfg.bin_pick).tote.inner_bounds()


def _cube_off_the_wall(gap: float, hand: str = "3-finger") -> tuple[Episode, list[Estimate], np.ndarray]:
    """A cube lying ``gap`` (m) from the tote's +y wall (``_alone``)."""
    lo, hi = _inner_bounds()
    return _alone("cube", (0.5 * (lo[0] + hi[0]), hi[1] - 0.02 - gap), hand)


def _picked(ep: Episode, grasp) -> bool:
    """Does the hand, on ``grasp``, lift the episode's only part clear of the walls?"""
    b, att, part = ep.cfg.bin_pick, Attempt(0), ep.wc.blocks[0].block
    pick_and_drop(ep, Plan(1, part, grasp, ep.wc.block_poses()[0], part), area_of(ep.wc, b),
                  OutBox(ep, outbox_of(ep.wc.cfg, b)),
                  att)
    return att.grasped


def test_a_part_22_mm_from_a_wall_is_pinched_along_it_without_touching_it():
    ep, ests, T_world_cam = _cube_off_the_wall(0.022)
    _, grasp, _ = choose_part(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    assert abs(grasp.T_world_gripper[0, 0]) > 0.99  # squeezed along the wall: the open hand's boxes reach into it
    assert _picked(ep, grasp)


def test_a_part_12_mm_from_a_wall_is_pinched_off_centre_in_the_hand_without_touching_it():
    ep, ests, T_world_cam = _cube_off_the_wall(0.012)
    centred = dataclasses.replace(ep.cfg, bin_pick=dataclasses.replace(ep.cfg.bin_pick, wall_shifts=(),
                                                                          wall_tilts_deg=()))
    with pytest.raises(EpisodeFailed) as e:
        choose_part(ep.wc, centred, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    assert e.value.reason == Failure.NOTHING_GRASPABLE  # centred in the hand, the fingers' sides reach the wall
    _, grasp, _ = choose_part(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    assert grasp.T_world_gripper[2, 2] < -0.999  # shifted, not tilted
    assert _picked(ep, grasp)


def test_a_part_in_a_corner_is_grasped_with_the_hand_tilted_away_from_the_walls():
    lo, hi = _inner_bounds()
    half = 0.5 * float(np.ptp(CAT["l_block"].vertices[:, :2], 0).max())
    ep, ests, T_world_cam = _alone("l_block", hi[:2] - half - 0.02)  # 20 mm from the +x and the +y wall
    upright = dataclasses.replace(ep.cfg, bin_pick=dataclasses.replace(ep.cfg.bin_pick, wall_tilts_deg=()))
    with pytest.raises(EpisodeFailed) as e:
        choose_part(ep.wc, upright, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    assert e.value.reason == Failure.NOTHING_GRASPABLE  # straight down, no shift keeps the fingers off both walls
    _, grasp, _ = choose_part(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    assert np.degrees(np.arccos(-grasp.T_world_gripper[2, 2])) > 5.0
    assert _picked(ep, grasp)


def test_a_part_against_a_wall_is_out_of_the_3_finger_hands_reach_and_picked_by_the_2_finger_hand():
    ep, ests, T_world_cam = _cube_off_the_wall(0.002)
    with pytest.raises(EpisodeFailed) as e:
        choose_part(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    assert e.value.reason == Failure.NOTHING_GRASPABLE  # fingers 2 and 3 reach 20-25 mm to the side: into the wall
    ep, ests, T_world_cam = _cube_off_the_wall(0.002, "2-finger")
    _, grasp, _ = choose_part(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    assert abs(grasp.T_world_gripper[0, 0]) > 0.99 and grasp.T_world_gripper[2, 2] < -0.999  # along the wall, upright
    assert _picked(ep, grasp)
    assert not ep.ctl.unexpected_contacts(1)


def test_a_brick_on_its_side_along_a_wall_is_pinched_across_its_studs_by_the_2_finger_hand():
    """A 2x2 brick on its side 12 mm from the +y wall, its studs facing along the wall: the 3-finger hand may squeeze
    it only across the wall, with no room for a finger there; the 2-finger hand pinches it across its studs."""
    lo, hi = _inner_bounds()
    R = axis_angle_R(np.array([0.0, 1.0, 0.0]), np.pi / 2)  # studs (object z) along world x
    v = CAT["brick_2x2"].vertices @ R.T
    T = make_T(R, (0.5 * (lo[0] + hi[0]) - v[:, 0].mean(), hi[1] - 0.012 - v[:, 1].max(), 0.011 - v[:, 2].min()))
    ep, ests, T_world_cam = _alone("brick_2x2", None, "3-finger", T)
    with pytest.raises(EpisodeFailed) as e:
        choose_part(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    assert e.value.reason == Failure.NOTHING_GRASPABLE
    ep, ests, T_world_cam = _alone("brick_2x2", None, "2-finger", T)
    _, grasp, _ = choose_part(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    assert abs(grasp.T_world_gripper[0, 0]) > 0.99  # the squeeze along the wall, across the studs
    assert _picked(ep, grasp)
    assert not ep.ctl.unexpected_contacts(1)


def test_a_brick_on_its_side_turned_against_a_wall_is_squeezed_along_it_by_the_hybrid_hand():
    """A 2x2 brick on its side (its sides 19 mm high: no face the 20 mm cup seals on), turned 30 deg, a corner 2 mm
    from the -x wall: no face pair along the wall and no room for a finger across it; the hybrid hand squeezes it
    along the wall, by two of its edges (the wall keeps it from turning square to the pads), and lifts it; with
    ``wall_squeeze = false``, nothing graspable."""
    lo, hi = _inner_bounds()
    R = axis_angle_R(np.array([0.0, 0.0, 1.0]), np.radians(30.0)) @ axis_angle_R(np.array([0.0, 1.0, 0.0]), -np.pi / 2)
    v = CAT["brick_2x2"].vertices @ R.T
    T = make_T(R, (lo[0] + 0.002 - v[:, 0].min(), 0.5 * (lo[1] + hi[1]) - v[:, 1].mean(), 0.011 - v[:, 2].min()))
    ep, ests, T_world_cam = _alone("brick_2x2", None, "hybrid", T)
    for choose in (choose_cup, choose_part):
        with pytest.raises(EpisodeFailed) as e:
            choose(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
        assert e.value.reason == Failure.NOTHING_GRASPABLE
    off = dataclasses.replace(ep.cfg, bin_pick=dataclasses.replace(ep.cfg.bin_pick, wall_squeeze=False))
    with pytest.raises(EpisodeFailed):
        Hybrid(ep).choose(ep.wc, off, ests, T_world_cam, np.zeros((0, 3)), 0.0, [])
    _, grasp, _ = Hybrid(ep).choose(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0, [])
    assert isinstance(grasp, Squeeze) and abs(grasp.T_world_gripper[1, 0]) > 0.99  # along the x wall
    assert _picked(ep, grasp)
    assert not ep.ctl.unexpected_contacts(1)


def test_a_squeeze_whose_hand_would_reach_the_wall_moves_off_it():
    """A 2x2 brick on its side, square to the -y wall, its studs 1 mm from it: centred on the brick, the squeeze's
    fingers would come within ``wall_clearance`` of the wall; the hybrid hand squeezes it the least of ``OFF_WALL``
    off the wall that clears it, and lifts it."""
    lo, hi = _inner_bounds()
    R = axis_angle_R(np.array([1.0, 0.0, 0.0]), np.pi / 2)  # the studs (object +z) toward -y
    v = CAT["brick_2x2"].vertices @ R.T
    T = make_T(R, (0.5 * (lo[0] + hi[0]) - v[:, 0].mean(), lo[1] + 0.001 - v[:, 1].min(), 0.011 - v[:, 2].min()))
    ep, ests, T_world_cam = _alone("brick_2x2", None, "hybrid", T)
    _, grasp, _ = Hybrid(ep).choose(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0, [])
    assert isinstance(grasp, Squeeze) and 0.0 < grasp.off_wall <= max(OFF_WALL)
    assert grasp.clearance < ep.cfg.bin_pick.wall_clearance + 0.0021  # the least move that clears: 2 mm steps
    assert _picked(ep, grasp)


def test_tally_finds_parts_in_the_out_box_and_parts_thrown_out():
    cfg = _cfg()
    wc0 = bin_workcell(cfg, [])
    area, box = area_of(wc0, cfg.bin_pick), outbox_of(wc0.cfg, cfg.bin_pick)
    lo, _ = area.tote.inner_bounds()
    poses = [_flat("cube", area.tote.center), _flat("cube", box.center),
             _flat("cube", (lo[0] - 0.08, area.tote.center[1]), z=0.0)]  # on the table beside the tote
    ep = _episode(cfg, ["cube", "cube", "cube"], poses)
    assert tally(ep.wc, area, OutBox(ep, box), [1, 2, 3]) == ([2], [3])


def _oracle_episode(cfg: TrialConfig, index: int = 0, perception: str = "oracle") -> BinPickRecord:
    mount = tuple(tuple(float(v) for v in r) for r in load_hand_eye(cfg.hand_eye))
    rec, _ = run_episode(EpisodeJob(get_task("bin-pick"), 0, index, perception, cfg, mount))
    return rec


@pytest.mark.slow
def test_an_oracle_episode_empties_the_tote_and_stops_when_it_sees_it_empty():
    rec = _oracle_episode(_cfg(3), index=3)  # a tote with no part lying against a wall (the hand cannot reach those)
    assert rec.failure is None and rec.outcome == "success" and rec.removed == 3 and rec.cleared == 1.0
    assert [a.outcome for a in rec.attempts] == ["success"] * 3
    for a in rec.attempts:
        assert a.target.class_ok and a.pose_error.err < 1e-3 and 0.0 < a.visib_fract <= 1.0 and a.removed
    assert 0.0 < rec.sim_time - sum(a.sim_time for a in rec.attempts) <= 2.0  # and the first look


def test_failures_in_a_row_and_the_attempt_limit_end_an_episode():
    far = "noisy-oracle:0.08,0"  # every estimate 8 cm off: no pick can succeed
    rec = _oracle_episode(_cfg(2, max_failures=2), perception=far)
    assert rec.failure == Failure.FAILED_IN_A_ROW and len(rec.attempts) == 2 and rec.removed == 0
    rec = _oracle_episode(_cfg(2, max_failures=100), perception=far)
    assert rec.failure == Failure.ATTEMPT_LIMIT and len(rec.attempts) == 4
    assert all(a.outcome == "failure" and a.failure for a in rec.attempts)
    back = EpisodeRecord.from_json(json.loads(json.dumps(rec.to_json())))
    assert isinstance(back, BinPickRecord) and back.to_json() == rec.to_json()


def test_an_episode_ends_when_no_part_it_sees_has_a_grasp():
    cfg = _cfg(1)
    lo, hi = area_of(bin_workcell(cfg, []), cfg.bin_pick).tote.inner_bounds()
    ep = _episode(cfg, ["cube"], [_flat("cube", (lo[0] + 0.017, lo[1] + 0.017))])  # in a corner: no finger fits
    with pytest.raises(EpisodeFailed) as e:
        empty_tote(ep)
    assert e.value.reason == Failure.NOTHING_GRASPABLE  # the second look sees the same: no second attempt
    assert [a.failure for a in ep.rec.attempts] == [Failure.NOTHING_GRASPABLE] and ep.rec.removed == 0


def test_a_part_in_a_corner_is_shaken_off_the_walls_and_picked_at_the_next_look():
    cfg = _cfg(1, shakes=1)
    area = area_of(bin_workcell(cfg, []), cfg.bin_pick)
    lo, hi = area.tote.inner_bounds()
    corner = (lo[0] + 0.017, lo[1] + 0.017)  # as above: no finger fits
    u = shake_direction(area, [make_T(np.eye(3), (*corner, 0.02))], cfg.bin_pick.shake_margin)
    assert np.allclose(u, [-np.sqrt(0.5), -np.sqrt(0.5)])  # the tote jerks into the corner: the part slides out
    assert shake_direction(area, [make_T(np.eye(3), (*(0.5 * (lo + hi))[:2], 0.02))], 0.04) is None
    ep = _episode(cfg, ["cube"], [_flat("cube", corner)])
    shaker = Shaker.of(ep.wc.model, ep.wc.data, cfg.bin_pick.shaker)
    empty_tote(ep)
    assert [a.failure for a in ep.rec.attempts] == [Failure.NOTHING_GRASPABLE, None] and ep.rec.removed == 1
    assert ep.rec.attempts[0].shaken and not ep.rec.attempts[1].shaken
    assert np.abs(ep.wc.data.qpos[shaker.qadr]).max() < 1e-4  # the tote back where it stands
    back = EpisodeRecord.from_json(json.loads(json.dumps(ep.rec.to_json())))
    assert back.to_json() == ep.rec.to_json() and "shaken" not in ep.rec.to_json()["attempts"][1]
    assert Shaker.of(bin_workcell(_cfg(1), []).model, None, cfg.bin_pick.shaker) is None  # no stage by default
    assert bin_metrics([ep.rec.to_json()])["bin_pick"]["shakes"] == 1


def test_the_tote_shaken_while_the_arm_carries_a_part_away_frees_one_in_a_corner_for_the_next_look():
    cfg = _cfg(2, "2-finger", shakes=1, shake_away=True)
    lo, _ = area_of(bin_workcell(cfg, []), cfg.bin_pick).tote.inner_bounds()
    ep = _episode(cfg, ["cube", "cube"], [_flat("cube", (0.45, 0.0)), _flat("cube", (lo[0] + 0.017, lo[1] + 0.017))])
    empty_tote(ep)  # without the shake while away: picked, nothing graspable (then shaken), picked
    assert [(a.failure, a.shaken) for a in ep.rec.attempts] == [(None, True), (None, False)] and ep.rec.removed == 2
    assert ep.wc.background is None and ep.log.sim["shake"] > 0.0


def test_an_episode_ends_when_the_arm_reaches_no_grasp_of_what_it_sees():
    cfg = _cfg(1)
    cfg = dataclasses.replace(cfg, grasp=dataclasses.replace(cfg.grasp, reach_tol=1e-12))  # no IK solution is close
    ep = _episode(cfg, ["cube"], [_flat("cube", (0.45, 0.0))])
    with pytest.raises(EpisodeFailed) as e:
        empty_tote(ep)
    assert e.value.reason == Failure.UNREACHABLE  # the same plan again would fail again: one attempt, not three
    assert [a.failure for a in ep.rec.attempts] == [Failure.UNREACHABLE] and ep.rec.removed == 0


@pytest.mark.slow
def test_a_short_oracle_campaign_is_deterministic_and_clears_most_parts(tmp_path):
    cfg = _cfg(4)
    console = Console(file=io.StringIO(), width=200)
    s = run_trials(tmp_path / "a", 2, 0, "oracle", 2, cfg, display=Display(console, False))
    printed = " ".join(console.file.getvalue().split())  # the summary's lines wrap where the numbers put them
    assert "bin picking: cleared" in printed and "episodes ended by" in printed
    assert "per target block" not in printed  # the table tasks' lines say nothing of a tote
    run_trials(tmp_path / "b", 2, 0, "oracle", 1, cfg, display=Display(progress=False))
    assert (tmp_path / "a" / EPISODES).read_bytes() == (tmp_path / "b" / EPISODES).read_bytes()
    b = json.loads((tmp_path / "a" / SUMMARY).read_text())["bin_pick"]
    assert b == s["bin_pick"] and b["parts_present"] == 8
    went = [a["outcome"] == "success" for r in map(json.loads, (tmp_path / "a" / EPISODES).read_text().splitlines())
            for a in r["attempts"] if a["target"]]
    assert (b["grasps"]["success"], b["grasps"]["n"]) == (sum(went), len(went)) == (b["picks"], len(went))
    assert "grasps (attempts that went for a part)" in printed
    # 354 of 464 oracle attempts succeeded (12 parts, bin, seed 0, 40 episodes: docs/benchmarks.md)
    floor = success_floor(354, 464, b["attempts"]["n"])
    assert b["percent_cleared"]["mean"] >= 25.0 and b["attempts"]["success"] >= floor, b
    recs = {i: json.loads(line) for i, line in enumerate((tmp_path / "a" / EPISODES).read_text().splitlines())}
    r = compare_runs(recs, recs)
    assert r["bin_pick"]["better"] == "neither" and not is_worse(r, 0.05)
    assert s["perception_latency"] == {"seconds": 0.0, "how": "provider"}  # the oracle computes nothing


def _bin_run(cleared: list[float], ok: int, tries: int = 10, sim_time: float = 60.0) -> dict[int, dict]:
    """Bin-picking records: per episode ``ok`` of ``tries`` attempts succeed, then two looks that found nothing to go
    for (no grasps)."""
    return {i: {"episode": i, "seed": 0, "task": "bin-pick", "outcome": "failure", "cleared": c, "sim_time": sim_time,
                "attempts": [{"outcome": "success" if j < ok else "failure", "target": {"type": "cube"}}
                             for j in range(tries)] + [{"outcome": "failure", "target": None}] * 2}
            for i, c in enumerate(cleared)}


def test_compare_judges_bin_picking_by_reliability_not_by_percent_cleared():
    a = _bin_run([0.8] * 8, 9)
    b = _bin_run([1.0] * 8, 5)  # clears more, by trying again: less reliable
    r = compare_runs(a, b)["bin_pick"]
    assert r["percent_cleared"]["difference"] == pytest.approx(20.0) and r["percent_cleared"]["wilcoxon_p"] < 0.05
    assert r["better"] == "A" and r["decided_by"] == "reliability" and r["attempts"]["fisher_p"] < 0.05
    lo, hi = r["grasps"]["difference_ci95"]
    assert r["grasps"]["difference"] == pytest.approx(-0.4) and lo < -0.4 < hi < 0
    assert r["attempts"]["a"]["n"] == 96 and r["attempts"]["difference"] == pytest.approx(-4 / 12)
    assert is_worse(compare_runs(a, b), 0.05) and not is_worse(compare_runs(b, a), 0.05)
    console = Console(file=io.StringIO(), width=200)
    print_comparison(compare_runs(a, b), ("a", "b"), console)
    printed = console.file.getvalue()
    assert "percent cleared (a figure, not the verdict): A 80.0 %, B 100.0 %" in printed, printed
    assert "grasp success (attempts that went for a part): A 72/80, B 40/80" in printed, printed
    assert "better: A (more reliable" in printed and "per block" not in printed, printed


def test_compare_counts_perception_latency_in_picks_per_hour_where_reliability_ties():
    a, b = _bin_run([1.0] * 8, 9), _bin_run([1.0] * 8, 9)
    r = compare_runs(a, b, (0.0, 5.0))["bin_pick"]
    assert r["attempts"]["difference"] == 0 and r["attempts"]["fisher_p"] == 1.0
    # 9 picks in 60 s of motion against 60 s + 13 looks x 5 s: 540 against 259.2 picks per hour
    assert r["picks_per_hour"]["a_mean"] == pytest.approx(540.0) and r["picks_per_hour"]["b_mean"] == pytest.approx(259.2)
    assert r["better"] == "A" and r["decided_by"] == "picks_per_hour" and r["picks_per_hour"]["wilcoxon_p"] < 0.05
    assert compare_runs(a, b)["bin_pick"]["better"] == "neither" and not is_worse(compare_runs(a, b), 0.05)


@pytest.mark.parametrize("args, message", [
    (["--task", "bin-pick", "--scene", "table"], "--scene bin or --scene pile"),
    (["--scene", "pile"], "use it with --task bin-pick"),
    (["--task", "bin-pick", "--blocks", "31"], "max_parts 30"),
    (["--task", "bin-pick", "--hand", "4-finger"], "is not a hand; choose one of: 3-finger, 2-finger"),
])
def test_bad_bin_pick_input_is_one_line_and_writes_nothing(capsys, tmp_path, args, message):
    out = tmp_path / "run"
    refused(capsys, ["trials", *args, "--episodes", "1", "--out", out, "--no-progress"], message)
    assert not out.exists()


@pytest.mark.parametrize("toml, args, message", [
    ("[grasp]\nmax_width = 0.02\n", [], "wider than the hand opens"),
    ("[bin_pick.clutter]\nmax_parts = 100\n", ["--blocks", "40"], "do not fit the tote"),
    ("[bin_pick]\npart_clearance = []\n", [], "bin_pick.part_clearance must be one or more distances"),
    ("[bin_pick]\npart_clearance = [0.0, 0.5]\n", [], "bin_pick.part_clearance = (0.0, 0.5) is out of range"),
    ("[bin_pick]\nwall_tilts_deg = [60.0]\n", [], "bin_pick.wall_tilts_deg must be angles"),
    ("[scene.workcell]\nhand = \"kg3\"\n", [], "scene.workcell.hand 'kg3' is not a hand"),
    ("[bin_pick]\noutbox_offset = [0.0, 0.2]\n", [], "puts the out-box on the bin's area (overlap 30.0 mm)"),
    ("[bin_pick]\noutbox_offset = [0.0, 0.24]\n", ["--scene", "pile"], "on the pile's area (overlap 30.0 mm)"),
    ("[bin_pick]\nshakes = 2\n", ["--scene", "pile"], "bin_pick.shakes = 2 shakes the tote, and a pile has none"),
    ("[bin_pick]\nshake_away = true\n", [], "shakes = 0 gives it none"),
    ("[bin_pick.shaker]\ncycles = 0\n", [], "cycles"),
])
def test_parts_too_big_for_the_hand_too_many_for_the_tote_or_bad_clearances_are_refused(capsys, tmp_path, toml, args,
                                                                                      message):
    (tmp_path / "c.toml").write_text(toml)
    out = tmp_path / "run"
    refused(capsys, ["trials", "--task", "bin-pick", "--config", tmp_path / "c.toml", *args, "--episodes", "1",
                     "--out", out, "--no-progress"], message)
    assert not out.exists()


def test_one_number_is_a_one_value_part_clearance_and_a_fixed_pair_still_needs_two():
    """A campaign.json written when ``part_clearance`` was one number still loads (compare, report, resume)."""
    b = from_dict(BinPickConfig, {"part_clearance": -0.015})
    assert b.part_clearance == (-0.015,)
    with pytest.raises(ConfigError, match="expected a list"):
        from_dict(ClutterConfig, {"parts": 12})



def test_a_look_from_a_camera_settled_a_little_elsewhere_sees_the_same_tote():
    """The robot stops when it sees what it found nothing graspable in: judged on the estimates in the world (the
    camera's pose as the robot knows it: forward kinematics and the calibrated mount, 0.4 mm and 0.03 deg off the
    true one), so an arm settled 0.3 mm and 0.01 rad apart does not cost another look."""
    parts = [make_T(axis_angle_R(np.array([0.3, 0.2, 1.0]), 0.4 * k), (0.45 + 0.03 * k, 0.01 * k, 0.02))
             for k in range(3)]
    mount = make_T(axis_angle_R(np.array([0.0, 1.0, 0.0]), np.radians(12.0)), (0.0, 0.065, -0.11))
    calibrated = mount @ make_T(axis_angle_R(np.array([1.0, 1.0, 0.0]), np.radians(0.03)), (0.0003, -0.0002, 0.0002))
    hands = [make_T(np.diag([1.0, -1.0, -1.0]), (0.45, 0.0, 0.5)),
             make_T(axis_angle_R(np.array([1.0, 0.0, 0.0]), 0.01) @ np.diag([1.0, -1.0, -1.0]), (0.4503, 0.0, 0.5))]
    in_camera = [[(k + 1, np.linalg.inv(G @ mount) @ T) for k, T in enumerate(parts)] for G in hands]
    seen = [[(i, G @ calibrated @ T) for i, T in view] for G, view in zip(hands, in_camera)]
    assert _same_view(seen[1], seen[0])
    assert not _same_view(in_camera[1], in_camera[0])  # the camera frame's poses differ
    moved = [(i, T.copy()) for i, T in seen[0]]
    moved[1][1][0, 3] += 0.001
    assert not _same_view(moved, seen[0]) and not _same_view(seen[0][:2], seen[0])
