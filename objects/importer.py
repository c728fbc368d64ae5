"""Meshes in, an object set out: each mesh read, repaired, centred, measured, its symmetries found (or taken from a
BOP ``models_info.json``), decomposed into convex pieces and checked against the workcell.

All meshes are processed before anything is written, so a bad one leaves the disk as it was.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from posegrasp.errors import UserError
from posegrasp.geometry import R_to_quat
from posegrasp.objects.checks import fit_warnings
from posegrasp.objects.config import ImportConfig
from posegrasp.objects.decompose import convex_pieces, union_volume
from posegrasp.objects.mass import mass_properties
from posegrasp.objects.formats import check_file, read_part
from posegrasp.objects.mesh import UNITS, centred
from posegrasp.objects.objset import SetObject
from posegrasp.objects.rest import upright
from posegrasp.objects.symmetry import find_symmetries

#: Display colours, one per object in turn.
PALETTE = ((0.85, 0.15, 0.15, 1.0), (0.15, 0.45, 0.85, 1.0), (0.95, 0.75, 0.1, 1.0), (0.2, 0.7, 0.3, 1.0),
           (0.6, 0.3, 0.75, 1.0), (0.95, 0.5, 0.1, 1.0), (0.1, 0.7, 0.7, 1.0), (0.55, 0.35, 0.2, 1.0))
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass(frozen=True)
class Source:
    """One mesh to import: its file, unit, extra scale factor and name; ``models_info``/``bop_id`` when it comes
    from a BOP folder."""

    path: Path
    unit: str
    name: str
    models_info: Path | None = None
    bop_id: int | None = None
    scale: float = 1.0


@dataclass(frozen=True)
class Workcell:
    """What the fit checks need: the fingers' (min, max) span (m), the pick area's (x, y) size (m), and the hand
    camera's focal length (px) and distance to the pick area at the look pose (m)."""

    hand: tuple[float, float]
    pick_area: tuple[float, float]
    camera: tuple[float, float]

    @classmethod
    def default(cls) -> "Workcell":
        """From the shipped trial and workcell settings."""
        from posegrasp.grasping.config import GraspConfig
        from posegrasp.sim.config import load_workcell_config

        g, w = GraspConfig(), load_workcell_config()
        f = w.hand_camera.height / 2 / np.tan(np.deg2rad(w.hand_camera.fovy_deg) / 2)
        area = w.pick_area.half_size
        return cls(hand=(g.min_width, g.max_width), pick_area=(2 * area[0], 2 * area[1]),
                   camera=(float(f), w.look_height))


def _default_name(path: Path) -> str:
    return re.sub(r"[^a-z0-9_.-]+", "_", path.stem.lower()).strip("_.-") or "object"


def sources(paths: list[Path], units: list[str], names: list[str] | None = None,
            scales: list[float] | None = None) -> list[Source]:
    """The meshes named by ``paths`` (files, or BOP models folders / dataset roots, read in mm), with names.

    ``units``: one unit for every file, or one per path (a BOP folder's entry is ignored: BOP is in mm).
    ``scales``: factors multiplying the unit, one for every path or one per path (default 1).
    """
    bad = [u for u in units if u not in UNITS]
    if bad or len(units) not in (1, len(paths)):
        raise UserError(f"--unit {' '.join(units)}: give one of {', '.join(UNITS)} for all meshes, or one per mesh "
                        f"({len(paths)})")
    scales = scales or [1.0]
    if len(scales) not in (1, len(paths)) or not all(np.isfinite(f) and f > 0 for f in scales):
        raise UserError(f"--scale {' '.join(f'{f:g}' for f in scales)}: give one finite factor > 0 for all meshes, "
                        f"or one per mesh ({len(paths)})")
    out: list[Source] = []
    for p, unit, scale in zip(map(Path, paths), units * len(paths) if len(units) == 1 else units,
                              scales * len(paths) if len(scales) == 1 else scales):
        if not p.is_dir():
            check_file(p)
            out.append(Source(p, unit, _default_name(p), scale=scale))
            continue
        models = p / "models" if (p / "models").is_dir() else p
        plys = sorted(models.glob("obj_*.ply"))
        if not plys:
            raise UserError(f"{p}: folder holds no BOP models (models/obj_NNNNNN.ply); name mesh files or a BOP "
                            "models folder")
        info = models / "models_info.json"
        for ply in plys:
            try:
                bop_id = int(ply.stem[4:])
            except ValueError:
                raise UserError(f"{ply}: not a BOP model name (obj_NNNNNN.ply)") from None
            out.append(Source(ply, "mm", ply.stem, info if info.is_file() else None, bop_id))
    if names:
        if len(names) != len(out):
            raise UserError(f"--name gives {len(names)} names for {len(out)} meshes; give one name per mesh")
        out = [Source(s.path, s.unit, n, s.models_info, s.bop_id, s.scale) for s, n in zip(out, names)]
    for s in out:
        if not _NAME.match(s.name):
            raise UserError(f"object name {s.name!r} is not allowed; use letters, digits, '_', '.', '-'")
    seen = [s.name for s in out]
    dup = sorted({n for n in seen if seen.count(n) > 1})
    if dup:
        raise UserError(f"object names {dup} repeat; give each mesh its own name with --name")
    return out


Symmetries = tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]


def _given_symmetries(src: Source, offset: np.ndarray) -> Symmetries | None:
    """The BOP models_info symmetries of ``src``, moved into the centred frame (``x_obj = x_model + offset``)."""
    if src.models_info is None:
        return None
    from posegrasp.bop import load_models_info

    info = load_models_info(src.models_info).get(src.bop_id)
    if info is None:
        return None
    S = np.eye(4)
    S[:3, 3] = offset
    disc = []
    for T in info.symmetries_discrete:
        U, _, Vt = np.linalg.svd(T[:3, :3])  # undo the rounding in the file: the nearest rotation
        T = T.copy()
        T[:3, :3] = U @ Vt
        disc.append(S @ T @ np.linalg.inv(S))
    cont = [(a / np.linalg.norm(a), c + offset) for a, c in info.symmetries_continuous]
    return disc, cont


def import_object(src: Source, obj_id: int, cfg: ImportConfig, cell: Workcell) -> SetObject:
    """One object of a set from ``src``, with id ``obj_id``."""
    step = src.path.suffix.lower() in (".step", ".stp")  # in its own declared unit
    scale = src.scale * (1.0 if step else UNITS[src.unit])
    part = read_part(src.path, scale, (cfg.step_linear_tolerance, cfg.step_angular_tolerance))
    solid = centred(part.mesh, scale, str(src.path), "m" if step else src.unit, cfg.max_hole_fraction,
                    (cfg.min_size, cfg.max_size), cfg.remesh_cells)
    mesh = solid.mesh
    props = mass_properties(mesh, cfg.density)
    tol = cfg.sym_tol_rel * props.diameter
    given = _given_symmetries(src, solid.offset)
    disc, cont = given if given is not None else find_symmetries(
        mesh, props.center_of_mass, props.inertia, tol, cfg.sym_points, cfg.max_fold, cfg.seed)
    up = upright(mesh, props.center_of_mass, tol)
    pieces = convex_pieces(mesh, cfg.max_pieces, cfg.coacd_threshold, cfg.seed)
    warnings = list(part.notes) + fit_warnings(mesh, props.diameter, up.R_table_obj, cell.hand, cell.pick_area,
                                               cell.camera, cfg.min_pixels)
    cover = union_volume(pieces) / props.volume
    if abs(cover - 1.0) > 0.10:
        warnings.append(f"its {len(pieces)} collision pieces hold {cover:.2f} times its volume (hulls over hollows); "
                        "raise max_pieces or lower coacd_threshold in --config")
    return SetObject(
        obj_id=obj_id, name=src.name, vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces),
        mass=props.mass, density=cfg.density, friction=cfg.friction,
        rgba=part.rgba or (PALETTE[(obj_id - 1) % len(PALETTE)] if part.surface is None else (1.0, 1.0, 1.0, 1.0)),
        surface=None if part.surface is None else part.surface.moved(1.0, solid.offset),
        collision=tuple({"type": "mesh", "vertices": p} for p in pieces),
        upright_quat=tuple(R_to_quat(up.R_table_obj).tolist()), upright_down=up.down, flat_top=up.flat_top,
        flat_bottom=up.flat_bottom, diameter=props.diameter, min_xyz=props.min_xyz,
        extents=props.extents, symmetries_discrete=tuple(disc), symmetries_continuous=tuple(cont),
        collision_volume_ratio=cover,
        source={"file": src.path.name, "unit": "m" if step else src.unit, "scale": solid.scale,
                "offset": (np.round(solid.offset, 9) + 0.0).tolist(),
                "symmetries": "found" if given is None else f"{src.models_info.name} (obj_id {src.bop_id})"},
        repairs=solid.repairs, volume_change=solid.volume_change if solid.repairs else 0.0,
        warnings=tuple(warnings))


def import_objects(srcs: list[Source], cfg: ImportConfig, cell: Workcell,
                   on_done: Callable[[SetObject, float], None] | None = None) -> list[SetObject]:
    """Every source imported in order (ids 1, 2, ...); ``on_done(obj, seconds)`` after each."""
    out = []
    for i, src in enumerate(srcs, start=1):
        t0 = time.perf_counter()
        out.append(import_object(src, i, cfg, cell))
        if on_done is not None:
            on_done(out[-1], time.perf_counter() - t0)
    return out
