"""Validating a BOP dataset (``posegrasp dataset check``): schema, units, ids, rotations, masks against
``scene_gt_info.json`` (bop_toolkit's rules: boxes [x, y, w, h] with w = x_max - x_min, empty ones all -1,
``px_count_all`` and ``bbox_obj`` over the whole silhouette, also beyond the image), depth against the models at
their ground-truth poses, ``models_eval/`` and the test split's ``test_targets_bop19.json``. Works on any BOP
dataset, not only generated ones.

Every problem is a line naming the file (relative to the dataset root) and what is wrong with it.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from posegrasp import bop
from posegrasp import bop_models
from posegrasp import io as pio
from posegrasp.errors import DatasetError, UserError
from posegrasp.geometry import invert

#: Required keys and their kinds: "num" a number, "int" an integer, ("nums", n) a list of n numbers.
CAMERA_KEYS = {"fx": "num", "fy": "num", "cx": "num", "cy": "num", "width": "int", "height": "int"}
MODEL_KEYS = {"diameter": "num", **{f"{p}_{a}": "num" for p in ("min", "size") for a in "xyz"}}
SCENE_CAMERA_KEYS = {"cam_K": ("nums", 9)}
#: Keys of scene_camera.json checked only when present.
SCENE_CAMERA_OPTIONAL = {"cam_R_w2c": ("nums", 9), "cam_t_w2c": ("nums", 3), "depth_scale": "num"}
GT_KEYS = {"cam_R_m2c": ("nums", 9), "cam_t_m2c": ("nums", 3), "obj_id": "int"}
INFO_KEYS = {"bbox_obj": ("nums", 4), "bbox_visib": ("nums", 4), "px_count_all": "int", "px_count_valid": "int",
             "px_count_visib": "int", "visib_fract": "num"}
TARGET_KEYS = {"scene_id": "int", "im_id": "int", "obj_id": "int", "inst_count": "int"}
HIST_BINS = np.linspace(0.0, 1.0, 11)


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

    @property
    def ok(self) -> bool:
        return not self.problems


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def schema_problems(obj: Any, keys: dict[str, Any], where: str) -> list[str]:
    """Missing keys and wrongly typed values of a JSON object against ``keys``."""
    if not isinstance(obj, dict):
        return [f"{where}: expected a JSON object, got {type(obj).__name__}"]
    out = []
    for k, kind in keys.items():
        if k not in obj:
            out.append(f"{where}: missing key '{k}'")
            continue
        v = obj[k]
        if kind == "num" and not _is_num(v):
            out.append(f"{where}: '{k}' must be a number, got {v!r}")
        elif kind == "int" and not (isinstance(v, int) and not isinstance(v, bool)):
            out.append(f"{where}: '{k}' must be an integer, got {v!r}")
        elif isinstance(kind, tuple) and not (isinstance(v, list) and len(v) == kind[1] and all(_is_num(x) for x in v)):
            out.append(f"{where}: '{k}' must be a list of {kind[1]} numbers, got {v!r}")
    return out


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


class _Checker:
    """Accumulates problems over one dataset; ``max_problems`` stops the search early."""

    def __init__(self, root: Path, depth_tol_mm: float, max_problems: int, labels_only: bool = False):
        self.root, self.tol, self.max_problems, self.labels_only = root, depth_tol_mm, max_problems, labels_only
        self.report = CheckReport()
        self.meshes: dict[int, Any] = {}
        self.infos: dict[str, Any] = {}

    def add(self, msg: str) -> None:
        self.report.problems.append(msg)

    @property
    def full(self) -> bool:
        return len(self.report.problems) >= self.max_problems

    def rel(self, p: Path) -> str:
        return str(p.relative_to(self.root))

    def json(self, path: Path) -> Any:
        """Parsed JSON, or None with a problem recorded."""
        try:
            return json.loads(path.read_text())
        except FileNotFoundError:
            self.add(f"{self.rel(path)}: missing")
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            self.add(f"{self.rel(path)}: not valid JSON ({e})")
        except OSError as e:
            self.add(f"{self.rel(path)}: unreadable ({e.strerror})")
        return None

    def image(self, path: Path, shape: tuple[int, int], what: str) -> np.ndarray | None:
        """An image of the camera's size, or None with a problem recorded."""
        try:
            img = pio.read_image(path)
        except OSError:
            self.add(f"{self.rel(path)}: {'missing' if not path.exists() else 'unreadable (corrupt or not an image)'}")
            return None
        if img.shape[:2] != shape:
            self.add(f"{self.rel(path)}: {what} is {img.shape[1]}x{img.shape[0]}, camera.json says {shape[1]}x{shape[0]}")
            return None
        return img

    # -- dataset level --------------------------------------------------------------------------------
    def models(self) -> None:
        path = bop.models_info_path(self.root)
        data = self.json(path)
        if not isinstance(data, dict) or not data:
            if data is not None:
                self.add(f"{self.rel(path)}: expected a non-empty object keyed by obj_id")
            return
        for key, d in data.items():
            where = f"{self.rel(path)}: obj {key}"
            if not key.isdigit():
                self.add(f"{where}: key must be an integer obj_id")
                continue
            probs = schema_problems(d, MODEL_KEYS, where)
            if probs:
                self.report.problems.extend(probs)
                continue
            if d["diameter"] < 1.0:
                self.add(f"{where}: diameter {d['diameter']} looks like metres; BOP models_info is in millimetres")
            for s, flat in enumerate(d.get("symmetries_discrete", [])):
                if not (isinstance(flat, list) and len(flat) == 16 and all(_is_num(x) for x in flat)):
                    self.add(f"{where}: symmetries_discrete[{s}] must be 16 numbers (4x4 row-major)")
                elif (why := rotation_problem(np.reshape(flat, (4, 4))[:3, :3])) is not None:
                    self.add(f"{where}: symmetries_discrete[{s}] rotation {why}")
            for s, c in enumerate(d.get("symmetries_continuous", [])):
                self.report.problems.extend(schema_problems(c, {"axis": ("nums", 3), "offset": ("nums", 3)},
                                                            f"{where}: symmetries_continuous[{s}]"))
            self.infos[key] = d
            self.model(int(key), d)
            if not self.labels_only:  # eval falls back to models/ without models_eval/
                self.eval_model(int(key))

    def model(self, obj_id: int, d: dict[str, Any]) -> None:
        """The PLY exists, loads, and its extent (mm) matches ``models_info.json``."""
        p = bop.model_path(self.root, obj_id)
        if not p.is_file():
            self.add(f"{self.rel(p)}: missing (listed in models_info.json)")
            return
        try:
            mesh = bop_models.load_model(p)  # metres, assuming the file is in mm
        except UserError:
            self.add(f"{self.rel(p)}: unreadable (corrupt or not a PLY mesh)")
            return
        size_mm = np.ptp(np.asarray(mesh.vertices), axis=0) * 1000.0
        want = np.array([d["size_x"], d["size_y"], d["size_z"]], float)
        ratio = float(np.max(want) / max(np.max(size_mm), 1e-12))
        if not 0.98 < ratio < 1.02:
            units = " (the model looks like metres)" if 500 < ratio < 2000 else ""
            self.add(f"{self.rel(p)}: extent {np.round(size_mm, 2).tolist()} mm does not match models_info.json "
                     f"size {want.tolist()} mm{units}")
            return
        self.meshes[obj_id] = mesh

    def eval_model(self, obj_id: int) -> None:
        """``models_eval/`` (the BOP metrics' points and renderings) holds the model, with its extent and at least
        its vertices."""
        p = bop.models_eval_dir(self.root) / f"obj_{obj_id:06d}.ply"
        if not p.is_file():
            self.add(f"{self.rel(p)}: missing; BOP's metrics use models_eval/ (rerun the datagen command to add it)")
            return
        try:
            dense = bop_models.load_model(p)
        except UserError:
            self.add(f"{self.rel(p)}: unreadable (corrupt or not a PLY mesh)")
            return
        mesh = self.meshes.get(obj_id)
        if mesh is None:
            return
        if not np.allclose(np.ptp(dense.vertices, axis=0), np.ptp(mesh.vertices, axis=0), rtol=0.02, atol=1e-4):
            self.add(f"{self.rel(p)}: extent differs from models/obj_{obj_id:06d}.ply")
        elif len(dense.vertices) < len(mesh.vertices):
            self.add(f"{self.rel(p)}: {len(dense.vertices)} vertices, fewer than the model's {len(mesh.vertices)}")

    def targets(self, split: str) -> None:
        """``test_targets_bop19.json`` (test split): entries well formed, naming images of the split, with
        inst_count = the object's instances there at least 10 % visible (BOP 2019)."""
        path = bop.targets_path(self.root)
        if not path.is_file():
            self.add(f"{self.rel(path)}: missing; BOP 2019 scores the test split on it (rerun the datagen command "
                     "to add it)")
            return
        rows = self.json(path)
        if not isinstance(rows, list):
            if rows is not None:
                self.add(f"{self.rel(path)}: expected a list of targets")
            return
        scenes: dict[int, dict[int, bop.ImageRecord]] = {}
        for i, t in enumerate(rows):
            if self.full:
                return
            probs = schema_problems(t, TARGET_KEYS, f"{self.rel(path)}: entry {i}")
            if probs:
                self.report.problems.extend(probs)
                continue
            if t["scene_id"] not in scenes:
                scenes[t["scene_id"]] = self.scene_records(split, t["scene_id"])
            rec = scenes[t["scene_id"]].get(t["im_id"])
            if rec is None:
                self.add(f"{self.rel(path)}: entry {i} names scene {t['scene_id']} image {t['im_id']}, not in {split}/")
                continue
            n = sum(g.obj_id == t["obj_id"] and g.info is not None and g.info.visib_fract >= bop.MIN_TARGET_VISIB
                    for g in rec.instances)
            if t["inst_count"] != n:
                self.add(f"{self.rel(path)}: entry {i} (scene {t['scene_id']} im {t['im_id']} obj {t['obj_id']}): "
                         f"inst_count {t['inst_count']} != {n} instances with visib_fract >= {bop.MIN_TARGET_VISIB}")

    def scene_records(self, split: str, scene_id: int) -> dict[int, bop.ImageRecord]:
        """{im_id: record} of a scene; empty when it is missing or unreadable (reported where scenes are checked)."""
        if not bop.scene_dir(self.root, split, scene_id).is_dir():
            return {}
        try:
            return {r.im_id: r for r in bop.iter_scene_images(self.root, split, [scene_id])}
        except (UserError, KeyError, TypeError, ValueError):
            return {}

    def camera(self) -> tuple[int, int] | None:
        path = bop.camera_path(self.root)
        d = self.json(path)
        if d is None:
            return None
        probs = schema_problems(d, CAMERA_KEYS, self.rel(path))
        if "depth_scale" in d and not (_is_num(d["depth_scale"]) and d["depth_scale"] > 0):
            probs.append(f"{self.rel(path)}: 'depth_scale' must be a positive number, got {d['depth_scale']!r}")
        self.report.problems.extend(probs)
        return None if probs else (int(d["height"]), int(d["width"]))

    # -- scenes ---------------------------------------------------------------------------------------
    def scene(self, sd: Path, shape: tuple[int, int], max_images: int | None) -> None:
        cams = self.json(sd / "scene_camera.json")
        gts = self.json(sd / "scene_gt.json")
        infos = self.json(sd / "scene_gt_info.json")
        for name, x in (("scene_camera", cams), ("scene_gt", gts), ("scene_gt_info", infos)):
            if x is not None and not isinstance(x, dict):
                self.add(f"{self.rel(sd)}/{name}.json: expected a JSON object keyed by image id, got {type(x).__name__}")
        if not all(isinstance(x, dict) for x in (cams, gts, infos)):
            return
        ids = [set(x) for x in (cams, gts, infos)]
        if not ids[0] == ids[1] == ids[2]:
            self.add(f"{self.rel(sd)}: scene_camera, scene_gt and scene_gt_info list different images")
        self.report.scenes += 1
        for key in sorted(ids[0] & ids[1] & ids[2], key=lambda k: int(k) if k.isdigit() else -1)[:max_images]:
            if self.full:
                return
            self.image_record(sd, key, cams[key], gts[key], infos[key], shape)

    def image_record(self, sd: Path, key: str, cam: Any, gts: Any, infos: Any, shape: tuple[int, int]) -> None:
        rel = self.rel(sd)
        where = f"{rel}/scene_camera.json: im {key}"
        probs = schema_problems(cam, SCENE_CAMERA_KEYS, where)
        if not probs:
            probs = schema_problems(cam, {k: v for k, v in SCENE_CAMERA_OPTIONAL.items() if k in cam}, where)
        if not key.isdigit():
            probs.append(f"{rel}: image id {key!r} is not an integer")
        if not isinstance(gts, list) or not isinstance(infos, list) or len(gts) != len(infos):
            probs.append(f"{rel}: im {key}: scene_gt and scene_gt_info must be lists of the same length")
        if probs:
            self.report.problems.extend(probs)
            return
        im = int(key)
        scale = cam.get("depth_scale", 1.0)
        if not scale > 0:
            self.add(f"{where}: 'depth_scale' must be a positive number, got {scale!r}")
            return
        if "cam_R_w2c" in cam and (why := rotation_problem(np.reshape(cam["cam_R_w2c"], (3, 3)))):
            self.add(f"{where}: cam_R_w2c {why}")
        if "cam_t_w2c" in cam and np.linalg.norm(cam["cam_t_w2c"]) < 10.0:
            self.add(f"{where}: cam_t_w2c {cam['cam_t_w2c']} looks like metres; BOP translations are in millimetres")
        K = np.reshape(cam["cam_K"], (3, 3))
        self.report.images += 1
        depth_mm = None if self.labels_only else self.rgbd(sd, im, shape, scale)
        for i, (g, info) in enumerate(zip(gts, infos)):
            self.instance(sd, im, i, g, info, K, depth_mm, shape)

    def rgbd(self, sd: Path, im: int, shape: tuple[int, int], scale: float) -> np.ndarray | None:
        """Check image ``im``'s colour and depth images; its depth (mm), or None if unusable."""
        rgb_png, rgb_jpg = bop.image_path(sd, "rgb", im, "png"), bop.image_path(sd, "rgb", im, "jpg")
        self.image(rgb_png if rgb_png.exists() or not rgb_jpg.exists() else rgb_jpg, shape, "rgb")
        dpath = bop.image_path(sd, "depth", im)
        depth = self.image(dpath, shape, "depth")
        if depth is not None and depth.dtype != np.uint16:
            self.add(f"{self.rel(dpath)}: depth must be a uint16 png, got {depth.dtype}")
            depth = None
        return None if depth is None else depth.astype(np.float64) * scale

    def instance(self, sd: Path, im: int, i: int, g: Any, info: Any, K: np.ndarray, depth_mm: np.ndarray | None,
                 shape: tuple[int, int]) -> None:
        rel = self.rel(sd)
        where = f"{rel}/scene_gt.json: im {im} gt {i}"
        probs = schema_problems(g, GT_KEYS, where) + schema_problems(info, INFO_KEYS, f"{rel}/scene_gt_info.json: im {im} gt {i}")
        if probs:
            self.report.problems.extend(probs)
            return
        oid = g["obj_id"]
        if str(oid) not in self.infos:
            self.add(f"{where}: obj_id {oid} is not in models/models_info.json")
        R, t = np.reshape(g["cam_R_m2c"], (3, 3)), np.asarray(g["cam_t_m2c"], float)
        units_ok = True
        if (why := rotation_problem(R)) is not None:
            self.add(f"{where}: cam_R_m2c {why}")
            units_ok = False
        if np.linalg.norm(t) < 10.0:
            self.add(f"{where}: cam_t_m2c {t.tolist()} looks like metres; BOP translations are in millimetres")
            units_ok = False
        self.report.instances[oid] += 1
        self.report.visib_fracts.append(float(info["visib_fract"]))
        if self.labels_only:
            return
        masks = [self.image(bop.mask_path(sd, im, i, visible=v), shape, "mask") for v in (False, True)]
        if any(m is None for m in masks):
            return
        full, visib = (m > 0 for m in masks)
        self.mask_info(f"{rel}/scene_gt_info.json: im {im} gt {i}", full, visib, info, depth_mm)
        if visib.any():
            self.report.visible[oid] += 1
        if depth_mm is not None and units_ok and oid in self.meshes:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t / 1000.0
            self.depth_on_model(f"{rel}/depth/{im:06d}.png: gt {i} (obj {oid})", depth_mm, K, visib, T, self.meshes[oid])

    def mask_info(self, where: str, full: np.ndarray, visib: np.ndarray, info: dict, depth_mm: np.ndarray | None) -> None:
        """Pixel counts, boxes and visible fraction in ``scene_gt_info.json`` against the masks (in the image)."""
        n_all, n_vis = int(full.sum()), int(visib.sum())
        h, w = full.shape
        outside = int((visib & ~full).sum())
        if outside:
            self.add(f"{where}: {outside} visible-mask pixels lie outside the full (amodal) mask")
        bx, by, bw, bh = info["bbox_obj"]
        inside = info["px_count_all"] > 0 and bx >= 0 and by >= 0 and bx + bw < w and by + bh < h
        if info["px_count_all"] < n_all or (inside and info["px_count_all"] != n_all):
            self.add(f"{where}: px_count_all {info['px_count_all']} != {n_all} pixels in mask/"
                     + ("" if inside else " (or more, with the silhouette beyond the image)"))
        if info["px_count_visib"] != n_vis:
            self.add(f"{where}: px_count_visib {info['px_count_visib']} != {n_vis} pixels in mask_visib/")
        if depth_mm is not None and info["px_count_valid"] != (n_valid := int((full & (depth_mm > 0)).sum())):
            self.add(f"{where}: px_count_valid {info['px_count_valid']} != {n_valid} mask pixels with depth")
        frac = info["px_count_visib"] / info["px_count_all"] if info["px_count_all"] else 0.0
        if abs(info["visib_fract"] - frac) > 1e-3:
            self.add(f"{where}: visib_fract {info['visib_fract']} != px_count_visib / px_count_all = {frac:.4f}")
        for key, count in (("bbox_obj", info["px_count_all"]), ("bbox_visib", n_vis)):
            if not count and list(info[key]) != list(bop.EMPTY_BOX):
                self.add(f"{where}: {key} {info[key]} of no pixel must be {list(bop.EMPTY_BOX)} (bop_toolkit)")
        bv = bop.mask_bbox(visib)
        if n_vis and np.abs(np.subtract(info["bbox_visib"], bv)).max() > 1:
            self.add(f"{where}: bbox_visib {info['bbox_visib']} != box of mask_visib {list(bv)} (w = x_max - x_min)")
        if n_all:
            x, y, mw, mh = bop.mask_bbox(full)
            if bx > x + 1 or by > y + 1 or bx + bw < x + mw - 1 or by + bh < y + mh - 1:
                self.add(f"{where}: bbox_obj {info['bbox_obj']} does not contain the mask's box {[x, y, mw, mh]}")
            elif inside and np.abs(np.subtract(info["bbox_obj"], (x, y, mw, mh))).max() > 1:
                self.add(f"{where}: bbox_obj {info['bbox_obj']} != box of mask {[x, y, mw, mh]} (w = x_max - x_min)")

    def depth_on_model(self, where: str, depth_mm: np.ndarray, K: np.ndarray, visib: np.ndarray, T: np.ndarray,
                       mesh) -> None:
        """Depth at the visible mask back-projected into the object frame must lie on the model."""
        import trimesh

        v, u = np.nonzero(visib & (depth_mm > 0))
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
        if med > self.tol:
            self.add(f"{where}: depth at the visible mask lies {med:.1f} mm (median) from the model at its GT pose "
                     f"(tolerance {self.tol} mm)")


def check_dataset(root: str | Path, split: str | None = None, depth_tol_mm: float = 5.0, max_images: int | None = None,
                  max_problems: int = 200, progress: bool = False, labels_only: bool = False) -> CheckReport:
    """Validate the BOP dataset at ``root`` (all splits, or ``split``); ``max_images`` per scene limits the work.

    The search stops after ``max_problems`` problems; ``progress`` shows a bar over scenes. ``labels_only``
    checks ``models/`` and the JSON labels (poses, units, ids), not the images, ``models_eval/`` or the BOP19
    targets, as ``eval`` does before it scores.
    """
    from posegrasp.progress import track

    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"dataset folder {root} does not exist")
    c = _Checker(root, depth_tol_mm, max_problems, labels_only)
    c.models()
    shape = c.camera()
    splits = find_splits(root)
    if split is not None:
        if split not in splits:
            raise DatasetError(f"split {split!r} not found in {root} (splits with scenes: {splits or 'none'})")
        splits = [split]
    c.report.splits = splits
    if not splits:
        c.add(f"{root}: no split folder with scene folders (e.g. train_pbr/000000/)")
    for tmp in [] if labels_only else sorted(root.rglob(".*.tmp"))[:5]:
        c.add(f"{c.rel(tmp)}: leftover of an interrupted write; rerun the generator to complete the dataset")
    if shape is None:
        return c.report
    scenes = [bop.scene_dir(root, s, sid) for s in splits for sid in bop.list_scenes(root, s)]
    for sd in track(scenes, "checking scenes", enabled=progress):
        if c.full:
            c.report.stopped_early = True
            break
        c.scene(sd, shape, max_images)
    if "test" in splits and not c.full and not labels_only:
        c.targets("test")
    return c.report


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
