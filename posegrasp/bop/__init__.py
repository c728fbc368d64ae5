"""Reading and writing datasets in the BOP format (https://bop.felk.cvut.cz/datasets/).

Layout under a dataset root::

    models/obj_XXXXXX.ply, models/models_info.json      (mm)
    models_eval/obj_XXXXXX.ply                          (mm; the models resampled densely, for the BOP metrics)
    camera.json, test_targets_bop19.json
    <split>/<scene 6 digits>/{rgb,depth,mask,mask_visib}/<im 6 digits>.png|jpg
    <split>/<scene>/mask[_visib]/<im>_<gt index 6 digits>.png
    <split>/<scene>/scene_gt.json, scene_camera.json, scene_gt_info.json

Files are in millimetres (models, translations, depth png x depth_scale); everything this module
returns is in metres: the conversion happens here, at the boundary. Poses are 4x4 ``T_cam_obj``
(model frame -> OpenCV camera frame: x right, y down, z forward). Writers are atomic. The images'
codecs are in ``posegrasp.bop.images``, the models' meshes in ``posegrasp.bop.models``, the results files in
``posegrasp.bop.results``.
"""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

import cv2
import numpy as np

from posegrasp.bop import images as bop_images, schema as bop_schema
from posegrasp import io as pio
from posegrasp.bop.images import MM, depth_from_png
from posegrasp.errors import DatasetError, DatasetFileError

TEST_TARGETS_FILE = "test_targets_bop19.json"
MIN_TARGET_VISIB = 0.1  #: BOP 2019: instances less visible are no targets
EMPTY_BOX = (-1, -1, -1, -1)


# ---------------------------------------------------------------------------- paths

def models_dir(root: str | Path) -> Path:
    """``<root>/models``."""
    return Path(root) / "models"


def model_path(root: str | Path, obj_id: int) -> Path:
    """``<root>/models/obj_XXXXXX.ply``."""
    return models_dir(root) / f"obj_{obj_id:06d}.ply"


def models_eval_dir(root: str | Path) -> Path:
    """``<root>/models_eval`` (the models with dense, roughly uniform vertices: the BOP metrics' points)."""
    return Path(root) / "models_eval"


def eval_model_path(root: str | Path, obj_id: int) -> Path:
    """``<root>/models_eval/obj_XXXXXX.ply`` when the dataset has it, else the model itself."""
    p = models_eval_dir(root) / f"obj_{obj_id:06d}.ply"
    return p if os.path.lexists(p) else model_path(root, obj_id)


def targets_path(root: str | Path) -> Path:
    """``<root>/test_targets_bop19.json``."""
    return Path(root) / TEST_TARGETS_FILE


def models_info_path(root: str | Path) -> Path:
    """``<root>/models/models_info.json``."""
    return models_dir(root) / "models_info.json"


def camera_path(root: str | Path) -> Path:
    """``<root>/camera.json``."""
    return Path(root) / "camera.json"


def split_dir(root: str | Path, split: str) -> Path:
    """``<root>/<split>``."""
    return Path(root) / split


def scene_dir(root: str | Path, split: str, scene_id: int) -> Path:
    """``<root>/<split>/<scene 6 digits>``."""
    return split_dir(root, split) / f"{scene_id:06d}"


def image_path(scene: Path, kind: str, im_id: int, ext: str = "png") -> Path:
    """``<scene>/<kind>/<im 6 digits>.<ext>`` (kind: rgb, depth, gray)."""
    return scene / kind / f"{im_id:06d}.{ext}"


def mask_path(scene: Path, im_id: int, gt_index: int, visible: bool = True) -> Path:
    """``<scene>/mask_visib/<im>_<gt>.png`` (visible part) or ``<scene>/mask/...`` (full silhouette)."""
    return scene / ("mask_visib" if visible else "mask") / f"{im_id:06d}_{gt_index:06d}.png"


# ---------------------------------------------------------------------------- records

@dataclass
class Camera:
    """``camera.json``: image size (px), intrinsics K (3, 3) px, depth_scale (png value x scale = mm)."""

    width: int
    height: int
    K: np.ndarray
    depth_scale: float = 1.0


@dataclass
class ObjectInfo:
    """One entry of ``models_info.json``, in metres.

    symmetries_discrete: 4x4 transforms (m) mapping the model onto itself; symmetries_continuous:
    (axis (3,), offset (3,) m) pairs. ``symmetric`` is True if there is any symmetry.
    """

    obj_id: int
    diameter: float
    min_xyz: np.ndarray = field(default_factory=lambda: np.zeros(3))
    size_xyz: np.ndarray = field(default_factory=lambda: np.zeros(3))
    symmetries_discrete: list[np.ndarray] = field(default_factory=list)
    symmetries_continuous: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)

    @property
    def symmetric(self) -> bool:
        """Whether the model has any (discrete or continuous) symmetry: ADD-S applies."""
        return bool(self.symmetries_discrete or self.symmetries_continuous)

    def symmetry_rotations(self) -> tuple[np.ndarray, np.ndarray]:
        """The rotation parts (S, 3, 3) of the discrete symmetries and the continuous axes (A, 3), object frame."""
        return (np.array([np.asarray(D)[:3, :3] for D in self.symmetries_discrete]).reshape(-1, 3, 3),
                np.array([a for a, _ in self.symmetries_continuous]).reshape(-1, 3))


@dataclass
class GTInfo:
    """One entry of ``scene_gt_info.json`` as bop_toolkit computes it: boxes [x, y, w, h] px with w = x_max - x_min
    (``EMPTY_BOX`` when empty); ``px_count_all`` and ``bbox_obj`` over the whole silhouette, also outside the image;
    visib_fract = px_count_visib / px_count_all (0 when px_count_all is 0)."""

    bbox_obj: tuple[int, int, int, int] = EMPTY_BOX
    bbox_visib: tuple[int, int, int, int] = EMPTY_BOX
    px_count_all: int = 0
    px_count_valid: int = 0
    px_count_visib: int = 0
    visib_fract: float = 0.0


@dataclass
class GTInstance:
    """One annotated object in an image: BOP id, pose T_cam_obj (4x4, m), index in scene_gt, info."""

    obj_id: int
    T_cam_obj: np.ndarray
    gt_index: int
    info: GTInfo | None = None


@dataclass
class SceneCamera:
    """One entry of ``scene_camera.json``: K (3, 3), depth_scale, optional T_cam_world (4x4, m)."""

    K: np.ndarray
    depth_scale: float = 1.0
    T_cam_world: np.ndarray | None = None


@dataclass
class ImageRecord:
    """One image of a BOP split with its camera and annotations (all in metres); ``size`` (width, height) px is
    camera.json's, which its images must have."""

    root: Path
    split: str
    scene_id: int
    im_id: int
    camera: SceneCamera
    instances: list[GTInstance]
    size: tuple[int, int] | None = None

    @property
    def scene_dir(self) -> Path:
        return scene_dir(self.root, self.split, self.scene_id)

    @property
    def rgb_path(self) -> Path:
        """The colour image (png, else jpg)."""
        p = image_path(self.scene_dir, "rgb", self.im_id, "png")
        return p if os.path.lexists(p) else image_path(self.scene_dir, "rgb", self.im_id, "jpg")

    @property
    def depth_path(self) -> Path:
        return image_path(self.scene_dir, "depth", self.im_id, "png")

    def mask_path(self, gt_index: int, visible: bool = True) -> Path:
        """Path of the (visible or full) mask of annotation ``gt_index``."""
        return mask_path(self.scene_dir, self.im_id, gt_index, visible)

    def load_rgb(self) -> np.ndarray:
        """RGB uint8 (H, W, 3)."""
        img = bop_images.read(self.rgb_path, "rgb", self.size)
        return np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img[..., :3]

    def load_depth(self) -> np.ndarray:
        """Depth float32 (H, W) in metres along the optical axis; 0 = no measurement."""
        return depth_from_png(bop_images.read(self.depth_path, "depth", self.size), self.camera.depth_scale)

    def load_mask(self, gt_index: int, visible: bool = True) -> np.ndarray:
        """Boolean (H, W) mask of annotation ``gt_index``."""
        return bop_images.read(self.mask_path(gt_index, visible), "mask", self.size) > 0


def pose_from_bop(R: list[float] | np.ndarray, t_mm: list[float] | np.ndarray) -> np.ndarray:
    """4x4 pose (m) from BOP's row-major rotation (9 values) and translation (mm)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t_mm, dtype=np.float64).reshape(3) * MM
    return T


# ---------------------------------------------------------------------------- readers (checked: ``bop.schema``)

def _file(root_or_file: str | Path, default: Path) -> Path:
    p = Path(root_or_file)
    return p if p.suffix == ".json" else default


def load_models_info(root_or_file: str | Path) -> dict[int, ObjectInfo]:
    """``models_info.json`` (given the dataset root or the file itself) -> {obj_id: ObjectInfo} (m)."""
    out = {}
    for oid, d in bop_schema.models_info(_file(root_or_file, models_info_path(root_or_file))).items():
        disc = [s.copy() for s in d["symmetries_discrete"]]
        for s in disc:
            s[:3, 3] *= MM
        out[oid] = ObjectInfo(obj_id=oid, diameter=d["diameter"] * MM, min_xyz=d["min"] * MM, size_xyz=d["size"] * MM,
                              symmetries_discrete=disc,
                              symmetries_continuous=[(a, o * MM) for a, o in d["symmetries_continuous"]])
    return out


def load_camera(root_or_file: str | Path) -> Camera:
    """``camera.json`` (given the dataset root or the file) -> Camera."""
    d = bop_schema.camera(_file(root_or_file, camera_path(root_or_file)))
    return Camera(width=d["width"], height=d["height"], K=d["K"], depth_scale=d["depth_scale"])


def load_scene_gt(path: str | Path) -> dict[int, list[tuple[int, np.ndarray]]]:
    """``scene_gt.json`` -> {im_id: [(obj_id, T_cam_obj 4x4 m), ...]} in annotation order."""
    return {im: [(o, pose_from_bop(R, t)) for o, R, t in v] for im, v in bop_schema.scene_gt(path).items()}


def load_scene_camera(path: str | Path) -> dict[int, SceneCamera]:
    """``scene_camera.json`` -> {im_id: SceneCamera} (T_cam_world in m when present)."""
    return {im: SceneCamera(K=v["K"], depth_scale=v["depth_scale"],
                            T_cam_world=None if v["R_w2c"] is None else pose_from_bop(v["R_w2c"], v["t_w2c"]))
            for im, v in bop_schema.scene_camera(path).items()}


def load_scene_gt_info(path: str | Path) -> dict[int, list[GTInfo]]:
    """``scene_gt_info.json`` -> {im_id: [GTInfo, ...]} in annotation order."""
    return {im: [GTInfo(**g) for g in v] for im, v in bop_schema.scene_gt_info(path).items()}


def list_scenes(root: str | Path, split: str) -> list[int]:
    """Scene ids present in ``<root>/<split>`` (sorted)."""
    d = split_dir(root, split)
    if not d.is_dir():
        raise DatasetError(f"BOP split directory {d} does not exist")
    return sorted(int(p.name) for p in d.iterdir() if p.is_dir() and p.name.isdigit())


def iter_scene_images(root: str | Path, split: str, scene_ids: Iterable[int] | None = None) -> Iterator[ImageRecord]:
    """Every image of a split, scene by scene, with its camera and ground truth (m), each file checked
    (``bop.schema``) and against the others: ``scene_gt.json`` and ``scene_gt_info.json`` annotate images of
    ``scene_camera.json``, the same number of objects each. The images' size is camera.json's.

    ``scene_gt.json`` and ``scene_gt_info.json`` are optional (test images without annotations).
    """
    root = Path(root)
    cam = load_camera(root)
    for sid in (list_scenes(root, split) if scene_ids is None else scene_ids):
        sd = scene_dir(root, split, sid)
        cams = load_scene_camera(sd / "scene_camera.json")
        gts = load_scene_gt(sd / "scene_gt.json") if os.path.lexists(sd / "scene_gt.json") else {}
        infos = load_scene_gt_info(sd / "scene_gt_info.json") if os.path.lexists(sd / "scene_gt_info.json") else None
        for name, ims in (("scene_gt.json", gts), ("scene_gt_info.json", infos or {})):
            if extra := sorted(set(ims) - set(cams)):
                raise DatasetFileError(f"{sd / name}: image {extra[0]}: expected images of scene_camera.json "
                                       f"(it has no image {extra[0]})")
        for im_id in sorted(cams):
            gi = None if infos is None else infos.get(im_id, [])
            gt = gts.get(im_id, [])
            if gi is not None and len(gi) != len(gt):
                raise DatasetFileError(f"{sd / 'scene_gt_info.json'}: im {im_id}: expected {len(gt)} entries as in "
                                       f"scene_gt.json, got {len(gi)}")
            inst = [GTInstance(obj_id=o, T_cam_obj=T, gt_index=i, info=None if gi is None else gi[i])
                    for i, (o, T) in enumerate(gt)]
            yield ImageRecord(root=root, split=split, scene_id=sid, im_id=im_id, camera=cams[im_id], instances=inst,
                              size=(cam.width, cam.height))


# ---------------------------------------------------------------------------- writers

def pose_to_bop(T: np.ndarray) -> tuple[list[float], list[float]]:
    """BOP's row-major rotation (9 values) and translation (mm) of a 4x4 pose (m)."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, :3].reshape(-1).tolist(), (T[:3, 3] / MM).tolist()


def write_camera(root: str | Path, cam: Camera) -> Path:
    """Write ``<root>/camera.json``."""
    K = cam.K
    return pio.write_json(camera_path(root), {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "fx": float(K[0, 0]),
                                             "fy": float(K[1, 1]), "depth_scale": float(cam.depth_scale),
                                             "width": int(cam.width), "height": int(cam.height)})


def write_scene_gt(path: str | Path, gt: dict[int, list[tuple[int, np.ndarray]]]) -> Path:
    """Write ``scene_gt.json`` from {im_id: [(obj_id, T_cam_obj m), ...]} (translations in mm)."""
    out = {}
    for im_id, insts in sorted(gt.items()):
        rows = []
        for oid, T in insts:
            R, t = pose_to_bop(T)
            rows.append({"cam_R_m2c": R, "cam_t_m2c": t, "obj_id": int(oid)})
        out[str(im_id)] = rows
    return pio.write_json(path, out)


def write_scene_camera(path: str | Path, cams: dict[int, SceneCamera]) -> Path:
    """Write ``scene_camera.json`` from {im_id: SceneCamera} (T_cam_world translation in mm)."""
    out = {}
    for im_id, c in sorted(cams.items()):
        d: dict[str, Any] = {"cam_K": np.asarray(c.K, float).reshape(-1).tolist(), "depth_scale": float(c.depth_scale)}
        if c.T_cam_world is not None:
            d["cam_R_w2c"], d["cam_t_w2c"] = pose_to_bop(c.T_cam_world)
        out[str(im_id)] = d
    return pio.write_json(path, out)


def write_scene_gt_info(path: str | Path, infos: dict[int, list[GTInfo]]) -> Path:
    """Write ``scene_gt_info.json`` from {im_id: [GTInfo, ...]}."""
    out = {str(k): [{"bbox_obj": list(g.bbox_obj), "bbox_visib": list(g.bbox_visib), "px_count_all": g.px_count_all,
                     "px_count_valid": g.px_count_valid, "px_count_visib": g.px_count_visib,
                     "visib_fract": g.visib_fract} for g in v]
           for k, v in sorted(infos.items())}
    return pio.write_json(path, out)


def _extent(mask: np.ndarray, x0: int = 0, y0: int = 0) -> tuple[int, int, int, int] | None:
    """(x_min, y_min, x_max, y_max) px of a boolean mask's pixels, shifted by (x0, y0); None when empty."""
    x, y, w, h = cv2.boundingRect(np.ascontiguousarray(mask, dtype=np.uint8))  # of the non-zero pixels
    if w == 0:
        return None
    return x + x0, y + y0, x + w - 1 + x0, y + h - 1 + y0


def _box(extents: list[tuple[int, int, int, int] | None]) -> tuple[int, int, int, int]:
    """BOP box [x, y, w, h] (w = x_max - x_min, as bop_toolkit's ``calc_2d_bbox``) around extents; empty: -1s."""
    e = np.array([x for x in extents if x is not None]).reshape(-1, 4)
    if not len(e):
        return EMPTY_BOX
    x, y, x1, y1 = int(e[:, 0].min()), int(e[:, 1].min()), int(e[:, 2].max()), int(e[:, 3].max())
    return x, y, x1 - x, y1 - y


def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """BOP box [x, y, w, h] (px, w = x_max - x_min) of a boolean mask; ``EMPTY_BOX`` when it is empty."""
    return _box([_extent(mask)])


def gt_info_from_masks(mask: np.ndarray, mask_visib: np.ndarray, depth_m: np.ndarray,
                       box: tuple[int, int, int, int] | None = None, beyond_px: int = 0,
                       beyond_extent: tuple[int, int, int, int] | None = None) -> GTInfo:
    """GTInfo of one object from its full and visible masks in the image and the scene depth (m).

    bop_toolkit counts the whole silhouette, rendered on a canvas 3x the image's size: ``beyond_px`` are its
    pixels outside the image and ``beyond_extent`` their (x_min, y_min, x_max, y_max) in image pixel coordinates
    (may be negative), so ``px_count_all`` and ``bbox_obj`` are not clipped to the image. ``box`` [x0, x1) x
    [y0, y1) px, when given, holds the whole in-image full mask: the counts are then taken inside it (faster)
    if the visible mask lies inside it too.
    """
    x0 = y0 = 0
    if box is not None:
        bx0, by0, bx1, by1 = box
        sl = np.s_[by0:by1, bx0:bx1]
        if np.count_nonzero(mask_visib[sl]) == np.count_nonzero(mask_visib):
            x0, y0, mask, mask_visib, depth_m = bx0, by0, mask[sl], mask_visib[sl], depth_m[sl]
    n_all = int(np.count_nonzero(mask)) + int(beyond_px)
    n_visib = int(np.count_nonzero(mask_visib))
    return GTInfo(bbox_obj=_box([_extent(mask, x0, y0), beyond_extent]),
                  bbox_visib=_box([_extent(mask_visib, x0, y0)]), px_count_all=n_all,
                  px_count_valid=int(np.count_nonzero(mask & (depth_m > 0))), px_count_visib=n_visib,
                  visib_fract=float(n_visib / n_all) if n_all else 0.0)


@dataclass(frozen=True)
class EvalTarget:
    """One line of ``test_targets_bop19.json``: in image (scene_id, im_id), ``inst_count`` instances of obj_id."""

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


def targets_from_gt(records: Iterable[ImageRecord], min_visib: float = MIN_TARGET_VISIB) -> list[EvalTarget]:
    """BOP 2019 targets: per image and object, its instances with visib_fract >= ``min_visib`` (none: no line)."""
    out = []
    for r in records:
        n = Counter(g.obj_id for g in r.instances if g.info is not None and g.info.visib_fract >= min_visib)
        out += [EvalTarget(r.scene_id, r.im_id, o, c) for o, c in sorted(n.items())]
    return out


def write_test_targets(root: str | Path, targets: Iterable[EvalTarget]) -> Path:
    """Write ``<root>/test_targets_bop19.json`` (BOP's key order, sorted by scene, image and object)."""
    rows = [{"im_id": t.im_id, "inst_count": t.inst_count, "obj_id": t.obj_id, "scene_id": t.scene_id}
            for t in sorted(targets, key=lambda t: (t.scene_id, t.im_id, t.obj_id))]
    return pio.write_json(targets_path(root), rows)


def load_test_targets(root: str | Path) -> list[EvalTarget] | None:
    """``<root>/test_targets_bop19.json`` as EvalTargets, or None when the dataset has no such file."""
    p = targets_path(root)
    return [EvalTarget(*t) for t in bop_schema.targets(p)] if os.path.lexists(p) else None
