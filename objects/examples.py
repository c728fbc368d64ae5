"""Example parts made with trimesh (metres, closed, outward): a set of shapes that are not boxes, for the
docs' walk-through, the grasp tests and ``bench/make_parts.py``.

Sizes suit the workcell: every part fits the Jaco hand's 12-85 mm opening across some span, stands at least
20 mm tall on every resting face (the fingertips pinch at least 14 mm above the table), and fits the pick area.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import trimesh

_TF = trimesh.transformations


def _union(parts: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    return trimesh.boolean.union(parts, engine="manifold")


def _box(size: tuple[float, float, float], at: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(size, _TF.translation_matrix(at))


def u_channel(base: tuple[float, float, float] = (0.06, 0.04, 0.008), base_z: float = -0.011,
              wall: tuple[float, float, float] = (0.008, 0.04, 0.03), wall_x: float = 0.026) -> trimesh.Trimesh:
    """A U-channel, by default 60 x 40 x 30 mm: 8 mm base, two 8 mm walls, open along y (non-convex); ``base``
    and ``wall`` are box sizes (m), centred at ``base_z`` and at +-``wall_x``."""
    return _union([_box(base, (0, 0, base_z))] + [_box(wall, (x, 0, 0)) for x in (-wall_x, wall_x)])


def mug(radius: float = 0.028, inner: float = 0.024, height: float = 0.06, bottom: float = 0.006,
        handle: tuple[float, float, float, float] = (0.010, 0.017, 0.008, 0.033)) -> trimesh.Trimesh:
    """A mug, by default 56 mm across, 60 mm tall, 4 mm wall, 6 mm bottom, with a ring handle on +x (no symmetry
    but a flip); ``handle``: the ring's inner and outer radius, width and distance from the axis (m)."""
    cup = trimesh.boolean.difference([trimesh.creation.cylinder(radius, height, sections=32),
                                      trimesh.creation.cylinder(inner, height, sections=32,
                                                                transform=_TF.translation_matrix([0, 0, bottom]))],
                                     engine="manifold")
    upright = _TF.rotation_matrix(np.pi / 2, [1, 0, 0])
    r_in, r_out, width, x = handle
    ring = trimesh.creation.annulus(r_in, r_out, width, sections=16, transform=upright)
    return _union([cup, ring.apply_translation([x, 0, 0])])


def hex_nut() -> trimesh.Trimesh:
    """A hex nut: 42 mm across flats, 22 mm thick, a 20 mm bore (six-fold symmetric)."""
    body = trimesh.creation.cylinder(0.042 / np.sqrt(3.0), 0.022, sections=6)
    return trimesh.boolean.difference([body, trimesh.creation.cylinder(0.010, 0.03, sections=24)], engine="manifold")


def l_bracket() -> trimesh.Trimesh:
    """An L-bracket: a 55 x 30 x 16 mm foot and a 16 mm thick leg 50 mm tall at one end."""
    return _union([_box((0.055, 0.03, 0.016), (0, 0, -0.017)), _box((0.016, 0.03, 0.05), (-0.0195, 0, 0))])


def frustum() -> trimesh.Trimesh:
    """A cone frustum: 50 mm across at the bottom, 26 mm at the top, 45 mm tall (round)."""
    cyl = trimesh.creation.cylinder(0.025, 0.045, sections=48)
    v = cyl.vertices.copy()
    top = v[:, 2] > 0
    v[top, :2] *= 13.0 / 25.0
    return trimesh.Trimesh(v, cyl.faces)


def t_part() -> trimesh.Trimesh:
    """A T-part 60 x 22 x 55 mm: a 60 x 22 x 20 mm bar on a 22 x 22 x 35 mm stem."""
    return _union([_box((0.06, 0.022, 0.02), (0, 0, 0.0175)), _box((0.022, 0.022, 0.036), (0, 0, -0.0095))])


def flanged_shaft() -> trimesh.Trimesh:
    """A shaft 30 mm across and 45 mm long on a 56 mm flange 8 mm thick (round)."""
    return _union([trimesh.creation.cylinder(0.015, 0.045, sections=32),
                   trimesh.creation.cylinder(0.028, 0.008, sections=32,
                                             transform=_TF.translation_matrix([0, 0, -0.0185]))])


#: The example parts by name, in the order they are imported (object ids 1, 2, ...).
PARTS: dict[str, Callable[[], trimesh.Trimesh]] = {
    "mug": mug, "u_channel": u_channel, "hex_nut": hex_nut, "l_bracket": l_bracket, "frustum": frustum,
    "t_part": t_part, "flanged_shaft": flanged_shaft,
}
