"""The hybrid hand (``hand = "hybrid"``, ``sim.hybrid``) on the real simulator: the 2-finger hand plus the cup on its
slide and nothing else, the fingers pinching with the cup retracted, the cup sealing and lifting extended, the
slide's timing, determinism, settings no slide can have."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest

from posegrasp.catalog import load_catalog
from posegrasp.config import from_dict
from posegrasp.errors import ConfigError
from posegrasp.geometry import invert, make_T
from posegrasp.sim import hybrid as H
from posegrasp.sim import suction as S
from posegrasp.sim.camera import CameraRenderer
from posegrasp.sim.config import FINGERTIP_REACH, HYBRID_RETRACTED_Z, HybridConfig, WorkcellConfig, workcell_record
from posegrasp.sim.robot import robot_mjcf
from posegrasp.sim.workcell import HAND_CAMERA, BlockInstance, Workcell, finger_joints
from tests.test_suction import DOWN, DT, on_table, track

PARTS = load_catalog()
HYBRID = WorkcellConfig(hand="hybrid")
CUBE_TOP = np.array([0.45, 0.0, 0.04])  #: the cube's top centre standing on the table (``on_table``)


def cell(hand: str = "hybrid", cfg: WorkcellConfig | None = None) -> Workcell:
    return Workcell(cfg or WorkcellConfig(hand=hand), [BlockInstance(PARTS["cube"], (0.8, 0.3, 0.2, 1))])


def touching(wc: Workcell, geoms: np.ndarray, others: np.ndarray) -> bool:
    """Is any of ``geoms`` in contact with any of ``others`` now?"""
    g = wc.data.contact.geom[:wc.data.ncon]
    return bool((np.isin(g[:, 0], geoms) & np.isin(g[:, 1], others)).any()
                or (np.isin(g[:, 1], geoms) & np.isin(g[:, 0], others)).any())


def geoms(wc: Workcell, word: str) -> np.ndarray:
    return np.array([i for i in range(wc.model.ngeom) if word in wc.model.geom(i).name], dtype=int)


def start(wc: Workcell, T_world_gripper: np.ndarray) -> None:
    """The arm at rest with the gripper at ``T_world_gripper``, the cube standing under it."""
    q, *_ = wc.solve_gripper_ik(T_world_gripper, wc.look_q)
    wc.reset(q)
    on_table(wc, "cube")


def pinch(hand: str) -> tuple[Workcell, bool]:
    """Close the fingers on the cube (the pinch point at its centre), then lift it 5 cm; did the cup touch it?"""
    wc = cell(hand)
    p = CUBE_TOP - (0, 0, 0.02)
    start(wc, make_T(DOWN, p))
    cup, cube = geoms(wc, "suction"), geoms(wc, "block_1")
    cup_touched = False
    for i in range(130):
        wc.data.ctrl[wc.finger_act] = 1.0  # rad/s: closing; at the cube the actuators squeeze with their force limit
        track(wc, p + (0, 0, min(0.05, 0.001 * max(0, i - 50))), np.zeros(3))
        cup_touched |= touching(wc, cup, cube)
    return wc, cup_touched


def suction_pick(cfg: WorkcellConfig = HYBRID) -> tuple[Workcell, S.Vacuum, S.SealCheck, list]:
    """Extend the cup over the cube, press it 3 mm onto the top, switch the vacuum on, wait ``seal_time``, lift
    10 cm, checking the vacuum each period: the workcell, the vacuum, the seal and the checks."""
    wc = cell(cfg=cfg)
    start(wc, H.gripper_for_cup(make_T(DOWN, CUBE_TOP + (0, 0, 0.005)), cfg))
    base = wc.gripper_pose()[:3, 3]
    for _ in range(int(np.ceil(H.extend(wc, True) / DT))):
        track(wc, base, np.zeros(3))
    for i in range(40):
        track(wc, base - (0, 0, min(0.008, 0.0004 * i)), np.zeros(3))
    vac = S.Vacuum(wc)
    seal, checks = vac.on(1), []
    for i in range(int(np.ceil(S.seal_time(cfg.suction) / DT)) + 60):
        z = min(0.1, 0.003 * max(0, i - 5))
        track(wc, base + (0, 0, z - 0.008), np.array([0, 0, 0.15 if 0 < z < 0.1 else 0.0]))
        checks.append(vac.check())
    return wc, vac, seal, checks


# -- the model ----------------------------------------------------------------------------------------------------
def test_the_2_finger_hand_plus_the_cup_and_nothing_else():
    (root, cup), two = robot_mjcf(HYBRID), WorkcellConfig(hand="2-finger")
    assert cup == f"jaco_arm/jaco_hand/{S.CUP_BODY}"
    for kind, name in (("body", H.CARRIAGE_BODY), ("actuator", H.EXTEND_ACTUATOR), ("contact", H.BORE_EXCLUDE)):
        root.find(kind, f"jaco_hand/{name}").remove()
    assert root.to_xml_string() == robot_mjcf(two)[0].to_xml_string() and robot_mjcf(two)[1] is None
    wc = cell()
    assert finger_joints("hybrid") == finger_joints("2-finger") and wc.model.nu == 9 and wc.model.neq == 1
    np.testing.assert_allclose(wc.T_gripper_cam(), Workcell(two).T_gripper_cam(), atol=1e-12)  # one calibration
    np.testing.assert_allclose(invert(wc.gripper_pose()) @ S.cup_pose(wc), H.T_gripper_cup(HYBRID, False),
                               atol=5e-4)  # retracted at reset (sagging < 0.5 mm)
    assert H.extension(wc) < 5e-4 and HYBRID_RETRACTED_Z == H.rim_offset(HYBRID, extended=False)


def test_other_hands_ignore_the_slide_settings():
    other = HybridConfig(extension=0.1, extension_speed=0.5)
    for hand in ("3-finger", "2-finger", "suction"):
        a = robot_mjcf(WorkcellConfig(hand=hand))[0].to_xml_string()
        assert a == robot_mjcf(WorkcellConfig(hand=hand, hybrid=other))[0].to_xml_string() and "carriage" not in a
        assert "hybrid" not in workcell_record({"hand": hand, "suction": {}, "hybrid": {}})
    assert set(workcell_record({"hand": "hybrid", "suction": {}, "hybrid": {}})) == {"hand", "suction", "hybrid"}
    assert H.rim_offset(WorkcellConfig(hand="suction")) == 0.0
    with pytest.raises(ConfigError, match="needs workcell hand 'hybrid'"):
        H.rim_offset(WorkcellConfig(hand="2-finger"))


def test_retracted_cup_clears_the_fingers_at_any_angle_and_extended_leads_them():
    wc = cell()
    m, d = wc.model, wc.data
    cup, fingers = geoms(wc, "suction"), geoms(wc, "finger")
    lo, hi = m.jnt_range[m.joint(wc.finger_joint_names[0]).id]
    reach = -np.inf
    for q in np.linspace(lo, hi, 49):
        d.qpos[wc.finger_qadr] = q
        mujoco.mj_kinematics(m, d)
        assert min(mujoco.mj_geomDistance(m, d, int(c), int(f), 0.1, None) for c in cup for f in fingers) > 0.001
        T = invert(wc.gripper_pose())
        for f in fingers:
            g = m.geom(int(f))
            a, n = m.mesh_vertadr[g.dataid[0]], m.mesh_vertnum[g.dataid[0]]
            v = m.mesh_vert[a:a + n] @ d.geom_xmat[f].reshape(3, 3).T + d.geom_xpos[f]
            reach = max(reach, float((v @ T[:3, :3].T + T[:3, 3])[:, 2].max()))
    assert FINGERTIP_REACH - 2e-4 < reach <= FINGERTIP_REACH  # the constant is the meshes' farthest reach
    assert H.rim_offset(HYBRID) - reach > 0.005  # the extended rim leads the fingertips by 5 mm
    stem, body = H.hybrid_cylinders(HYBRID)
    assert body.z1 == 0.0 and stem.z1 == body.z0 and H.hybrid_boxes(HYBRID)[0] == stem.box()


def test_the_hand_camera_sees_the_cup_only_out():
    c = dataclasses.replace(HYBRID.hand_camera, width=160, height=120)
    images = []
    for hand, out in (("2-finger", False), ("hybrid", False), ("hybrid", True)):
        wc = Workcell(WorkcellConfig(hand=hand))
        wc.reset(wc.look_q)
        if out:
            wc.data.qpos[wc.model.joint(f"jaco_arm/jaco_hand/{H.EXTEND_JOINT}").qposadr[0]] = HYBRID.hybrid.extension
            mujoco.mj_forward(wc.model, wc.data)
        r = CameraRenderer(wc, HAND_CAMERA, c)
        images.append(r.rgb())
        r.close()
    np.testing.assert_array_equal(images[1], images[0])  # retracted: the 2-finger hand's pictures
    rows = np.flatnonzero((images[2] != images[1]).any(axis=(1, 2)))
    assert rows.size and rows.max() < 0.35 * c.height  # out: the cup at the top of the picture


# -- the slide ----------------------------------------------------------------------------------------------------
def test_the_slide_goes_out_and_in_in_the_time_it_says():
    wc = cell()
    start(wc, make_T(DOWN, CUBE_TOP + (0, 0, 0.15)))
    p, ext = wc.gripper_pose()[:3, 3], HYBRID.hybrid.extension
    for out, end in ((True, ext), (False, 0.0)):
        t = H.extend(wc, out)
        assert t == pytest.approx(ext / HYBRID.hybrid.extension_speed + H.EXTEND_SETTLE, abs=1e-6)
        n = int(np.ceil(t / DT))
        for i in range(n):
            track(wc, p, np.zeros(3))
            if i == n // 2:
                assert 0.25 * ext < H.extension(wc) < 0.75 * ext
        assert H.extension(wc) == pytest.approx(end, abs=5e-4)
    t = H.extend(wc, False)  # already in
    assert t == pytest.approx(H.EXTEND_SETTLE)


# -- pinch and suction ----------------------------------------------------------------------------------------------
def test_retracted_the_fingers_pinch_as_the_2_finger_hand_does():
    (two, _), (hyb, cup_touched) = pinch("2-finger"), pinch("hybrid")
    assert not cup_touched
    for wc in (two, hyb):
        assert wc.block_poses()[0, 2, 3] > 0.02 + 0.03  # lifted (slipping a little in the squeezing fingers)
        assert touching(wc, geoms(wc, "finger_tip_1"), geoms(wc, "block_1"))
        assert touching(wc, geoms(wc, "finger_tip_3"), geoms(wc, "block_1"))
    np.testing.assert_allclose(hyb.data.qpos[hyb.finger_qadr], two.data.qpos[two.finger_qadr], atol=0.01)
    (A, B) = hyb.block_poses()[0], two.block_poses()[0]
    np.testing.assert_allclose(A[:3, 3], B[:3, 3], atol=1e-3)  # the cube where the 2-finger hand holds it ...
    np.testing.assert_allclose(A[:3, :3], B[:3, :3], atol=5e-3)  # ... and turned as it holds it


def test_extended_the_cup_seals_on_a_flat_top_and_lifts_the_part():
    wc, vac, seal, checks = suction_pick()
    assert seal.sealed and seal.margin > 0
    assert all(c.held and c.part == 1 and c.load < 0.25 for c in checks) and vac.holding  # 0.21 as it lifts off
    assert wc.block_poses()[0, 2, 3] > 0.02 + 0.09  # lifted 10 cm with the cup
    assert not touching(wc, geoms(wc, "finger"), geoms(wc, "block_1"))
    assert H.extension(wc) == pytest.approx(HYBRID.hybrid.extension, abs=1e-3)
    rim = (invert(wc.gripper_pose()) @ S.cup_pose(wc))[:3, 3]  # the part's weight draws the slide and bellows out
    np.testing.assert_allclose(rim, (0, 0, H.rim_offset(HYBRID) + 0.001), atol=1e-3)


def test_same_run_same_result():
    (a, _, sa, ca), (b, _, sb, cb) = suction_pick(), suction_pick()
    assert ca == cb and sa == sb
    for field in ("qpos", "qvel", "act", "ctrl"):
        np.testing.assert_array_equal(getattr(a.data, field), getattr(b.data, field))


# -- settings -----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("hybrid, suction, names", [
    (dict(extension=0.05), {}, "extension = 0.05 m does not clear the fingertips"),
    (dict(extension=0.2), {}, "extension"),
    (dict(extension=0.1), dict(stroke=0.01), "extension = 0.1 m is more than the slide allows"),
    (dict(extension_speed=0.0), {}, "extension_speed"),
    ({}, dict(diameter=0.035), "diameter = 0.035 m is no cup between the hybrid hand's fingers"),
])
def test_settings_no_slide_can_have_are_refused(hybrid, suction, names):
    with pytest.raises(ConfigError, match=names) as e:
        from_dict(WorkcellConfig, {"hand": "hybrid", "hybrid": hybrid, "suction": suction}, where="workcell.toml")
    assert "\n" not in str(e.value)
    if "slide allows" in names or "between" in names:  # only the hybrid hand carries the slide
        assert from_dict(WorkcellConfig, {"hand": "suction", "hybrid": hybrid, "suction": suction}).hand == "suction"


def test_the_fingers_closed_round_the_cup_lie_in_their_boxes_and_clear_it():
    """In a suction pick the fingers close to ``cup_opening``: their meshes lie inside the planner's boxes
    (``finger_boxes``), within 51 mm of the axis (86 mm open), and with the cup out they keep ``cup_room`` from it,
    a millimetre narrower they would not."""
    from posegrasp.grasping.controller import finger_angle_for_opening, open_finger_points
    from posegrasp.grasping.tasks.bin_pick.planner import cup_opening, finger_boxes

    opening = cup_opening(HYBRID)
    boxes = [(np.asarray(lo) - 1e-9, np.asarray(hi) + 1e-9) for lo, hi in finger_boxes(HYBRID, opening)]
    pts = open_finger_points(HYBRID, round(1000 * opening))
    assert all(any(np.all(p >= lo) and np.all(p <= hi) for lo, hi in boxes) for p in pts)
    assert max(abs(x) for lo, hi in boxes for x in (lo[0], hi[0])) < 0.051
    wc = cell()
    m, d = wc.model, wc.data
    d.qpos[wc.model.joint(f"jaco_arm/jaco_hand/{H.EXTEND_JOINT}").qposadr[0]] = HYBRID.hybrid.extension
    cup, fingers = geoms(wc, "suction"), geoms(wc, "finger")
    gaps = []
    for o in (opening, opening - 0.001):
        d.qpos[wc.finger_qadr] = finger_angle_for_opening(HYBRID, o)
        mujoco.mj_kinematics(m, d)
        gaps.append(min(mujoco.mj_geomDistance(m, d, int(c), int(f), 0.1, None) for c in cup for f in fingers))
    assert gaps[0] >= HYBRID.hybrid.cup_room > gaps[1]
