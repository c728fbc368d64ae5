"""The hand's own surface as world points at the workcell's current state: what a cell's self-filter takes out of a
camera's view of a part the hand holds (the robot knows its joint angles and its meshes, not the part's pose)."""

from __future__ import annotations

import mujoco
import numpy as np

from posegrasp.sim.workcell import Workcell

#: Geoms of bodies whose names start so are the hand's (fingers, palm, the hybrid hand's cup).
HAND_PREFIX = "jaco_arm/jaco_hand/"


def _primitive_points(kind: int, size: np.ndarray, spacing: float) -> np.ndarray:
    """(N, 3) points (m, geom frame) about ``spacing`` apart on a box's faces or a cylinder's side and caps; none for
    other primitives."""
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        axes = [np.linspace(-s, s, max(2, int(np.ceil(2 * s / spacing)) + 1)) for s in size[:3]]
        g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        return g[np.any(np.isclose(np.abs(g), size[:3]), axis=1)]
    if kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        r, h = size[0], size[1]
        a = np.linspace(0.0, 2 * np.pi, max(8, int(np.ceil(2 * np.pi * r / spacing))), endpoint=False)
        z = np.linspace(-h, h, max(2, int(np.ceil(2 * h / spacing)) + 1))
        side = np.stack([np.repeat(r * np.cos(a)[None], len(z), 0), np.repeat(r * np.sin(a)[None], len(z), 0),
                         np.repeat(z[:, None], len(a), 1)], -1).reshape(-1, 3)
        rings = [np.stack([q * np.cos(a), q * np.sin(a), np.full_like(a, s * h)], -1)
                 for q in np.arange(spacing, r, spacing) for s in (-1.0, 1.0)]
        return np.concatenate([side, *rings, [[0.0, 0.0, h], [0.0, 0.0, -h]]])
    return np.zeros((0, 3))


def hand_points(wc: Workcell, spacing: float = 0.003) -> np.ndarray:
    """(N, 3) world points (m) on the hand's geoms now: mesh geoms' vertices, face centres and edge midpoints, boxes'
    and cylinders' surfaces about ``spacing`` (m) apart."""
    m, d = wc.model, wc.data
    out = []
    for g in range(m.ngeom):
        if not m.body(m.geom_bodyid[g]).name.startswith(HAND_PREFIX):
            continue
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
            i = m.geom_dataid[g]
            v = m.mesh_vert[m.mesh_vertadr[i]:m.mesh_vertadr[i] + m.mesh_vertnum[i]].astype(float)
            tri = v[m.mesh_face[m.mesh_faceadr[i]:m.mesh_faceadr[i] + m.mesh_facenum[i]]]  # (F, 3, 3)
            local = np.concatenate([v, tri.mean(1), 0.5 * (tri + np.roll(tri, 1, axis=1)).reshape(-1, 3)])
        else:
            local = _primitive_points(int(m.geom_type[g]), m.geom_size[g], spacing)
        out.append(local @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g])
    return np.concatenate(out) if out else np.zeros((0, 3))
