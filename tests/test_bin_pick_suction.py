"""Bin picking with the suction tool (``--hand suction``) and the hybrid hand (``--hand hybrid``): the cup's planner on the estimates, its pick in the tote
(press, seal, lift with the hold model watching, carry, let go), and its place among the tasks."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from posegrasp.grasping.perception import Estimate
from posegrasp.grasping.record import Failure
from posegrasp.grasping.targets import Plan
from posegrasp.grasping.tasks.base import EpisodeFailed
from posegrasp.grasping.grasps import Grasp
from posegrasp.grasping.suction_grasps import SuctionGrasp
from posegrasp.grasping.tasks.bin_pick.pick import Cup, Hybrid, OutBox, tool_of
from posegrasp.geometry import axis_angle_R, make_T, transform_points
from posegrasp.grasping.targets import reach_q
from posegrasp.grasping.tasks.bin_pick.planner import (HeapView, _reachable, approach_end, choose_cup, choose_part,
                                                       off_the_walls, pregrasp_height)
from posegrasp.grasping.tasks.bin_pick.attempt import _look, _open_and_retreat
from posegrasp.grasping.tasks.bin_pick.metrics import grasped_for
from posegrasp.grasping.tasks.bin_pick.record import Attempt
from posegrasp.grasping.tasks.bin_pick.roll import Roll, wall_rolls
from posegrasp.grasping.tasks.bin_pick.scene import area_of, bin_workcell, outbox_of, tray_of
from posegrasp.grasping.tasks.bin_pick.tray import TrayPlace
from posegrasp.sim.tray import Slot, TrayConfig
from test_bin_pick import CAT, _alone, _cfg, _episode, _flat, _inner_bounds, _oracle_episode
from tests.helpers import refused


def _cup_pick(ep, ests, T_world_cam) -> Attempt:
    """The cup's grasp on the only part, picked and dropped into the out-box."""
    j, grasp, T_est = choose_cup(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    b, att, part = ep.cfg.bin_pick, Attempt(0), ep.wc.blocks[0].block
    Cup(ep).pick(ep, Plan(1, part, grasp, T_est, part), area_of(ep.wc, b), OutBox(ep, outbox_of(ep.wc.cfg, b)), att)
    return att


def test_a_cube_flat_in_a_corner_is_picked_by_the_cup():
    lo, hi = _inner_bounds()
    half = 0.5 * float(np.ptp(CAT["cube"].vertices[:, :2], 0).max())
    ep, ests, T_world_cam = _alone("cube", hi[:2] - half - 0.003, "suction")  # 3 mm from the +x and the +y wall
    holds, hold = [], ep.ctl.hold

    def timed(duration, until=None):
        t0 = ep.ctl.sim_time
        hold(duration, until)
        holds.append((until is not None, ep.ctl.sim_time - t0))

    ep.ctl.hold = timed
    att = _cup_pick(ep, ests, T_world_cam)
    assert att.grasped and att.failure is None
    assert ep.wc.block_poses()[0][2, 3] < 0.1  # let go over the out-box: it fell
    (waited,) = [t for until, t in holds if until]
    assert waited < 0.5 * ep.cfg.grasp.release_time, holds  # once it has left the cup, not the full release time


def test_a_studs_up_brick_gives_the_cup_nothing_to_seal_on():
    lo, hi = _inner_bounds()
    ep, ests, T_world_cam = _alone("brick_2x2", 0.5 * (lo[:2] + hi[:2]), "suction")
    with pytest.raises(EpisodeFailed) as e:
        choose_cup(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
    assert e.value.reason == Failure.NOTHING_GRASPABLE


def test_a_cup_set_off_the_estimate_does_not_seal():
    """An estimate 8 mm off along the long cuboid's narrow side puts the rim across its edge: no seal."""
    lo, hi = _inner_bounds()
    ep, ests, T_world_cam = _alone("long_cuboid", 0.5 * (lo[:2] + hi[:2]), "suction")
    T = np.linalg.inv(T_world_cam) @ ep.wc.block_poses()[0]
    narrow = int(np.argmin(np.ptp(CAT["long_cuboid"].vertices[:, :2], 0)))  # the object axis across the top face
    T_off = T.copy()
    T_off[:3, 3] += 0.008 * (T_world_cam[:3, :3].T @ ep.wc.block_poses()[0][:3, narrow])
    with pytest.raises(EpisodeFailed) as e:
        _cup_pick(ep, [Estimate(ests[0].obj_id, T_off, 1.0)], T_world_cam)
    assert e.value.reason == Failure.NO_SEAL


@pytest.mark.slow
def test_a_suction_episode_is_deterministic_and_picks_parts():
    cfg = _cfg(4, "suction")
    a, b = _oracle_episode(cfg, index=1), _oracle_episode(cfg, index=1)
    assert a.to_json() == b.to_json()
    assert a.removed >= 1 and all(t.failure != Failure.NO_SEAL for t in a.attempts if t.pose_error
                                  and t.pose_error.err < 1e-3)


def test_the_suction_tool_picks_only_in_bin_picking(capsys, tmp_path):
    out = tmp_path / "run"
    refused(capsys, ["trials", "--task", "pick-place", "--hand", "suction", "--episodes", "1", "--out", out],
            "picks only in bin picking")
    assert not out.exists()


def _hybrid_pick(name: str, xy, T: np.ndarray | None = None) -> tuple[object, Attempt]:
    """Part ``name`` alone at ``xy`` (or at pose ``T``) in the tote, chosen and picked by the hybrid hand: its grasp
    and attempt."""
    ep, ests, T_world_cam = _alone(name, xy, "hybrid", T)
    tool = Hybrid(ep)
    j, grasp, T_est = tool.choose(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0, [])
    b, att, part = ep.cfg.bin_pick, Attempt(0), ep.wc.blocks[0].block
    tool.pick(ep, Plan(1, part, grasp, T_est, part), area_of(ep.wc, b), OutBox(ep, outbox_of(ep.wc.cfg, b)), att)
    return grasp, att


def test_the_hybrid_hand_takes_a_studs_up_brick_with_its_fingers():
    lo, hi = _inner_bounds()
    grasp, att = _hybrid_pick("brick_2x2", 0.5 * (lo[:2] + hi[:2]))
    assert isinstance(grasp, Grasp) and att.grasped and att.failure is None


def test_the_hybrid_hand_takes_a_cube_flat_in_a_corner_with_its_cup():
    lo, hi = _inner_bounds()
    half = 0.5 * float(np.ptp(CAT["cube"].vertices[:, :2], 0).max())
    grasp, att = _hybrid_pick("cube", hi[:2] - half - 0.003)
    assert isinstance(grasp, SuctionGrasp) and att.grasped and att.failure is None


def test_the_hybrid_hand_closes_its_fingers_round_the_cup_to_reach_a_part_flat_in_a_corner():
    """A long cuboid 5 mm from two walls, its top 25 mm above the floor: open, the fingers would reach the walls;
    closed round the cup, they stay in its shadow, and the part is drawn off the walls before the lift."""
    lo, hi = _inner_bounds()
    half = 0.5 * np.ptp(CAT["long_cuboid"].vertices[:, :2], 0)
    grasp, att = _hybrid_pick("long_cuboid", lo[:2] + half + 0.005)
    assert isinstance(grasp, SuctionGrasp) and att.grasped and att.failure is None


def test_a_prism_pinched_on_its_slopes_by_a_wall_is_drawn_off_it_and_lifted():
    """A prism lying on a slope, its end cap 2 mm from a wall: no face for the cup, its end caps out of the fingers'
    reach, so the fingers pinch its slopes; lifted along the wall, it turned out of them."""
    lo, hi = _inner_bounds()
    part = CAT["triangular_prism"]
    T = make_T(axis_angle_R(np.array([1.0, 0.0, 0.0]), np.radians(120.0)), np.zeros(3))
    v = transform_points(T, part.vertices)
    T[:3, 3] = (hi[0] - 0.002 - v[:, 0].max(), 0.5 * (lo[1] + hi[1]), lo[2] - v[:, 2].min() + 0.002)
    grasp, att = _hybrid_pick("triangular_prism", None, T)
    assert isinstance(grasp, Grasp) and grasp.width < 0.04  # across the slopes
    assert att.grasped and att.failure is None


def _two_parts(names: list[str], poses: list[np.ndarray], min_support: float):
    """The ``names`` at ``poses`` in the tote, the hybrid hand's oracle estimates and settings with ``min_support``."""
    ep = _episode(_cfg(len(names), "hybrid"), names, poses)
    T_world_cam = ep.T_world_cam()
    ests = [Estimate(CAT[n].obj_id, np.linalg.inv(T_world_cam) @ T, 1.0) for n, T in zip(names, ep.wc.block_poses())]
    cfg = dataclasses.replace(ep.cfg, bin_pick=dataclasses.replace(ep.cfg.bin_pick, min_support=min_support))
    return ep, cfg, ests, T_world_cam


def test_a_poorly_supported_pinch_is_a_last_resort():
    """A standing cylinder (pinched on its curved side: 22 % of the pads on flat faces) and a lying long cuboid (30 %):
    with ``min_support`` between the two, the fingers go for the cuboid; a part with no other pinch is still pinched."""
    lo, hi = _inner_bounds()
    c = 0.5 * (lo + hi)
    names = ["cylinder", "long_cuboid"]
    poses = [_flat(names[0], (c[0] - 0.05, c[1])), _flat(names[1], (c[0] + 0.05, c[1]), 90.0)]
    for min_support, part in ((0.0, 0), (0.25, 1)):
        ep, cfg, ests, T_world_cam = _two_parts(names, poses, min_support)
        j, grasp, _ = choose_part(ep.wc, cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0)
        assert j == part
    every = dataclasses.replace(cfg, bin_pick=dataclasses.replace(cfg.bin_pick, min_support=0.5))
    _, grasp, _ = choose_part(ep.wc, every, ests[:1], T_world_cam, np.zeros((0, 3)), 0.0)
    assert grasp.support < 0.5  # every pinch is poorly supported: the best of them


def test_the_hybrid_hand_takes_a_lower_part_with_its_cup_before_a_poorly_supported_pinch():
    """A prism ridge up (the cup seals on none of its faces; its fingers' best pinch 20 % on flat faces) and, 10 mm
    lower, a long cuboid flat 6 mm from two walls (out of the fingers' reach): the fingers on the higher prism win
    unless their pinch counts as poorly supported, and then the cup takes the cuboid."""
    lo, hi = _inner_bounds()
    names = ["triangular_prism", "long_cuboid"]
    T = _flat(names[1], (0.0, 0.0))
    v = transform_points(T, CAT[names[1]].vertices)
    T[:2, 3] += hi[:2] - 0.006 - v[:, :2].max(0)
    poses = [_flat(names[0], (0.5 * (lo[0] + hi[0]) - 0.05, 0.5 * (lo[1] + hi[1]))), T]
    for min_support, part, kind in ((0.0, 0, Grasp), (0.25, 1, SuctionGrasp)):
        ep, cfg, ests, T_world_cam = _two_parts(names, poses, min_support)
        j, grasp, _ = Hybrid(ep).choose(ep.wc, cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0, [])
        assert j == part and type(grasp) is kind


def test_for_the_tray_the_hybrid_hand_takes_its_cup_first_unless_a_second_look_sees_the_fingers_shift():
    """The prism and cuboid above, the pinch on the prism well supported: for the out-box the fingers take the higher
    prism; for the tray the cup takes the cuboid (closing fingers shift a part, the pick's estimate would not know);
    with the tray's second look, which sees the shift, the fingers again."""
    lo, hi = _inner_bounds()
    names = ["triangular_prism", "long_cuboid"]
    T = _flat(names[1], (0.0, 0.0))
    T[:2, 3] += hi[:2] - 0.006 - transform_points(T, CAT[names[1]].vertices)[:, :2].max(0)
    poses = [_flat(names[0], (0.5 * (lo[0] + hi[0]) - 0.05, 0.5 * (lo[1] + hi[1]))), T]
    slots = (Slot(names[0], (-0.05, 0.0)), Slot(names[1], (0.05, 0.0)))
    ep = _episode(_cfg(2, "hybrid", place="tray", tray=TrayConfig(slots=slots)), names, poses)
    T_world_cam = ep.T_world_cam()
    ests = [Estimate(CAT[n].obj_id, np.linalg.inv(T_world_cam) @ T, 1.0) for n, T in zip(names, ep.wc.block_poses())]
    chosen = []
    for second_look in (False, True):
        b = ep.cfg.bin_pick
        ep.job = dataclasses.replace(ep.job, cfg=dataclasses.replace(ep.cfg, bin_pick=dataclasses.replace(
            b, min_support=0.0, tray=dataclasses.replace(b.tray, second_look=second_look))))
        b = ep.cfg.bin_pick
        for dest in (OutBox(ep, outbox_of(ep.wc.cfg, b)), TrayPlace(ep, tray_of(ep.wc.cfg, b))):
            j, grasp, _ = tool_of(ep, dest).choose(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0, [])
            chosen.append((j, type(grasp)))
    assert chosen == [(0, Grasp), (1, SuctionGrasp), (0, Grasp), (0, Grasp)]


def test_a_part_near_a_wall_is_drawn_off_it():
    cfg = _cfg(1)
    part, tote = CAT["cube"], area_of(bin_workcell(cfg, []), cfg.bin_pick).tote
    lo, hi = tote.inner_bounds()
    T = np.eye(4)
    T[:3, 3] = (lo[0] + 0.022, hi[1] - 0.020, lo[2])  # 2 mm from the -x wall, at the +y wall
    assert np.allclose(off_the_walls(part, T, tote, 0.006), (0.004, -0.006, 0.0))
    T[:2, 3] = 0.5 * (lo[:2] + hi[:2])
    assert not off_the_walls(part, T, tote, 0.006).any()


def test_a_cup_room_no_finger_opening_keeps_is_refused(tmp_path, capsys):
    cfg = tmp_path / "room.toml"
    cfg.write_text("[scene.workcell.hybrid]\ncup_room = 0.05\n")
    out = tmp_path / "run"
    refused(capsys, ["trials", "--config", cfg, "--task", "bin-pick", "--hand", "hybrid", "--episodes", "1", "--out",
                     out], "cup_room = 0.05 m")
    assert not out.exists()


def test_a_cup_grasp_is_reachable_only_where_its_approach_starts_within_reach():
    """A cup tilted 36 deg at the tote's far side: the pre-grasp above the grasp is in reach, the one above where the
    cup's approach along its axis starts (``approach_end``, 2 cm back: nearer the far side) is not, and that one is
    the pose the arm goes to, so the planner finds no reachable grasp."""
    cfg = _cfg(1, hand="hybrid")
    wc = bin_workcell(cfg, [])
    area = area_of(wc, cfg.bin_pick)
    z = np.array([-0.55, 0.2, -0.81]) / np.linalg.norm([-0.55, 0.2, -0.81])
    x = np.array([0.0, 1.0, 0.0]) - z[1] * z
    x /= np.linalg.norm(x)
    T = make_T(np.stack([x, np.cross(z, x), z], 1), (0.538, -0.023, 0.065))
    g = SuctionGrasp(T, 0.001, 0.004, 0.0, 0.01, 36.0, 0.0, 1.0, 0.095)
    assert reach_q(wc, cfg.grasp, T, pregrasp_height(cfg, area, T)) is not None
    assert np.allclose(approach_end(g)[:3, 3], T[:3, 3] - 0.02 * z)
    start = approach_end(g)
    assert reach_q(wc, cfg.grasp, start, pregrasp_height(cfg, area, start)) is None
    assert _reachable(wc, cfg, HeapView(wc, cfg, [], np.eye(4), np.zeros((0, 3))), [(1.0, 0, g)]) is None


def _lying_in_the_corner(name: str, yaw_deg: float, gap: float = 0.002) -> np.ndarray:
    """Part ``name`` on its side (its object z axis horizontal, turned ``yaw_deg`` from world x) ``gap`` (m) from the
    tote's +x and +y walls."""
    lo, hi = _inner_bounds()
    T = make_T(axis_angle_R(np.array([0.0, 0.0, 1.0]), np.radians(yaw_deg))
               @ axis_angle_R(np.array([0.0, 1.0, 0.0]), np.pi / 2), np.zeros(3))
    v = transform_points(T, CAT[name].vertices)
    T[:3, 3] = (*(hi[:2] - gap - v[:, :2].max(0)), lo[2] - v[:, 2].min() + 0.001)
    return T


def _wall_gaps(ep) -> np.ndarray:
    """The only part's distances (m) from the tote's -x, +x, -y and +y walls (the simulator's truth)."""
    lo, hi = _inner_bounds()
    v = transform_points(ep.wc.block_poses()[0], ep.wc.blocks[0].block.vertices)
    return np.concatenate([v[:, :2].min(0) - lo[:2], hi[:2] - v[:, :2].max(0)])[[0, 2, 1, 3]]


@pytest.mark.parametrize("yaw", [0.0, 90.0])
def test_the_hybrid_hand_rolls_a_cylinder_out_of_a_corner_and_then_picks_it(yaw):
    """A cylinder on its side 2 mm from two walls: no face for the cup, no room for a finger beside it, its end disc
    on a wall: the closed fingers roll it off the wall it lies along, and at the next look the fingers pick it."""
    ep, ests, T_world_cam = _alone("cylinder", None, "hybrid", _lying_in_the_corner("cylinder", yaw))
    tool, b, part = Hybrid(ep), ep.cfg.bin_pick, CAT["cylinder"]
    along = 3 if yaw == 0.0 else 1  # the wall it lies along: +y, or +x
    _, roll, T_est = tool.choose(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0, [])
    assert isinstance(roll, Roll) and len(roll.lengths) >= 3
    with pytest.raises(EpisodeFailed) as e:
        tool.pick(ep, Plan(1, part, roll, T_est, part), area_of(ep.wc, b), OutBox(ep, outbox_of(ep.wc.cfg, b)),
                  Attempt(0))
    assert e.value.reason == Failure.ROLLED
    gaps = _wall_gaps(ep)
    assert gaps[along] > 0.03 and gaps[4 - along] < 0.005  # off one wall past the fingers' reach, still on the other
    _open_and_retreat(ep, area_of(ep.wc, b), tool)  # as the attempt loop does
    _look(ep, area_of(ep.wc, b))
    ests = [Estimate(part.obj_id, np.linalg.inv(T_world_cam) @ ep.wc.block_poses()[0], 1.0)]
    _, grasp, T_est = tool.choose(ep.wc, ep.cfg, ests, T_world_cam, np.zeros((0, 3)), 0.0, [])
    att = Attempt(1)
    tool.pick(ep, Plan(1, part, grasp, T_est, part), area_of(ep.wc, b), OutBox(ep, outbox_of(ep.wc.cfg, b)), att)
    assert not isinstance(grasp, Roll) and att.grasped and att.failure is None


def test_only_a_round_part_lying_by_a_wall_is_rolled():
    """A cylinder standing, or lying in the middle of the tote, and a cuboid on its side by the wall: no roll."""
    lo, hi = _inner_bounds()
    area = area_of(bin_workcell(_cfg(1, "hybrid"), []), _cfg(1, "hybrid").bin_pick)
    middle = _flat("cylinder", 0.5 * (lo[:2] + hi[:2]))
    lying = _lying_in_the_corner("cylinder", 0.0)
    assert wall_rolls(CAT["cylinder"], lying, area, 0.005, 0.011)
    lying_middle = lying.copy()
    lying_middle[:2, 3] = 0.5 * (lo[:2] + hi[:2])
    for name, T in (("cylinder", _lying_in_the_corner("cylinder", 0.0) @ make_T(axis_angle_R(
            np.array([0.0, 1.0, 0.0]), -np.pi / 2), np.zeros(3))), ("cylinder", middle), ("cylinder", lying_middle),
                    ("long_cuboid", _lying_in_the_corner("long_cuboid", 0.0))):
        assert wall_rolls(CAT[name], T, area, 0.005, 0.011) == [], name


def test_a_roll_counts_as_an_attempt_but_not_as_a_grasp():
    target = {"instance": 1, "type": "cylinder"}
    assert not grasped_for({"target": target, "failure": Failure.ROLLED.value, "outcome": "failure"})
    assert grasped_for({"target": target, "failure": Failure.SLIP.value, "outcome": "failure"})
    assert not grasped_for({"target": None, "failure": Failure.NOTHING_GRASPABLE.value, "outcome": "failure"})
