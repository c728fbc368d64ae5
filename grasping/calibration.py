"""Hand-eye calibration of the hand camera: ChArUco views from many arm poses, Park and Martin's method.

A ChArUco board (OpenCV ``CharucoBoard``, drawn with ``generateImage``) lies flat on the table as a
textured thin box. The arm visits ``n_poses`` camera poses looking at it (IK on the camera frame, moved
through the actuators with ``Workcell.drive_arm``); each view gives ``T_world_gripper`` from the measured
joints and ``T_cam_board`` from ``solvePnP`` on the detected ChArUco corners. Park and Martin's method
solves ``T_gripper_cam``: ``cv2.calibrateHandEye(..., CALIB_HAND_EYE_PARK)`` where the installed OpenCV has
it (the pinned opencv-contrib-python-headless 5.0 wheel ships the constants but not the function), else
``park_martin`` below. The result is compared with the simulator's true mount.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import mujoco
import numpy as np
from dm_control import mjcf

from posegrasp.config import settings
from posegrasp.errors import ConfigError, DatasetError, UserError
from posegrasp.geometry import axis_angle_R, invert, look_at_R, make_T, rotation_angle
from posegrasp.inputs import read_json
from posegrasp.io import write_json
from posegrasp.outputs import mark_json
from posegrasp.sim.camera import CameraRenderer
from posegrasp.sim.config import WorkcellConfig
from posegrasp.sim.workcell import HAND_CAMERA, Workcell, build_mjcf, compile_workcell


@settings
class BoardConfig:
    """A ChArUco board lying on the table: squares (columns, rows), sizes (m), centre (x, y) (m), texture px/m."""

    squares: tuple[int, int] = (7, 5)
    square: float = 0.035
    marker: float = 0.026
    dictionary: str = "DICT_5X5_100"
    center: tuple[float, float] = (0.45, 0.0)
    px_per_m: float = 6000.0


@settings
class CalibrationConfig:
    """Viewpoints: ``n_poses`` camera poses at ``height`` (m) above the board, up to ``offset`` (m) off its
    centre and tilted up to ``tilt_deg`` toward it, with random roll; seeded."""

    n_poses: int = 12
    height: tuple[float, float] = (0.28, 0.40)
    offset: float = 0.10
    tilt_deg: float = 25.0
    min_corners: int = 12
    board: BoardConfig = dataclasses.field(default_factory=BoardConfig)


def make_board(cfg: BoardConfig) -> cv2.aruco.CharucoBoard:
    """The OpenCV board object (object frame: origin at a board corner, z out of the board, metres)."""
    try:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, cfg.dictionary))
    except AttributeError:
        raise ConfigError(f"unknown ArUco dictionary {cfg.dictionary!r}; use e.g. DICT_5X5_100") from None
    return cv2.aruco.CharucoBoard(cfg.squares, cfg.square, cfg.marker, dictionary)


def board_png(cfg: BoardConfig) -> bytes:
    """The board image (exactly the board's size, no margin) as PNG bytes."""
    w, h = (round(n * cfg.square * cfg.px_per_m) for n in cfg.squares)
    img = make_board(cfg).generateImage((w, h), marginSize=0, borderBits=1)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    if not ok:
        raise OSError("could not encode the ChArUco board image")
    return buf.tobytes()


class BoardWorkcell(Workcell):
    """The plain workcell (no blocks) with a ChArUco board on the table.

    The board is a static body added after every other body, so all ids of the plain workcell stay valid.
    ``T_world_board`` is where the board's OpenCV object frame should be (for checks; never used to solve).
    """

    def __init__(self, cfg: WorkcellConfig, board: BoardConfig):
        super().__init__(cfg)
        root = build_mjcf(cfg)
        bw, bh = (n * board.square for n in board.squares)
        tex = root.asset.add("texture", name="charuco", type="2d",
                             file=mjcf.Asset(board_png(board), ".png"))
        mat = root.asset.add("material", name="charuco", texture=tex, texrepeat=(1, 1), specular=0.0,
                             shininess=0.0, reflectance=0.0)
        body = root.worldbody.add("body", name="charuco_board", pos=(*board.center, 0.0005))
        body.add("geom", name="charuco_board", type="box", size=(bw / 2, bh / 2, 0.0005), material=mat,
                 contype=0, conaffinity=0)
        self.mjcf_root, self.model = root, compile_workcell(root, cfg, 0)
        self.data = mujoco.MjData(self.model)
        self.reset()
        self.board = board


def _view_poses(cfg: CalibrationConfig, seed: int) -> list[np.ndarray]:
    """``T_world_cam`` candidates looking at the board centre from varied positions, tilts and rolls."""
    rng = np.random.default_rng(seed)
    c = np.array([*cfg.board.center, 0.0])
    poses = []
    for _ in range(cfg.n_poses * 4):
        h = rng.uniform(*cfg.height)
        tilt = np.deg2rad(rng.uniform(0.3, 1.0) * cfg.tilt_deg)
        az = rng.uniform(0, 2 * np.pi)
        pos = c + np.array([np.cos(az) * np.tan(tilt) * h, np.sin(az) * np.tan(tilt) * h, h])
        pos[:2] += rng.uniform(-cfg.offset, cfg.offset, 2) * 0.3
        up = np.array([1.0, 0.0, 0.0])
        R = look_at_R(c - pos, up_hint=up) @ axis_angle_R([0, 0, 1], rng.uniform(-0.6, 0.6))
        poses.append(make_T(R, pos))
    return poses


def detect_board(rgb: np.ndarray, K: np.ndarray, board: cv2.aruco.CharucoBoard, min_corners: int) -> np.ndarray | None:
    """``T_cam_board`` (m) from the ChArUco corners in an RGB image, or None with too few corners."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
    if ids is None or len(ids) < min_corners:
        return None
    obj, img = board.matchImagePoints(corners, ids)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
    return make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())


@dataclass
class CalibrationResult:
    """The solved mount, its error against the true one, and what it was solved from."""

    T_gripper_cam: np.ndarray
    trans_error_m: float
    rot_error_deg: float
    n_views: int
    resolution: tuple[int, int]

    def to_json(self) -> dict:
        return {"T_gripper_cam": self.T_gripper_cam, "method": "Park and Martin (1994)",
                "n_views": self.n_views, "resolution": list(self.resolution),
                "error_vs_true_mount": {"translation_m": self.trans_error_m, "rotation_deg": self.rot_error_deg}}


def calibrate(wcfg: WorkcellConfig, cfg: CalibrationConfig, seed: int = 0) -> CalibrationResult:
    """Run the calibration in simulation; raises UserError when too few views see the board."""
    wc = BoardWorkcell(wcfg, cfg.board)
    c = wcfg.hand_camera
    cam = CameraRenderer(wc, HAND_CAMERA, c)
    board = make_board(cfg.board)
    grippers, targets = [], []
    q = wc.look_q
    for T_world_cam in _view_poses(cfg, seed):
        if len(grippers) >= cfg.n_poses:
            break
        q_goal, dp, dr = wc.solve_camera_ik(T_world_cam, q)
        if dp > 2e-3 or dr > 2e-2:
            continue
        wc.drive_arm(q_goal, tol=5e-3, timeout=4.0, gain=6.0)
        q = wc.arm_q
        T_cam_board = detect_board(cam.rgb(), cam.K, board, cfg.min_corners)
        if T_cam_board is None:
            continue
        grippers.append(wc.gripper_pose())  # forward kinematics of the measured joints
        targets.append(T_cam_board)
    cam.close()
    if len(grippers) < 3:
        raise UserError(f"only {len(grippers)} views saw the board; use more --poses or a larger board")
    T = solve_hand_eye(grippers, targets)
    true = wc.T_gripper_cam()
    return CalibrationResult(T, float(np.linalg.norm(T[:3, 3] - true[:3, 3])),
                             float(np.degrees(rotation_angle(T[:3, :3], true[:3, :3]))), len(grippers),
                             (c.width, c.height))


def park_martin(T_base_gripper: list[np.ndarray], T_cam_target: list[np.ndarray]) -> np.ndarray:
    """``T_gripper_cam`` from AX = XB over all pairs of views (Park and Martin 1994).

    A = T_bg_j^-1 T_bg_i (gripper motion), B = T_ct_j T_ct_i^-1 (camera motion). Rotation: with
    alpha = log R_A, beta = log R_B, M = sum beta alpha^T and R_X = (M^T M)^(-1/2) M^T. Translation: least
    squares of (R_A - I) t_X = R_X t_B - t_A.
    """
    A, B = [], []
    for i in range(len(T_base_gripper)):
        for j in range(i + 1, len(T_base_gripper)):
            A.append(invert(T_base_gripper[j]) @ T_base_gripper[i])
            B.append(T_cam_target[j] @ invert(T_cam_target[i]))
    M = sum(np.outer(cv2.Rodrigues(b[:3, :3])[0].ravel(), cv2.Rodrigues(a[:3, :3])[0].ravel()) for a, b in zip(A, B))
    w, V = np.linalg.eigh(M.T @ M)
    R = V @ np.diag(w ** -0.5) @ V.T @ M.T
    C = np.concatenate([a[:3, :3] - np.eye(3) for a in A])
    d = np.concatenate([R @ b[:3, 3] - a[:3, 3] for a, b in zip(A, B)])
    return make_T(R, np.linalg.lstsq(C, d, rcond=None)[0])


def solve_hand_eye(T_base_gripper: list[np.ndarray], T_cam_target: list[np.ndarray]) -> np.ndarray:
    """Park and Martin's hand-eye solution: OpenCV's ``calibrateHandEye`` if present, else ``park_martin``."""
    solver = getattr(cv2, "calibrateHandEye", None)
    if solver is None:
        return park_martin(T_base_gripper, T_cam_target)
    R, t = solver([T[:3, :3] for T in T_base_gripper], [T[:3, 3] for T in T_base_gripper],
                  [T[:3, :3] for T in T_cam_target], [T[:3, 3] for T in T_cam_target], method=cv2.CALIB_HAND_EYE_PARK)
    return make_T(R, np.ravel(t))


def save_hand_eye(path: str | Path, result: CalibrationResult) -> Path:
    """Write the calibration JSON atomically, marked as written by ``posegrasp calibrate``."""
    return write_json(path, mark_json(result.to_json(), "calibrate"))


def load_hand_eye(path: str | Path) -> np.ndarray:
    """``T_gripper_cam`` (4x4, m, OpenCV camera frame) from a calibration JSON."""
    p = Path(path)
    if not os.path.lexists(p):
        raise DatasetError(f"hand-eye calibration {p} does not exist; run `posegrasp calibrate --out {p}`")
    doc = read_json(p, DatasetError)
    try:
        T = np.asarray(doc["T_gripper_cam"], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"hand-eye calibration {p} is not a calibration JSON with a 4x4 T_gripper_cam") from None
    if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
        raise DatasetError(f"hand-eye calibration {p}: T_gripper_cam is not a 4x4 rigid transform")
    return T
