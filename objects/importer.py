"""Meshes in, an object set out: each mesh read, repaired, centred, measured, its symmetries found (or taken from a
BOP ``models_info.json``), decomposed into convex pieces and checked against the workcell.

All meshes are processed before anything is written, so a bad one leaves the disk as it was.
"""

from __future__ import annotations

import os
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
from posegrasp.objects.formats.part import Part
from posegrasp.objects.mesh import UNITS, SolidMesh, centred
from posegrasp.objset import SetObject
from posegrasp.objects.rest import upright
from posegrasp.objects.symmetry import Symmetries, find_symmetries, near_warnings
from posegrasp.surface import TexturedSurface, baked

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
    return Symmetries(disc, cont)


def _looks(part: Part, solid: SolidMesh, obj_id: int) -> tuple[tuple[float, float, float, float],
                                                                 TexturedSurface | None]:
    """The object's colour and drawn surface (m, object frame): the file's texture where it has one; else, for a
    remeshed solid whose input surface covers it, that surface in the part's one colour (the detail the remesh
    rounded off stays visible); else None, the model drawn in the colour."""
    white = (1.0, 1.0, 1.0, 1.0)
    if part.surface is not None:
        return part.rgba or white, part.surface.moved(1.0, solid.offset)
    rgba = part.rgba or PALETTE[(obj_id - 1) % len(PALETTE)]
    if solid.surface is None:
        return rgba, None
    rgb = np.round(255 * np.asarray(rgba[:3])).astype(np.uint8)
    faces = np.asarray(solid.surface.faces)
    return white, baked(np.asarray(solid.surface.vertices), faces, np.tile(rgb, (len(faces), 1)))


def import_object(src: Source, obj_id: int, cfg: ImportConfig) -> SetObject:
    """One object of a set from ``src``, with id ``obj_id``."""
    step = src.path.suffix.lower() in (".step", ".stp")  # in its own declared unit
    scale = src.scale * (1.0 if step else UNITS[src.unit])
    part = read_part(src.path, scale, (cfg.step_linear_tolerance, cfg.step_angular_tolerance),
                     Path(cfg.mesh_root) if cfg.mesh_root else None)
    solid = centred(part.mesh, scale, str(src.path), "m" if step else src.unit, cfg.max_hole_fraction,
                    (cfg.min_size, cfg.max_size), cfg.remesh_cells)
    mesh = solid.mesh
    props = mass_properties(mesh, cfg.density)
    tol = cfg.sym_tol_rel * props.diameter
    given = _given_symmetries(src, solid.offset)
    sym = given if given is not None else find_symmetries(
        mesh, props.center_of_mass, props.inertia, tol, cfg.sym_points, cfg.max_fold, cfg.seed)
    up = upright(mesh, props.center_of_mass, tol)
    pieces = convex_pieces(mesh, cfg.max_pieces, cfg.coacd_threshold, cfg.seed, cfg.collision_faces,
                          cfg.coacd_iterations)
    warnings = list(part.notes) + fit_warnings(mesh, props.diameter, up.R_table_obj, cfg.fit, cfg.min_pixels) \
        + near_warnings(sym, tol, props.diameter)
    cover = union_volume(pieces) / props.volume
    if abs(cover - 1.0) > 0.10:
        warnings.append(f"its {len(pieces)} collision pieces hold {cover:.2f} times its volume (hulls over hollows); "
                        "raise max_pieces or lower coacd_threshold in --config")
    rgba, surface = _looks(part, solid, obj_id)
    return SetObject(
        obj_id=obj_id, name=src.name, vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces),
        mass=props.mass, density=cfg.density, friction=cfg.friction, rgba=rgba, surface=surface,
        collision=tuple({"type": "mesh", "vertices": p} for p in pieces),
        upright_quat=tuple(R_to_quat(up.R_table_obj).tolist()), upright_down=up.down, flat_top=up.flat_top,
        flat_bottom=up.flat_bottom, diameter=props.diameter, min_xyz=props.min_xyz,
        extents=props.extents, symmetries_discrete=tuple(sym.discrete), symmetries_continuous=tuple(sym.continuous),
        collision_volume_ratio=cover,
        source={"file": src.path.name, "unit": "m" if step else src.unit, "scale": solid.scale,
                "offset": (np.round(solid.offset, 9) + 0.0).tolist(),
                "symmetries": "found" if given is None else f"{src.models_info.name} (obj_id {src.bop_id})"},
        repairs=solid.repairs, volume_change=solid.volume_change if solid.repairs else 0.0,
        warnings=tuple(warnings))


def _import_job(job: tuple[Source, int, ImportConfig]) -> tuple[SetObject, float]:
    """One part imported (a worker's task), and the seconds it took."""
    t0 = time.perf_counter()
    obj = import_object(*job)
    return obj, time.perf_counter() - t0


def import_objects(srcs: list[Source], cfg: ImportConfig,
                   on_done: Callable[[SetObject, float], None] | None = None,
                   workers: int | str | None = 1) -> list[SetObject]:
    """Every source imported (ids 1, 2, ... in order), one task per part on ``workers`` processes
    (``posegrasp.executor``: None one per core, 1 in this process, or ``"ray"``); ``on_done(obj, seconds)`` as each
    finishes. Every part is imported on its own with seeded steps, so the set does not depend on ``workers``."""
    from posegrasp.executor import make_executor

    if isinstance(workers, int) or workers is None:
        workers = max(1, min(len(srcs), workers or os.cpu_count() or 1))
    out: list[SetObject | None] = [None] * len(srcs)
    with make_executor(workers) as ex:
        for i, (obj, seconds) in ex.imap(_import_job, [(s, i, cfg) for i, s in enumerate(srcs, start=1)]):
            out[i] = obj
            if on_done is not None:
                on_done(obj, seconds)
    return out  # type: ignore[return-value]
