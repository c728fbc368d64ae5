"""Hand-eye calibration on the real simulator and renderer: board rendering, Park-Martin, the solved mount."""

from __future__ import annotations

import numpy as np
import pytest

from posegrasp.grasping.calibration import (BoardConfig, BoardWorkcell, CalibrationConfig, calibrate, detect_board,
                                  load_hand_eye, make_board, park_martin)
from posegrasp.grasping.config import HAND_EYE_JSON
from posegrasp.errors import UserError
from posegrasp.geometry import axis_angle_R, invert, make_T, rotation_angle
from posegrasp.sim.camera import CameraRenderer
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.workcell import HAND_CAMERA, Workcell


@pytest.fixture(scope="module")
def result():
    return calibrate(WorkcellConfig(), CalibrationConfig(n_poses=10), seed=0)


def test_calibration_error_under_2mm_and_0_2deg(result):
    assert result.n_views >= 10
    assert result.trans_error_m < 2e-3, result.trans_error_m
    assert result.rot_error_deg < 0.2, result.rot_error_deg


def test_board_is_detected_where_it_lies():
    """The rendered texture is not mirrored and PnP puts the board's corner where the box lies."""
    cfg, board = WorkcellConfig(), BoardConfig()
    wc = BoardWorkcell(cfg, board)
    assert wc.drive_arm(wc.look_q)
    c = cfg.hand_camera
    cam = CameraRenderer(wc, HAND_CAMERA, c)
    T_cam_board = detect_board(cam.rgb(), cam.K, make_board(board), min_corners=20)
    cam.close()
    assert T_cam_board is not None
    T_world_board = wc.camera_pose() @ T_cam_board
    corners = [np.array([board.center[0] + sx * board.squares[0] * board.square / 2,
                         board.center[1] + sy * board.squares[1] * board.square / 2, 0.001])
               for sx in (-1, 1) for sy in (-1, 1)]
    assert min(np.linalg.norm(T_world_board[:3, 3] - p) for p in corners) < 1.5e-3
    assert abs(abs(T_world_board[2, 2]) - 1.0) < 1e-3  # the board plane is the table plane


def test_park_martin_recovers_a_known_mount():
    rng = np.random.default_rng(0)
    X = make_T(axis_angle_R(rng.normal(size=3), 0.4), rng.normal(size=3) * 0.1)
    T_base_target = make_T(axis_angle_R(rng.normal(size=3), 1.0), [0.5, 0.1, 0.0])
    grippers = [make_T(axis_angle_R(rng.normal(size=3), rng.uniform(0.2, 1.0)), rng.normal(size=3) * 0.2)
                for _ in range(6)]
    targets = [invert(G @ X) @ T_base_target for G in grippers]
    np.testing.assert_allclose(park_martin(grippers, targets), X, atol=1e-9)


def test_shipped_calibration_matches_the_true_mount():
    T = load_hand_eye(HAND_EYE_JSON)
    true = Workcell(WorkcellConfig()).T_gripper_cam()
    assert np.linalg.norm(T[:3, 3] - true[:3, 3]) < 2e-3
    assert np.degrees(rotation_angle(T[:3, :3], true[:3, :3])) < 0.2
    assert not np.allclose(T, true, atol=1e-6)  # a measured result, not a copy of the true mount


def test_missing_or_bad_calibration_file(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        load_hand_eye(tmp_path / "none.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"T_gripper_cam": [[1, 2], [3, 4]]}')
    with pytest.raises(UserError, match="4x4"):
        load_hand_eye(bad)
