"""Scenes of the kitting and stack tasks, drawn by seed from the scene generator's parts (``sim.scene``).

- kitting: the pick-area scene of ``sim.scene.make_scene``, but one block, of a type with an upright face,
  is set standing upright (random yaw, 1 mm above the table) and the scene is dropped again until at least one block lies
  upright with a grasp clear of its neighbours, so there is always a block the robot can kit.
- stack: the pick-area blocks, one of which fits the base and is dropped upright, plus a base block (the
  last instance) standing upright on the place pad, its centre within ``StackConfig.base_jitter`` of the
  pad's and its yaw uniform; everything is settled by simulation.

The same seed and settings give the same scene.
"""

from __future__ import annotations

import mujoco
import numpy as np

from posegrasp.catalog import PartType
from posegrasp.errors import SceneUnsettled
from posegrasp.geometry import axis_angle_R, make_T, transform_points
from posegrasp.grasping.config import GraspConfig, TrialConfig
from posegrasp.grasping.grasps import plan_grasps, surface_points
from posegrasp.grasping.tasks import PAD_TOP, believed_upright, can_stack, standing_R, standing_extent, task_types
from posegrasp.sim.scene import choose_types, drop_and_settle, drop_poses, randomise_lights, settle
from posegrasp.sim.workcell import BlockInstance, Workcell

#: Drops tried before a scene counts as one that never settles.
MAX_DROPS = 20


def _workcell(cfg: TrialConfig, types: list[PartType], rng: np.random.Generator) -> Workcell:
    """A workcell with ``types`` in random palette colours and random lights (as ``sim.scene.make_scene``)."""
    scfg = cfg.scene
    colours = [scfg.palette[i] for i in rng.integers(0, len(scfg.palette), size=len(types))]
    wc = Workcell(scfg.workcell, [BlockInstance(b, (*c, 1.0)) for b, c in zip(types, colours)])
    randomise_lights(wc, scfg, rng)
    return wc


def _standing(block: PartType, xy: np.ndarray, surface_z: float, rng: np.random.Generator) -> np.ndarray:
    """The block standing upright at a random yaw over ``xy`` (m), 1 mm above a surface at ``surface_z`` (a
    block dropped from higher up may topple: a standing cylinder did, scene after scene)."""
    yaw = axis_angle_R(np.array([0.0, 0.0, 1.0]), rng.uniform(0.0, 2.0 * np.pi))
    return make_T(yaw @ standing_R(block), (xy[0], xy[1], surface_z + 0.001 - standing_extent(block)[0]))


def _any_upright(wc: Workcell, ks: list[int], tol_deg: float, g_cfg: GraspConfig) -> bool:
    """Does any of the blocks ``ks`` (1-based) stand upright with a grasp clear of its neighbours
    (``grasps.plan_grasps`` on the true poses)? An upright block hemmed in by others leaves the task nothing
    to do: 3 of 200 kitting episodes failed as "unreachable" so."""
    poses = wc.block_poses()
    clouds = [transform_points(T, surface_points(inst.block, g_cfg.neighbour_points)) for inst, T in zip(wc.blocks, poses)]
    for k in ks:
        block = wc.blocks[k - 1].block
        if believed_upright(block, poses[k - 1], tol_deg):
            others = np.concatenate([np.zeros((0, 3))] + [c for j, c in enumerate(clouds) if j != k - 1])
            if plan_grasps(block, poses[k - 1], others, g_cfg, 0.0, yaw_stable=True):
                return True
    return False


def kitting_scene(cfg: TrialConfig, seed: int, n_blocks: int) -> Workcell:
    """A settled pick-area scene of ``n_blocks`` blocks, at least one standing upright."""
    rng = np.random.default_rng(seed)
    types = choose_types(cfg.scene, n_blocks, rng)
    u = int(rng.integers(n_blocks))
    if types[u].upright_down is None:
        able = [b for b in task_types(cfg) if b.upright_down is not None]
        types[u] = able[int(rng.integers(len(able)))]
    wc = _workcell(cfg, types, rng)
    candidates = [k for k, b in enumerate(types, start=1) if b.upright_down is not None]

    def arrange(poses: list[np.ndarray], blocks: list[PartType]) -> list[np.ndarray]:
        poses[u] = _standing(blocks[u], poses[u][:2, 3], 0.0, rng)
        return poses

    for _ in range(MAX_DROPS):
        drop_and_settle(wc, cfg.scene, types, rng, arrange=arrange)
        if _any_upright(wc, candidates, cfg.kitting.upright_tol_deg, cfg.grasp):
            return wc
    raise SceneUnsettled(f"blocks did not come to rest with one upright after {MAX_DROPS} drops")


def stack_scene(cfg: TrialConfig, seed: int, n_blocks: int) -> Workcell:
    """A settled scene: ``n_blocks`` blocks in the pick area, one of which fits the base and stands upright,
    and the base (instance ``n_blocks + 1``) standing on the place pad."""
    scfg, rng = cfg.scene, np.random.default_rng(seed)
    types = choose_types(scfg, n_blocks, rng)
    pool = task_types(cfg)
    bases = [b for b in pool if any(can_stack(b, t) for t in pool)]
    base = bases[int(rng.integers(len(bases)))]
    u = int(rng.integers(n_blocks))
    if not can_stack(base, types[u]):
        fits = [t for t in pool if can_stack(base, t)]
        types[u] = fits[int(rng.integers(len(fits)))]
    wc = _workcell(cfg, [*types, base], rng)
    pad, area = scfg.workcell.place_area, scfg.workcell.pick_area
    candidates = [k for k, b in enumerate(types, start=1) if can_stack(base, b)]
    for _ in range(MAX_DROPS):
        wc.reset()
        poses = drop_poses(scfg, types, rng)
        poses[u] = _standing(types[u], poses[u][:2, 3], 0.0, rng)
        xy = np.asarray(pad.center) + rng.uniform(-cfg.stack.base_jitter, cfg.stack.base_jitter, size=2)
        T_base = _standing(base, xy, PAD_TOP, rng)
        for k, T in enumerate([*poses, T_base], start=1):
            wc.set_block_pose(k, T)
        mujoco.mj_forward(wc.model, wc.data)
        settled = settle(wc, scfg)
        xy_now = wc.block_poses()[:, :2, 3]
        inside = np.all(np.abs(xy_now[:-1] - area.center) <= area.half_size)
        if (settled and inside and np.linalg.norm(xy_now[-1] - xy) < cfg.stack.base_move_tol
                and _any_upright(wc, candidates, cfg.stack.upright_tol_deg, cfg.grasp)):
            wc.data.qvel[:] = 0.0
            wc.data.time = 0.0
            return wc
    raise SceneUnsettled(f"blocks did not come to rest with one upright after {MAX_DROPS} drops")
