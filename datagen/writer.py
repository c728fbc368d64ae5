"""Writing generated frames into a BOP dataset, a scene complete only once all its files are.

Per scene: ``rgb/`` (jpg or png), ``depth/`` (uint16 png, value x depth_scale = mm), optional ``depth_clean/``,
``mask/`` (amodal) and ``mask_visib/`` (0/255 png per annotation), then ``scene_camera.json``,
``scene_gt.json``, ``scene_datagen.json`` (what generation did) and, last, ``scene_gt_info.json``: a scene
is complete exactly when that file exists. The bytes of every file come from ``posegrasp.bop``.

A worker encodes a scene's files in memory (``SceneWriter``) and returns them; the process that owns the
output folder writes them (``SceneWriter.write``), so workers never touch the dataset (no shared filesystem
on a cluster, and a worker outliving a killed parent has nothing to write). Image files go straight
into the scene's folder, made afresh (a killed run's partial folder is incomplete and is written again), without
temporary files or per-file fsyncs (10-40 ms a frame); one ``os.sync()`` before the JSON files (atomic and
fsynced) makes sure a scene marked complete has all its images on disk even after a power cut.
"""

from __future__ import annotations

import functools
import os
import shutil
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.bop import images as bop_images
from posegrasp import inputs
from posegrasp import io as pio
from posegrasp.catalog import set_root
from posegrasp.errors import DatasetError
from posegrasp.geometry import invert
from posegrasp.sim.camera import Frame

COMPLETE_FILE = "scene_gt_info.json"
EVAL_EDGE = 0.05  #: longest edge of a ``models_eval/`` model, as a fraction of its diameter


def write_if_changed(path: Path, data: bytes) -> None:
    """Atomically write ``data`` unless ``path`` already holds exactly it."""
    if not (path.is_file() and inputs.read_bytes(path, "mesh", DatasetError) == data):
        pio.write_bytes(path, data)


def _set_models(objects: str) -> dict[str, bytes]:
    """The object set's BOP ``models/`` files (name -> bytes): its PLY models and ``models_info.json``."""
    src = set_root(objects) / "models"
    return _set_models_in(src, [p.name for p in sorted(src.iterdir()) if p.suffix in (".ply", ".json")])


def _set_models_in(folder: Path, names: Iterable[str]) -> dict[str, bytes]:
    """The files ``names`` of ``folder`` (name -> bytes), each a bounded regular file (``posegrasp.inputs``)."""
    return {n: inputs.read_bytes(folder / n, "mesh", DatasetError) for n in names}


def prepare_root(root: Path, camera: bop.Camera, objects: str = "") -> None:
    """Write ``models/`` (the object set ``objects``'s BOP models, byte for byte; ``""``: the shipped blocks) and
    ``camera.json``; remove leftovers of killed writes (``models_eval/``, the caller's: ``write_models_eval``). Models
    of another set or a ``camera.json`` for another camera are a DatasetError (one dataset, one set, one camera) once
    a scene was completed with them; before that (a failed start) they are replaced."""
    for tmp in [*root.glob(".*.tmp"), *root.glob("models/.*.tmp"), *root.glob("models_eval/.*.tmp")]:
        tmp.unlink(missing_ok=True)
    models = _set_models(objects)
    have = {p.name for p in bop.models_dir(root).glob("*") if p.suffix in (".ply", ".json")}
    if has_scenes(root) and (have != set(models) or _set_models_in(bop.models_dir(root), models) != models):
        raise DatasetError(f"{root} was generated from another object set (its models/ differ from those of "
                           f"{set_root(objects)}); use a new --out or the original --objects")
    for name in sorted(have - set(models)):  # a failed start with another set
        for d in (bop.models_dir(root), bop.models_eval_dir(root)):
            (d / name).unlink(missing_ok=True)
    for name, data in models.items():
        write_if_changed(bop.models_dir(root) / name, data)
    cam_file = bop.camera_path(root)
    if cam_file.is_file() and has_scenes(root):
        old = bop.load_camera(cam_file)
        if (old.width, old.height) != (camera.width, camera.height) or not np.allclose(old.K, camera.K) \
                or old.depth_scale != camera.depth_scale:
            raise DatasetError(f"{cam_file} describes another camera ({old.width}x{old.height}, depth_scale "
                               f"{old.depth_scale}); use a new --out or the same --resolution and depth_scale")
    bop.write_camera(root, camera)


def write_models_eval(root: Path) -> None:
    """Write ``models_eval/``: each model of ``models/`` with its edges split down to ``EVAL_EDGE`` x its diameter
    (``bop_models.resample_for_eval``), in mm, as the BOP metrics' evaluation points and VSD's renderings use, and
    ``models_info.json`` (the same surfaces, so the same info; bop_toolkit's ``eval_bop19_pose.py`` reads it there)."""
    diameters = {o: i.diameter / bop.MM for o, i in bop.load_models_info(root).items()}
    for oid, diameter in diameters.items():
        src = bop.model_path(root, oid)
        v, f = bop_models.resample_for_eval(*bop_models.model_arrays(src, scale=1.0), EVAL_EDGE * diameter)
        write_if_changed(bop.models_eval_dir(root) / src.name, bop_models.ply_bytes(v, f))
    write_if_changed(bop.models_eval_dir(root) / "models_info.json", bop.models_info_path(root).read_bytes())


def has_scenes(root: Path, split: str = "*") -> bool:
    """Whether ``split`` (any split: ``*``) of ``root`` holds a complete scene (its settings then bind)."""
    return any(root.glob(f"{split}/*/{COMPLETE_FILE}"))


class SceneWriter:
    """One scene's encoded images and labels, accumulated in memory (in a worker) and written by ``write`` into
    ``<root>/<split>/<scene>/`` (by the process owning the dataset)."""

    def __init__(self, depth_scale: float, rgb_ext: str, jpg_quality: int = 95):
        self.depth_scale, self.rgb_ext, self.jpg_quality = depth_scale, rgb_ext, jpg_quality
        self.files: dict[Path, bytes] = {}  # image files, by path relative to the scene folder
        self.gt: dict[int, list[tuple[int, np.ndarray]]] = {}
        self.cams: dict[int, bop.SceneCamera] = {}
        self.infos: dict[int, list[bop.GTInfo]] = {}
        self.extra: dict[str, Any] = {}

    def _put(self, path: Path, data: bytes) -> None:
        self.files[path] = data

    def add(self, im_id: int, frame: Frame, rgb: np.ndarray, depth: np.ndarray, clean_depth: bool) -> None:
        """Encode image ``im_id``: ``rgb`` and ``depth`` (m) as measured, masks and labels from ``frame``
        (``frame.extra``: ``amodal`` masks, their pixel ``boxes`` and their parts ``beyond`` the image)."""
        d = Path()  # paths relative to the scene folder
        self._put(bop.image_path(d, "rgb", im_id, self.rgb_ext), bop_images.encode_rgb(rgb, self.rgb_ext, self.jpg_quality))
        self._put(bop.image_path(d, "depth", im_id), bop_images.encode_depth(depth, self.depth_scale))
        if clean_depth:
            self._put(bop.image_path(d, "depth_clean", im_id), bop_images.encode_depth(frame.depth, self.depth_scale))
        gts, infos = [], []
        for i, (oid, T) in enumerate(zip(frame.obj_ids, frame.T_cam_obj)):
            # visible = the scene render's pixels of block i within its silhouette: the two rasterisers (MuJoCo's
            # scene, pyrender's model alone) can disagree on a single edge pixel of a thin imported part
            amodal, box = frame.extra["amodal"][i], frame.extra["boxes"][i]
            visib = np.zeros_like(amodal)
            if box is not None:  # (the amodal mask lies in its box)
                sl = np.s_[box[1]:box[3], box[0]:box[2]]
                visib[sl] = (frame.mask[sl] == i + 1) & amodal[sl]
            info = bop.gt_info_from_masks(amodal, visib, depth, box, *frame.extra["beyond"][i])
            full_png = bop_images.encode_mask(amodal) if info.px_count_all else self._empty_mask(amodal.shape)
            same = info.px_count_visib == info.px_count_all and np.array_equal(visib, amodal)  # fully visible
            self._put(bop.mask_path(d, im_id, i, visible=False), full_png)
            self._put(bop.mask_path(d, im_id, i, visible=True), full_png if same else bop_images.encode_mask(visib))
            gts.append((int(oid), T))
            infos.append(info)
        self.gt[im_id], self.infos[im_id] = gts, infos
        self.cams[im_id] = bop.SceneCamera(K=frame.K, depth_scale=self.depth_scale,
                                           T_cam_world=invert(frame.T_world_cam))

    @staticmethod
    @functools.lru_cache(maxsize=4)
    def _empty_mask(shape: tuple[int, int]) -> bytes:
        return bop_images.encode_mask(np.zeros(shape, bool))

    def finish(self, extra: dict[str, Any]) -> None:
        """Close the scene with what ``scene_datagen.json`` records."""
        self.extra = extra

    def write(self, scene_dir: Path, extra_file: str = "scene_datagen.json") -> None:
        """Write the scene into ``scene_dir`` from scratch (leftovers of a killed run removed): the images, one
        ``os.sync()``, then the JSON files (``extra_file`` holds ``finish``'s record), ``scene_gt_info.json`` last
        (scene complete)."""
        if scene_dir.exists():
            shutil.rmtree(scene_dir)
        for sub in {*map(Path, ("rgb", "depth", "mask", "mask_visib")), *(Path(rel).parent for rel in self.files)}:
            (scene_dir / sub).mkdir(parents=True, exist_ok=True)
        with pio.writing_into(scene_dir):  # a fresh folder, incomplete until its last file: no temporary files
            for rel, data in self.files.items():
                with open(scene_dir / rel, "xb") as f:
                    f.write(data)
        os.sync()
        bop.write_scene_camera(scene_dir / "scene_camera.json", self.cams)
        bop.write_scene_gt(scene_dir / "scene_gt.json", self.gt)
        pio.write_json(scene_dir / extra_file, self.extra)
        bop.write_scene_gt_info(scene_dir / COMPLETE_FILE, self.infos)
