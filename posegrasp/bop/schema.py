"""What each BOP JSON file must hold: strict readers that return its values checked for shape, type, finiteness
and range, in the file's own units (mm, px), or raise ``DatasetFileError`` naming the file, the key and what was
expected. ``posegrasp.bop`` builds its records (in metres) from them; nothing else parses a BOP JSON file.

JSON is read as UTF-8 without NaN or Infinity; ids are JSON object keys of decimal digits or integers.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Callable

import numpy as np

from posegrasp import inputs
from posegrasp.errors import DatasetFileError

#: Largest length (mm) any BOP file may hold: a model diameter, a translation, a box size (100 m).
MAX_MM = 1e5
#: Largest image side (px) and focal length (px) accepted.
MAX_PX = 100_000
#: Largest id (object, scene, image) and per-image instance count accepted.
MAX_ID = 999_999
MAX_INSTANCES = 10_000
#: A model's diameter (mm) must lie in [MIN_DIAMETER, MAX_MM]; below it the file is most likely in metres.
MIN_DIAMETER = 1.0


def _short(v: Any) -> str:
    """A value as the error message shows it: its repr, cut at 60 characters; null for None."""
    s = "null" if v is None else repr(v)
    return s if len(s) <= 60 else s[:57] + "..."


def fail(path: Path, key: str, expected: str, got: Any = ...) -> DatasetFileError:
    """The error for ``path`` at ``key`` (empty: the whole file): ``expected`` (and what it holds instead)."""
    return DatasetFileError(f"{path}: {key + ': ' if key else ''}expected {expected}"
                            + ("" if got is ... else f", got {_short(got)}"))


def read_json(path: str | Path) -> Any:
    """The parsed JSON of ``path`` (``posegrasp.inputs.read_json``: a bounded regular file of UTF-8 text, no NaN,
    Infinity or duplicate key)."""
    path = Path(path)
    if not os.path.lexists(path):
        raise fail(path, "", "a file (it does not exist)")
    return inputs.read_json(path, DatasetFileError)


# ---------------------------------------------------------------------------- values

def obj(v: Any, path: Path, key: str, what: str = "a JSON object") -> dict[str, Any]:
    """``v`` if it is a JSON object."""
    if not isinstance(v, dict):
        raise fail(path, key, what, v)
    return v


def get(d: dict[str, Any], k: str, path: Path, key: str) -> Any:
    """``d[k]``; a missing key is an error at ``key``."""
    if k not in d:
        raise fail(path, key, f"a key '{k}'", "none")
    return d[k]


def num(v: Any, path: Path, key: str, lo: float = -math.inf, hi: float = math.inf, lo_open: bool = False) -> float:
    """``v`` as a finite float in [lo, hi] (``lo_open``: (lo, hi])."""
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) \
        and (v > lo if lo_open else v >= lo) and v <= hi
    if not ok:
        rng = "" if (lo, hi) == (-math.inf, math.inf) else f" in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise fail(path, key, f"a finite number{rng}", v)
    return float(v)


def integer(v: Any, path: Path, key: str, lo: int, hi: int) -> int:
    """``v`` as an int in [lo, hi] (a float with an integer value is accepted)."""
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v == int(v) and lo <= v <= hi
    if not ok:
        raise fail(path, key, f"an integer in [{lo}, {hi}]", v)
    return int(v)


def nums(v: Any, n: int, path: Path, key: str, bound: float = math.inf) -> np.ndarray:
    """``v`` as a float64 array of ``n`` finite numbers of magnitude at most ``bound``."""
    if not (isinstance(v, list) and len(v) == n and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and abs(x) <= bound
            for x in v)):
        rng = "" if bound == math.inf else f" within +-{bound:g}"
        raise fail(path, key, f"a list of {n} finite numbers{rng}", v)
    return np.asarray(v, dtype=np.float64)


def id_key(k: str, path: Path, key: str) -> int:
    """A JSON object key naming an id: decimal digits, at most ``MAX_ID``."""
    if not (k.isascii() and k.isdigit() and int(k) <= MAX_ID):
        raise fail(path, key, f"keys that are integer ids in [0, {MAX_ID}]", k)
    return int(k)


def by_id(data: Any, path: Path, what: str) -> dict[int, Any]:
    """A JSON object keyed by ids (``what``: image, obj) as {id: value}."""
    d = obj(data, path, "", f"a JSON object keyed by {what} id")
    out = {id_key(k, path, f"{what} {k}"): v for k, v in d.items()}
    if len(out) != len(d):
        keys = sorted(d, key=lambda k: (int(k), k))
        dup = next(b for a, b in zip(keys, keys[1:]) if int(a) == int(b))
        raise fail(path, f"{what} {dup}", f"one key per {what} id ({dup!r} names the id of another key)")
    return out


def entries(v: Any, path: Path, key: str) -> list[Any]:
    """``v`` if it is a JSON list of at most ``MAX_INSTANCES`` entries."""
    if not isinstance(v, list) or len(v) > MAX_INSTANCES:
        raise fail(path, key, f"a list of at most {MAX_INSTANCES} entries", v)
    return v


def intrinsics(K: np.ndarray, path: Path, key: str) -> np.ndarray:
    """A 3x3 camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy in (0, MAX_PX]."""
    K = K.reshape(3, 3)
    if not (0 < K[0, 0] <= MAX_PX and 0 < K[1, 1] <= MAX_PX and np.array_equal(K[2], [0, 0, 1]) and K[1, 0] == 0):
        raise fail(path, key, f"[fx, 0, cx, 0, fy, cy, 0, 0, 1] with fx, fy in (0, {MAX_PX}]", K.reshape(-1).tolist())
    return K


# ---------------------------------------------------------------------------- files

def camera(path: str | Path) -> dict[str, Any]:
    """``camera.json``: width, height (px), K (3, 3) px and depth_scale (png value x scale = mm; default 1)."""
    path = Path(path)
    d = obj(read_json(path), path, "")
    out: dict[str, Any] = {k: integer(get(d, k, path, ""), path, f"'{k}'", 1, MAX_PX) for k in ("width", "height")}
    f = {k: num(get(d, k, path, ""), path, f"'{k}'", 0.0, MAX_PX, lo_open=True) for k in ("fx", "fy")}
    c = {k: num(get(d, k, path, ""), path, f"'{k}'", -MAX_PX, MAX_PX) for k in ("cx", "cy")}
    out["K"] = np.array([[f["fx"], 0.0, c["cx"]], [0.0, f["fy"], c["cy"]], [0.0, 0.0, 1.0]])
    out["depth_scale"] = num(d.get("depth_scale", 1.0), path, "'depth_scale'", 0.0, 1e3, lo_open=True)
    return out


def scene_camera(path: str | Path) -> dict[int, dict[str, Any]]:
    """``scene_camera.json`` -> {im_id: {"K": (3, 3), "depth_scale", "R_w2c": (3, 3) | None, "t_w2c": (3,) mm | None}}."""
    path = Path(path)
    out = {}
    for im, v in by_id(read_json(path), path, "image").items():
        key = f"im {im}"
        v = obj(v, path, key)
        K = intrinsics(nums(get(v, "cam_K", path, key), 9, path, f"{key} 'cam_K'", MAX_PX), path, f"{key} 'cam_K'")
        scale = num(v.get("depth_scale", 1.0), path, f"{key} 'depth_scale'", 0.0, 1e3, lo_open=True)
        if ("cam_R_w2c" in v) != ("cam_t_w2c" in v):
            raise fail(path, key, "both 'cam_R_w2c' and 'cam_t_w2c', or neither", sorted(v))
        R = nums(v["cam_R_w2c"], 9, path, f"{key} 'cam_R_w2c'", 2.0).reshape(3, 3) if "cam_R_w2c" in v else None
        t = nums(v["cam_t_w2c"], 3, path, f"{key} 'cam_t_w2c'", MAX_MM) if "cam_t_w2c" in v else None
        out[im] = {"K": K, "depth_scale": scale, "R_w2c": R, "t_w2c": t}
    return out


def _per_image(path: Path, row: Callable[[dict, str], Any]) -> dict[int, list[Any]]:
    """{im_id: [row(entry, key), ...]} of a per-image list file (``scene_gt``, ``scene_gt_info``), ``key`` naming
    the entry in messages ("im 3 gt 1")."""
    out = {}
    for im, v in by_id(read_json(path), path, "image").items():
        out[im] = [row(obj(g, path, f"im {im} gt {i}"), f"im {im} gt {i}")
                   for i, g in enumerate(entries(v, path, f"im {im}"))]
    return out


def scene_gt(path: str | Path) -> dict[int, list[tuple[int, np.ndarray, np.ndarray]]]:
    """``scene_gt.json`` -> {im_id: [(obj_id, R_m2c (3, 3), t_m2c (3,) mm), ...]} in annotation order."""
    path = Path(path)
    return _per_image(path, lambda g, key: (
        integer(get(g, "obj_id", path, key), path, f"{key} 'obj_id'", 0, MAX_ID),
        nums(get(g, "cam_R_m2c", path, key), 9, path, f"{key} 'cam_R_m2c'", 2.0).reshape(3, 3),
        nums(get(g, "cam_t_m2c", path, key), 3, path, f"{key} 'cam_t_m2c'", MAX_MM)))


def scene_gt_info(path: str | Path) -> dict[int, list[dict[str, Any]]]:
    """``scene_gt_info.json`` -> {im_id: [{bbox_obj, bbox_visib (4 ints), px_count_* (ints >= 0), visib_fract
    in [0, 1]}, ...]} in annotation order."""
    path = Path(path)

    def row(g: dict, key: str) -> dict[str, Any]:
        r: dict[str, Any] = {}
        for k in ("bbox_obj", "bbox_visib"):
            box = nums(get(g, k, path, key), 4, path, f"{key} '{k}'", 3 * MAX_PX)
            if not np.array_equal(box, np.round(box)) or (box[2:] < -1).any():
                raise fail(path, f"{key} '{k}'", "[x, y, w, h] integers with w, h >= 0 (or all -1)", g[k])
            r[k] = tuple(int(x) for x in box)
        for k in ("px_count_all", "px_count_valid", "px_count_visib"):
            r[k] = integer(get(g, k, path, key), path, f"{key} '{k}'", 0, 9 * MAX_PX ** 2)
        r["visib_fract"] = num(get(g, "visib_fract", path, key), path, f"{key} 'visib_fract'", 0.0, 1.0)
        return r

    return _per_image(path, row)


def targets(path: str | Path) -> list[tuple[int, int, int, int]]:
    """``test_targets_bop19.json`` -> [(scene_id, im_id, obj_id, inst_count), ...]; each (scene, image, object)
    once, inst_count in [1, MAX_INSTANCES]."""
    path = Path(path)
    rows = read_json(path)
    if not isinstance(rows, list):
        raise fail(path, "", "a JSON list of targets", rows)
    out, seen = [], set()
    for i, t in enumerate(rows):
        key = f"entry {i}"
        t = obj(t, path, key)
        ids = tuple(integer(get(t, k, path, key), path, f"{key} '{k}'", 0, MAX_ID) for k in ("scene_id", "im_id", "obj_id"))
        if ids in seen:
            raise fail(path, key, "each (scene_id, im_id, obj_id) once", dict(zip(("scene_id", "im_id", "obj_id"), ids)))
        seen.add(ids)
        out.append((*ids, integer(get(t, "inst_count", path, key), path, f"{key} 'inst_count'", 1, MAX_INSTANCES)))
    return out


def models_info(path: str | Path) -> dict[int, dict[str, Any]]:
    """``models_info.json`` -> {obj_id: {"diameter" mm, "min" (3,) mm, "size" (3,) mm, "symmetries_discrete": [(4, 4)
    mm], "symmetries_continuous": [(axis (3,), offset (3,) mm)]}}, sorted by obj_id; at least one object."""
    path = Path(path)
    data = by_id(read_json(path), path, "obj")
    if not data:
        raise fail(path, "", "at least one object", {})
    out = {}
    for oid, d in sorted(data.items()):
        key = f"obj {oid}"
        d = obj(d, path, key)
        diameter = get(d, "diameter", path, key)
        if isinstance(diameter, (int, float)) and 0 < diameter < MIN_DIAMETER:
            raise fail(path, f"{key} 'diameter'", f"millimetres, at least {MIN_DIAMETER:g} (this looks like metres)",
                       diameter)
        r: dict[str, Any] = {"diameter": num(diameter, path, f"{key} 'diameter'", MIN_DIAMETER, MAX_MM)}
        r["min"] = np.array([num(get(d, f"min_{a}", path, key), path, f"{key} 'min_{a}'", -MAX_MM, MAX_MM) for a in "xyz"])
        r["size"] = np.array([num(get(d, f"size_{a}", path, key), path, f"{key} 'size_{a}'", 0.0, MAX_MM) for a in "xyz"])
        sd = d.get("symmetries_discrete", [])
        r["symmetries_discrete"] = [
            nums(s, 16, path, f"{key} 'symmetries_discrete'[{j}]", MAX_MM).reshape(4, 4)
            for j, s in enumerate(entries(sd, path, f"{key} 'symmetries_discrete'"))]
        cont = []
        for j, s in enumerate(entries(d.get("symmetries_continuous", []), path, f"{key} 'symmetries_continuous'")):
            k = f"{key} 'symmetries_continuous'[{j}]"
            s = obj(s, path, k)
            axis = nums(get(s, "axis", path, k), 3, path, f"{k} 'axis'", MAX_MM)
            if not np.linalg.norm(axis) > 0:
                raise fail(path, f"{k} 'axis'", "a non-zero vector", s["axis"])
            cont.append((axis, nums(s.get("offset", [0, 0, 0]), 3, path, f"{k} 'offset'", MAX_MM)))
        r["symmetries_continuous"] = cont
        out[oid] = r
    return out
