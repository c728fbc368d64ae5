"""Validating a BOP dataset (``posegrasp dataset check``): schema, units, ids, rotations, masks against
``scene_gt_info.json`` (bop_toolkit's rules: boxes [x, y, w, h] with w = x_max - x_min, empty ones all -1,
``px_count_all`` and ``bbox_obj`` over the whole silhouette, also beyond the image), depth against the models at
their ground-truth poses, ``models_eval/`` and the test split's ``test_targets_bop19.json``. Works on any BOP
dataset, not only generated ones.

Every problem is a line naming the file (relative to the dataset root) and what is wrong with it.
"""

from __future__ import annotations

import functools
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.config import settings
from posegrasp.errors import DatasetError
from posegrasp.executor import make_executor
from posegrasp.geometry import invert

HIST_BINS = np.linspace(0.0, 1.0, 11)
#: Datasets of this many scenes or more are checked by a pool of processes (``check_dataset``'s ``workers``).
PARALLEL_FROM_SCENES = 8
#: A translation (mm) shorter than this is taken for one in metres.
METRES_BELOW_MM = 10.0


#: Pixels in from a visible mask's outline where its depth is compared with the model (``depth_on_model``).
INNER_PX = 2


@dataclass
class CheckReport:
    """What ``check_dataset`` found: problems (first ones first) and summary counts."""

    problems: list[str] = field(default_factory=list)
    splits: list[str] = field(default_factory=list)
    scenes: int = 0
    images: int = 0
    instances: Counter = field(default_factory=Counter)
    visible: Counter = field(default_factory=Counter)
    visib_fracts: list[float] = field(default_factory=list)
    depth_errors_mm: list[float] = field(default_factory=list)
    stopped_early: bool = False
    #: Scenes checked, or stopped in, so far (the scenes of ``scenes`` and those whose files did not read).
    scenes_done: int = 0

    def merge(self, other: "CheckReport", max_problems: int) -> None:
        """Add ``other``'s findings (of the scenes after this report's), up to ``max_problems`` problems in all."""
        self.problems.extend(other.problems[:max(max_problems - len(self.problems), 0)])
        self.scenes += other.scenes
        self.images += other.images
        self.instances.update(other.instances)
        self.visible.update(other.visible)
        self.visib_fracts.extend(other.visib_fracts)
        self.depth_errors_mm.extend(other.depth_errors_mm)
        self.scenes_done += other.scenes_done

    @property
    def ok(self) -> bool:
        return not self.problems


def rotation_problem(R: np.ndarray, tol: float = 1e-3) -> str | None:
    """Why a 3x3 matrix is not a rotation (orthonormal, det +1), or None."""
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > tol:
        return f"is not orthonormal (max |R R^T - I| = {err:.2g})"
    if np.linalg.det(R) < 0:
        return "has determinant -1 (a reflection)"
    return None


def find_splits(root: Path) -> list[str]:
    """Folders of ``root`` holding scene folders (6-digit names), models folders excluded."""
    return sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith("models")
                  and any(c.is_dir() and c.name.isdigit() for c in p.iterdir()))


@settings
class CheckOptions:
    """What ``check_dataset`` checks, and how far it goes."""

    #: Largest median distance (mm) of an instance's depth from its model at the ground-truth pose.
    depth_tol_mm: float = 5.0
    #: Images checked per scene (None: all).
    max_images: int | None = None
    #: The search stops after this many problems.
    max_problems: int = 200
    #: Compare each instance's depth with its model at the ground-truth pose (within ``depth_tol_mm``; the slow part).
    model_depth: bool = True
    #: Check ``models_eval/`` and the test split's BOP19 targets.
    scoring: bool = True
    #: Require them and ``models_eval/models_info.json`` (as other BOP tools do; ``eval`` falls back to ``models/``
    #: and the ground truth without them).
    complete: bool = True


class _Checker:
    """Accumulates problems over one dataset, read through ``posegrasp.bop`` (every file checked by
    ``bop.schema`` and ``bop.images``), as ``opts`` say."""

    def __init__(self, root: Path, opts: CheckOptions):
        self.root, self.opts = root, opts
        self.report = CheckReport()
        self.meshes: dict[int, Any] = {}
        self.infos: dict[int, bop.ObjectInfo] = {}

    def add(self, msg: str) -> None:
        self.report.problems.append(msg.replace(f"{self.root}/", "", 1))

    def read(self, f: Callable[..., Any], *args: Any) -> Any:
        """``f(*args)``, or None with its DatasetError recorded."""
        try:
            return f(*args)
        except DatasetError as e:
            self.add(str(e))
            return None

    @property
    def full(self) -> bool:
        return len(self.report.problems) >= self.opts.max_problems

    def rel(self, p: Path) -> str:
        return str(p.relative_to(self.root))

    # -- dataset level --------------------------------------------------------------------------------
    def models(self) -> None:
        """``models_info.json``, each model against it and, with ``scoring``, ``models_eval/``."""
        infos = self.read(bop.load_models_info, self.root)
        if infos is None:
            return
        where = self.rel(bop.models_info_path(self.root))
        for oid, info in infos.items():
            for s, D in enumerate(info.symmetries_discrete):
                if (why := rotation_problem(D[:3, :3])) is not None:
                    self.add(f"{where}: obj {oid} symmetries_discrete[{s}] rotation {why}")
            self.infos[oid] = info
            self.model(oid, info)
            if self.opts.scoring:
                self.eval_model(oid)
        if self.opts.scoring and self.opts.complete:
            self.eval_models_info(infos)

    def model(self, obj_id: int, info: bop.ObjectInfo) -> None:
        """The PLY loads and its extent (mm) matches ``models_info.json``."""
        p = bop.model_path(self.root, obj_id)
        mesh = self.read(bop_models.load_model, p)  # metres, assuming the file is in mm
        if mesh is None:
            return
        size_mm = np.ptp(np.asarray(mesh.vertices), axis=0) * 1000.0
        want = info.size_xyz * 1000.0
        ratio = float(np.max(want) / max(np.max(size_mm), 1e-12))
        if not 0.98 < ratio < 1.02:
            units = " (the model looks like metres)" if 500 < ratio < 2000 else ""
            self.add(f"{self.rel(p)}: extent {np.round(size_mm, 2).tolist()} mm does not match models_info.json "
                     f"size {np.round(want, 3).tolist()} mm{units}")
            return
        self.meshes[obj_id] = mesh

    def eval_model(self, obj_id: int) -> None:
        """``models_eval/`` (the BOP metrics' points and renderings) holds the model, with its extent and at least
        its vertices."""
        p = bop.models_eval_dir(self.root) / f"obj_{obj_id:06d}.ply"
        if not os.path.lexists(p):
            if self.opts.complete:
                self.add(f"{self.rel(p)}: missing; BOP's metrics use models_eval/ (rerun the datagen command to add "
                         "it)")
            return
        dense = self.read(bop_models.load_model, p)
        mesh = self.meshes.get(obj_id)
        if dense is None or mesh is None:
            return
        ratio = float(np.ptp(dense.vertices, axis=0).max() / np.ptp(mesh.vertices, axis=0).max())
        if not np.allclose(np.ptp(dense.vertices, axis=0), np.ptp(mesh.vertices, axis=0), rtol=0.02, atol=1e-4):
            units = " (it looks like metres; BOP models are in millimetres)" if 5e-4 < ratio < 2e-3 else ""
            self.add(f"{self.rel(p)}: extent differs from models/obj_{obj_id:06d}.ply{units}")
        elif len(dense.vertices) < len(mesh.vertices):
            self.add(f"{self.rel(p)}: {len(dense.vertices)} vertices, fewer than the model's {len(mesh.vertices)}")

    def eval_models_info(self, infos: dict[int, bop.ObjectInfo]) -> None:
        """``models_eval/models_info.json`` (bop_toolkit's ``eval_bop19_pose.py`` reads it): the objects and
        diameters of ``models/models_info.json``."""
        p = bop.models_eval_dir(self.root) / "models_info.json"
        if not os.path.lexists(p):
            self.add(f"{self.rel(p)}: missing; bop_toolkit's eval_bop19_pose.py reads it (rerun the datagen "
                     "command to add it)")
            return
        dense = self.read(bop.load_models_info, p)
        if dense is None:
            return
        if sorted(dense) != sorted(infos):
            self.add(f"{self.rel(p)}: objects {sorted(dense)} differ from models/models_info.json's {sorted(infos)}")
            return
        for oid, info in infos.items():
            if not np.isclose(dense[oid].diameter, info.diameter, rtol=0.02):
                self.add(f"{self.rel(p)}: obj {oid} 'diameter': expected {info.diameter * 1000:g} mm as in "
                         f"models/models_info.json, got {dense[oid].diameter * 1000:g}")

    def targets(self, split: str) -> None:
        """``test_targets_bop19.json`` (test split): entries naming images of the split and objects of the
        models, with inst_count = the object's instances there at least 10 % visible (BOP 2019)."""
        path = bop.targets_path(self.root)
        if not os.path.lexists(path):
            if self.opts.complete:
                self.add(f"{self.rel(path)}: missing; BOP 2019 scores the test split on it (rerun the datagen "
                         "command to add it)")
            return
        rows = self.read(bop.load_test_targets, self.root)
        scenes: dict[int, dict[int, bop.ImageRecord]] = {}
        for i, t in enumerate(rows or []):
            if self.full:
                return
            where = f"{self.rel(path)}: entry {i} (scene {t.scene_id} im {t.im_id} obj {t.obj_id})"
            if t.scene_id not in scenes:
                scenes[t.scene_id] = self.scene_records(split, t.scene_id)
            rec = scenes[t.scene_id].get(t.im_id)
            if rec is None:
                self.add(f"{where}: expected an image of {split}/")
                continue
            if t.obj_id not in self.infos:
                self.add(f"{where}: expected an obj_id of models/models_info.json")
                continue
            n = sum(g.obj_id == t.obj_id and g.info is not None and g.info.visib_fract >= bop.MIN_TARGET_VISIB
                    for g in rec.instances)
            if t.inst_count != n:
                self.add(f"{where}: 'inst_count': expected {n}, its instances with visib_fract >= "
                         f"{bop.MIN_TARGET_VISIB}, got {t.inst_count}")

    def scene_records(self, split: str, scene_id: int) -> dict[int, bop.ImageRecord]:
        """{im_id: record} of a scene; empty when it is missing or unreadable (reported where scenes are checked)."""
        if not bop.scene_dir(self.root, split, scene_id).is_dir():
            return {}
        try:
            return {r.im_id: r for r in bop.iter_scene_images(self.root, split, [scene_id])}
        except DatasetError:
            return {}

    # -- scenes ---------------------------------------------------------------------------------------
    def scene(self, split: str, scene_id: int, max_images: int | None) -> None:
        sd = bop.scene_dir(self.root, split, scene_id)
        for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
            if not os.path.lexists(sd / name):
                self.add(f"{self.rel(sd / name)}: missing")
                return
        records = self.read(lambda: list(bop.iter_scene_images(self.root, split, [scene_id])))
        if records is None:
            return
        self.report.scenes += 1
        for rec in records[:max_images]:
            if self.full:
                return
            self.image_record(rec)

    def image_record(self, rec: bop.ImageRecord) -> None:
        where = f"{self.rel(rec.scene_dir)}/scene_camera.json: im {rec.im_id}"
        T = rec.camera.T_cam_world
        if T is not None and (why := rotation_problem(T[:3, :3])):
            self.add(f"{where}: cam_R_w2c {why}")
        if T is not None and np.linalg.norm(T[:3, 3]) * 1000.0 < METRES_BELOW_MM:
            self.add(f"{where}: cam_t_w2c {np.round(T[:3, 3] * 1000.0, 4).tolist()} looks like metres; BOP "
                     "translations are in millimetres")
        self.report.images += 1
        self.read(rec.load_rgb)
        depth = self.read(rec.load_depth)
        depth_mm = None if depth is None else depth.astype(np.float64) * 1000.0
        for g in rec.instances:
            self.instance(rec, g, depth_mm)

    def instance(self, rec: bop.ImageRecord, g: bop.GTInstance, depth_mm: np.ndarray | None) -> None:
        rel, im, i, oid = self.rel(rec.scene_dir), rec.im_id, g.gt_index, g.obj_id
        where = f"{rel}/scene_gt.json: im {im} gt {i}"
        if oid not in self.infos:
            self.add(f"{where}: obj_id {oid} is not in models/models_info.json")
        R, t = g.T_cam_obj[:3, :3], g.T_cam_obj[:3, 3] * 1000.0
        units_ok = True
        if (why := rotation_problem(R)) is not None:
            self.add(f"{where}: cam_R_m2c {why}")
            units_ok = False
        if np.linalg.norm(t) < METRES_BELOW_MM:
            self.add(f"{where}: cam_t_m2c {np.round(t, 4).tolist()} looks like metres; BOP translations are in "
                     "millimetres")
            units_ok = False
        self.report.instances[oid] += 1
        self.report.visib_fracts.append(g.info.visib_fract)
        masks = [self.read(rec.load_mask, i, v) for v in (False, True)]
        if any(m is None for m in masks):
            return
        full, visib = masks
        self.mask_info(f"{rel}/scene_gt_info.json: im {im} gt {i}", full, visib, g.info, depth_mm)
        if visib.any():
            self.report.visible[oid] += 1
        if self.opts.model_depth and depth_mm is not None and units_ok and oid in self.meshes:
            self.depth_on_model(f"{rel}/depth/{im:06d}.png: gt {i} (obj {oid})", depth_mm, rec.camera.K, visib,
                                g.T_cam_obj, self.meshes[oid])

    def mask_info(self, where: str, full: np.ndarray, visib: np.ndarray, info: bop.GTInfo,
                  depth_mm: np.ndarray | None) -> None:
        """Pixel counts, boxes and visible fraction in ``scene_gt_info.json`` against the masks (in the image)."""
        n_all, n_vis = int(full.sum()), int(visib.sum())
        h, w = full.shape
        outside = int((visib & ~full).sum())
        if outside:
            self.add(f"{where}: {outside} visible-mask pixels lie outside the full (amodal) mask")
        bx, by, bw, bh = info.bbox_obj
        inside = info.px_count_all > 0 and bx >= 0 and by >= 0 and bx + bw < w and by + bh < h
        if info.px_count_all < n_all or (inside and info.px_count_all != n_all):
            self.add(f"{where}: px_count_all {info.px_count_all} != {n_all} pixels in mask/"
                     + ("" if inside else " (or more, with the silhouette beyond the image)"))
        if info.px_count_visib != n_vis:
            self.add(f"{where}: px_count_visib {info.px_count_visib} != {n_vis} pixels in mask_visib/")
        if depth_mm is not None and info.px_count_valid != (n_valid := int((full & (depth_mm > 0)).sum())):
            self.add(f"{where}: px_count_valid {info.px_count_valid} != {n_valid} mask pixels with depth")
        frac = info.px_count_visib / info.px_count_all if info.px_count_all else 0.0
        if abs(info.visib_fract - frac) > 1e-3:
            self.add(f"{where}: visib_fract {info.visib_fract} != px_count_visib / px_count_all = {frac:.4f}")
        for key, count in (("bbox_obj", info.px_count_all), ("bbox_visib", n_vis)):
            if not count and tuple(getattr(info, key)) != bop.EMPTY_BOX:
                self.add(f"{where}: {key} {list(getattr(info, key))} of no pixel must be {list(bop.EMPTY_BOX)} "
                         "(bop_toolkit)")
        bv = bop.mask_bbox(visib)
        if n_vis and np.abs(np.subtract(info.bbox_visib, bv)).max() > 1:
            self.add(f"{where}: bbox_visib {list(info.bbox_visib)} != box of mask_visib {list(bv)} "
                     "(w = x_max - x_min)")
        if n_all:
            x, y, mw, mh = bop.mask_bbox(full)
            if bx > x + 1 or by > y + 1 or bx + bw < x + mw - 1 or by + bh < y + mh - 1:
                self.add(f"{where}: bbox_obj {list(info.bbox_obj)} does not contain the mask's box {[x, y, mw, mh]}")
            elif inside and np.abs(np.subtract(info.bbox_obj, (x, y, mw, mh))).max() > 1:
                self.add(f"{where}: bbox_obj {list(info.bbox_obj)} != box of mask {[x, y, mw, mh]} "
                         "(w = x_max - x_min)")

    def depth_on_model(self, where: str, depth_mm: np.ndarray, K: np.ndarray, visib: np.ndarray, T: np.ndarray,
                       mesh) -> None:
        """Depth at the visible mask back-projected into the object frame must lie on the model. Only the mask's
        pixels ``INNER_PX`` in from its outline count: a sensor's lateral jitter (datagen's moves a reading up to
        2 px) lets a sliver of a part seen between others measure its neighbours."""
        import cv2
        import trimesh

        inner = cv2.erode(visib.astype(np.uint8), np.ones((2 * INNER_PX + 1,) * 2, np.uint8)) > 0
        v, u = np.nonzero(inner & (depth_mm > 0))
        if len(v) < 30:
            return
        sel = np.linspace(0, len(v) - 1, min(len(v), 300)).astype(int)
        v, u = v[sel], u[sel]
        z = depth_mm[v, u] / 1000.0
        ratio = float(np.median(z) / T[2, 3]) if T[2, 3] > 0 else float("nan")
        for factor, what in ((10.0, "depth_scale looks 10x too large"), (0.1, "depth_scale looks 10x too small"),
                             (1000.0, "depth looks like it is in metres x depth_scale, or translations in metres"),
                             (0.001, "depth looks 1000x too small")):
            if 0.7 * factor < ratio < 1.4 * factor:
                self.add(f"{where}: measured depth / GT distance = {ratio:.3g}: {what}")
                return
        pts = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
        Ti = invert(T)
        _, dist, _ = trimesh.proximity.closest_point(mesh, pts @ Ti[:3, :3].T + Ti[:3, 3])
        med = float(np.median(dist)) * 1000.0
        self.report.depth_errors_mm.append(med)
        if med > self.opts.depth_tol_mm:
            self.add(f"{where}: depth at the visible mask lies {med:.1f} mm (median) from the model at its GT pose "
                     f"(tolerance {self.opts.depth_tol_mm} mm)")


def _scene_report(root: Path, opts: CheckOptions, models: tuple, scene: tuple[str, int]) -> CheckReport:
    """The report of one scene (split, scene_id) alone, ``models`` the folder's ``_models_stamp``: a task of
    ``check_dataset``'s workers."""
    c = _Checker(root, opts)
    c.infos, c.meshes = _models(root, opts, models)
    c.scene(*scene, opts.max_images)
    c.report.scenes_done = 1
    return c.report


def _models_stamp(root: Path) -> tuple:
    """(name, size, mtime) of every file in ``models/``: the key of ``_models``'s cache."""
    d = bop.models_dir(root)
    return tuple((p.name, st.st_size, st.st_mtime_ns) for p in sorted(d.iterdir()) if (st := p.stat())) \
        if d.is_dir() else ()


@functools.lru_cache(maxsize=1)
def _models(root: Path, opts: CheckOptions, stamp: tuple) -> tuple[dict[int, bop.ObjectInfo], dict[int, Any]]:
    """The models' infos and meshes a scene's check compares with, read once per process and state of ``models/``
    (``stamp``; their problems are the dataset-level check's)."""
    c = _Checker(root, opts)
    c.models()
    return c.infos, c.meshes


def check_dataset(root: str | Path, split: str | None = None, opts: CheckOptions = CheckOptions(),
                  progress: bool = False, workers: int | None = None) -> CheckReport:
    """Validate the BOP dataset at ``root`` (all splits, or ``split``), as ``opts`` say (what is checked, how many
    images per scene, when the search stops).

    Every file is read as ``train`` and ``eval`` read it; ``progress`` shows a bar over scenes. The scenes are
    checked by ``workers`` processes (None: one per core from ``PARALLEL_FROM_SCENES`` scenes on, else this one); the
    problems and their order do not depend on it.
    """
    from posegrasp.progress import track

    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"dataset folder {root} does not exist")
    c = _Checker(root, opts)
    c.models()
    camera = c.read(bop.load_camera, root)
    splits = find_splits(root)
    if split is not None:
        if split not in splits:
            raise DatasetError(f"split {split!r} not found in {root} (splits with scenes: {splits or 'none'})")
        splits = [split]
    c.report.splits = splits
    if not splits:
        c.add(f"{root}: no split folder with scene folders (e.g. train_pbr/000000/)")
    for tmp in sorted(root.rglob(".*.tmp"))[:5]:
        c.add(f"{c.rel(tmp)}: leftover of an interrupted write; rerun the generator to complete the dataset")
    if camera is None:
        return c.report
    scenes = [(s, sid) for s in splits for sid in bop.list_scenes(root, s)]
    n = workers if workers is not None else 1 if len(scenes) < PARALLEL_FROM_SCENES else os.cpu_count() or 1
    parts: dict[int, CheckReport] = {}
    with make_executor(min(n, len(scenes)) or 1) as ex:
        task = functools.partial(_scene_report, root, opts, _models_stamp(root))
        for i, part in track(ex.imap(task, scenes), "checking scenes", len(scenes), enabled=progress):
            parts[i] = part
            while len(c.report.problems) < opts.max_problems and c.report.scenes_done in parts:
                c.report.merge(parts.pop(c.report.scenes_done), opts.max_problems)
            if c.full:
                c.report.stopped_early = c.report.scenes_done < len(scenes)
                break
    if "test" in splits and not c.full and opts.scoring:
        c.targets("test")
    return c.report


def require_valid(root: str | Path, split: str, max_images: int | None = None, scoring: bool = False,
                  progress: bool = False) -> None:
    """Refuse (DatasetError, one line naming the first problem's file) a dataset in which ``dataset check`` finds
    a problem in ``split`` (``scoring``: also in ``models_eval/`` and the BOP19 targets where the dataset has them,
    as ``eval`` reads them), before
    anything is trained on or scored. The depth-against-model comparison, a tolerance on the data's quality rather
    than its form, is left to ``dataset check``."""
    root = Path(root)
    if not bop.models_dir(root).is_dir():
        raise DatasetError(f"--data {root} is not a BOP dataset (no models/ folder)")
    opts = CheckOptions(max_images=max_images, max_problems=10, model_depth=False, scoring=scoring, complete=False)
    report = check_dataset(root, split, opts, progress=progress)
    if report.problems:
        n = f"{len(report.problems)}{'+' if report.stopped_early or len(report.problems) >= 10 else ''}"
        raise DatasetError(f"--data {root}: {report.problems[0]} ({n} problem(s); 'posegrasp dataset check' lists "
                           "them)")


def print_report(report: CheckReport, root: str | Path, show_problems: int = 20) -> None:
    """Summary tables (images, instances per object, visibility histogram, depth error) and the first problems."""
    from rich.console import Console
    from rich.table import Table

    con = Console()
    con.print(f"[bold]{root}[/bold]: splits {', '.join(report.splits) or '-'}, {report.scenes} scenes, "
              f"{report.images} images, {sum(report.instances.values())} instances")
    t = Table(title="instances per object")
    for col in ("obj_id", "instances", "visible", "share"):
        t.add_column(col, justify="right")
    total = max(sum(report.instances.values()), 1)
    for oid, n in sorted(report.instances.items()):
        t.add_row(str(oid), str(n), str(report.visible[oid]), f"{100 * n / total:.1f}%")
    con.print(t)
    if report.visib_fracts:
        h, _ = np.histogram(report.visib_fracts, HIST_BINS)
        ht = Table(title="visibility (visib_fract)")
        ht.add_column("range")
        ht.add_column("instances", justify="right")
        ht.add_column("")
        for lo, hi, n in zip(HIST_BINS[:-1], HIST_BINS[1:], h):
            ht.add_row(f"{lo:.1f}-{hi:.1f}", str(n), "#" * int(round(40 * n / max(h.max(), 1))))
        con.print(ht)
    if report.depth_errors_mm:
        e = np.asarray(report.depth_errors_mm)
        con.print(f"depth vs model at GT pose: median {np.median(e):.2f} mm, worst instance {e.max():.2f} mm "
                  f"({len(e)} instances)")
    if report.ok:
        con.print("[green]OK[/green]: no problems found")
        return
    con.print(f"[red]{len(report.problems)} problem(s)[/red]" + (", search stopped early" if report.stopped_early else ""))
    for p in report.problems[:show_problems]:
        con.print(f"  {p}", markup=False, highlight=False, soft_wrap=True)
    if len(report.problems) > show_problems:
        con.print(f"  ... and {len(report.problems) - show_problems} more")
