"""The kitting and stack tasks: their verdicts on hand-placed blocks settled by real physics, short oracle
campaigns, determinism, and bad input."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from helpers import KITTING_ORACLE, STACK_ORACLE, run_cli, success_floor
from posegrasp.catalog import load_catalog
from posegrasp.errors import UserError
from posegrasp.geometry import axis_angle_R, make_T
from posegrasp.grasping.compare import compare_runs
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.tasks import check_task, get_task
from posegrasp.grasping.record import EpisodeRecord, Failure
from posegrasp.grasping.runfolder import EPISODES
from posegrasp.grasping.tasks.base import PAD_TOP
from posegrasp.grasping.tasks.kitting import KittingConfig, kitting_verdict
from posegrasp.grasping.tasks.stack import StackConfig, can_stack, stack_verdict
from posegrasp.grasping.tasks.standing import standing_extent
from posegrasp.grasping.trials import Display, run_trials
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.scene import SceneConfig, settle
from posegrasp.sim.workcell import BlockInstance, Workcell

Z = np.array([0.0, 0.0, 1.0])
PAD = np.asarray(WorkcellConfig().place_area.center)


def _settled(blocks: list, poses: list[np.ndarray]) -> np.ndarray:
    """The blocks set at ``poses`` in a real workcell and settled by simulation; their final poses."""
    wc = Workcell(WorkcellConfig(), [BlockInstance(b, (0.8, 0.2, 0.2, 1.0)) for b in blocks])
    for k, T in enumerate(poses, start=1):
        wc.set_block_pose(k, T)
    assert settle(wc, SceneConfig())
    return wc.block_poses()


def _on_pad(block, yaw_deg: float, xy=PAD, flip: bool = False, z0: float = PAD_TOP) -> np.ndarray:
    R = axis_angle_R(Z, np.radians(yaw_deg))
    if flip:
        R = R @ axis_angle_R(np.array([1.0, 0.0, 0.0]), np.pi)
    return make_T(R, (xy[0], xy[1], z0 + standing_extent(block)[1] + 0.001 if flip
                      else z0 - standing_extent(block)[0] + 0.001))


@pytest.mark.parametrize("yaw, flip, reason", [(8.0, False, None), (-8.0, False, None),
                                               (12.0, False, Failure.MISALIGNED), (188.0, False, None),
                                               (0.0, True, Failure.WRONG_FACE)])
def test_kitting_verdict_on_a_settled_brick(yaw, flip, reason):
    brick = load_catalog()["brick_2x4"]  # symmetric by 180 deg about z: 188 deg is 8 deg off
    T = _settled([brick], [_on_pad(brick, yaw, flip=flip)])[0]
    err, got = kitting_verdict(brick, T, PAD, PAD_TOP, KittingConfig())
    assert got == reason, err
    if not flip:
        assert err.tilt_deg < 1.0 and err.te < 2e-3 and abs(abs(err.yaw_deg) - abs(yaw) % 180) < 1.0


@pytest.mark.parametrize("offset, yaw, reason", [(0.0, 5.0, None), (0.015, 0.0, "misplaced"),
                                                 (0.0, 14.0, Failure.MISALIGNED)])
def test_stack_verdict_on_a_settled_pair(offset, yaw, reason):
    cat = load_catalog()
    base, top = cat["arch"], cat["cube"]  # the cube's 90-degree symmetry: yaw compared modulo it
    T_base = _on_pad(base, 30.0)
    top_z = PAD_TOP + standing_extent(base)[1] - standing_extent(base)[0]
    xy = PAD + offset * np.array([np.cos(np.radians(30.0)), np.sin(np.radians(30.0))])
    T_top = _on_pad(top, 30.0 + 90.0 + yaw, xy=xy, z0=top_z)
    final = _settled([base, top], [T_base, T_top])
    err, shift, got = stack_verdict(base, T_base, final[0], top, final[1], StackConfig())
    assert got == reason, (err, shift)
    assert shift < 0.005 and err.tilt_deg < 1.0


def test_an_upright_block_is_compared_by_its_standing_copies():
    # the L-block's symmetry flips it onto its leg: that copy is 90 deg from the kit pose, nearer than the
    # upright one turned by 114 deg, yet the block stands upright and is misaligned, not the wrong face up
    lb = load_catalog()["l_block"]
    T = make_T(axis_angle_R(Z, np.radians(114.0)), (*PAD, PAD_TOP - standing_extent(lb)[0]))
    err, reason = kitting_verdict(lb, T, PAD, PAD_TOP, KittingConfig())
    assert reason == Failure.MISALIGNED and err.tilt_deg < 1e-6 and err.yaw_deg == pytest.approx(114.0)


def test_a_moved_base_fails_stack():
    cat = load_catalog()
    base, top = cat["cube"], cat["cube"]
    T = _on_pad(base, 0.0)
    moved = T.copy()
    moved[0, 3] += 0.008
    _, shift, got = stack_verdict(base, T, moved, top, moved @ make_T(np.eye(3), (0, 0, 0.04)), StackConfig())
    assert got == "base moved" and shift == pytest.approx(0.008)


def test_a_block_may_not_overhang_its_base():
    cat = load_catalog()
    assert can_stack(cat["cube"], cat["brick_2x2"]) and can_stack(cat["arch"], cat["cylinder"])
    # 31.8 mm on a 30 mm cylinder, 40 mm on it, 31.8 mm across a 25 mm wide cuboid: they fell off
    assert not any(can_stack(cat[b], cat[t]) for b, t in [("cylinder", "brick_2x2"), ("cylinder", "cube"),
                                                          ("long_cuboid", "brick_2x2")])


def test_pick_place_records_carry_no_task_fields():
    rec = EpisodeRecord(0, 0, 1, 1, "oracle").to_json()
    assert not {"task", "final_error", "estimate_error", "base"} & set(rec)
    assert {"task", "final_error"} <= set(EpisodeRecord(0, 0, 1, 1, "oracle", task="kitting").to_json())


def test_compare_refuses_runs_of_different_tasks():
    a = {0: {"episode": 0, "seed": 0, "outcome": "success", "task": "kitting"}}
    b = {0: {"episode": 0, "seed": 0, "outcome": "success"}}
    with pytest.raises(UserError, match="kitting run and run B a pick-place run"):
        compare_runs(a, b)


def test_a_task_the_catalogue_cannot_serve_is_refused():
    cfg = TrialConfig(task="stack", scene=dataclasses.replace(TrialConfig().scene, block_types=("triangular_prism",)))
    with pytest.raises(UserError, match="stack needs an object type with a flat top"):
        check_task(cfg)


@pytest.mark.parametrize("task, measured", [("kitting", KITTING_ORACLE), ("stack", STACK_ORACLE)])
@pytest.mark.slow
def test_short_oracle_campaign_and_same_seed_same_records(tmp_path, task, measured):
    cfg = TrialConfig(task=task)
    s = run_trials(tmp_path / "a", 8, seed=0, perception="oracle", workers=2, cfg=cfg, display=Display(progress=False))
    assert s["task"] == task and s["success"] >= success_floor(*measured, 8)  # 6 and 5
    recs = [json.loads(line) for line in (tmp_path / "a" / EPISODES).read_text().splitlines()]
    for r in recs:
        assert r["task"] == task
        if r["outcome"] == "success":
            fe = r["final_error"]
            tol = cfg.kitting if task == "kitting" else cfg.stack
            assert fe["te"] <= tol.pos_tol and abs(fe["yaw_deg"]) <= tol.yaw_tol_deg and fe["tilt_deg"] < 15
            assert r["estimate_error"]["re_deg"] < 1.0  # the oracle
        if task == "stack" and r.get("base", {}).get("estimate_error"):
            assert r["base"]["estimate_error"]["te"] < 2e-3
    run_trials(tmp_path / "b", 2, seed=0, perception="oracle", workers=1, cfg=cfg, display=Display(progress=False))
    assert (tmp_path / "b" / EPISODES).read_text().splitlines() == \
        (tmp_path / "a" / EPISODES).read_text().splitlines()[:2]


@pytest.mark.slow
def test_unknown_task_and_unservable_task_are_one_line(tmp_path):
    r = run_cli("trials", "--task", "juggling", "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "juggling" in r.stderr, r.stderr
    cfg = tmp_path / "t.toml"
    cfg.write_text('[scene]\nblock_types = ["brick_2x4"]\n')
    r = run_cli("trials", "--task", "stack", "--episodes", "1", "--config", str(cfg), "--out", str(tmp_path / "o2"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "flat top" in r.stderr, r.stderr
    assert not (tmp_path / "o2" / EPISODES).exists()


def test_yaw_stable_pinch_prefers_faces_that_reach_fingers_2_and_3():
    # an L-block pinched on its 25 mm end faces (finger 1 against finger 3 alone) turned 10 deg in the hand;
    # across its 50 mm long side faces it stays put
    from posegrasp.grasping.config import GraspConfig
    from posegrasp.grasping.grasps import plan_grasps

    lb = load_catalog()["l_block"]
    T = make_T(np.eye(3), (0.4, 0.0, -standing_extent(lb)[0]))
    free = plan_grasps(lb, T, np.zeros((0, 3)), GraspConfig(), 0.0)
    stable = plan_grasps(lb, T, np.zeros((0, 3)), GraspConfig(), 0.0, yaw_stable=True)
    assert free[0].width == pytest.approx(0.05, abs=1e-3)  # pick-and-place: the end faces, no wrist turn
    assert stable[0].stable and stable[0].width == pytest.approx(0.025, abs=1e-3)
    ends = [g for g in stable if g.width > 0.04]
    assert ends and not any(g.stable for g in ends)
    assert max(g.score for g in ends) < stable[0].score
    unpenalised = max(g.score for g in plan_grasps(lb, T, np.zeros((0, 3)), GraspConfig(), 0.0) if g.width > 0.04)
    assert max(g.score for g in ends) < unpenalised - GraspConfig().score.unstable + 0.2  # the penalty, not the hand_y shift


def test_firm_hold_tasks_run_noslip_and_pick_place_does_not_by_default_and_every_task_sleeps():
    from posegrasp.grasping.episode import episode_workcell
    import mujoco

    sleep = int(mujoco.mjtEnableBit.mjENBL_SLEEP)
    for task, firm, noslip, asleep in [("pick-place", (), 0, True), ("kitting", (), 2, True), ("stack", (), 2, True),
                                       ("pick-place", ("pick-place",), 2, True), ("kitting", ("pick-place",), 0, True),
                                       ("stack", None, 2, False)]:
        cfg = TrialConfig(task=task, firm_hold_tasks=firm) if firm else TrialConfig(task=task)
        cfg = dataclasses.replace(cfg, sleep=asleep)
        m = episode_workcell(get_task(task), cfg, 3, 2).model
        assert m.opt.noslip_iterations == noslip and bool(m.opt.enableflags & sleep) == asleep, (task, firm)
    with pytest.raises(UserError, match="firm_hold_tasks names unknown task"):
        check_task(TrialConfig(firm_hold_tasks=("juggling",)))
