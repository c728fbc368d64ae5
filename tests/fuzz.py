"""A seeded mutation fuzzer for every file the ``posegrasp`` commands read.

A small corpus is built once (``build_corpus``): a BOP dataset (``ds``), the shipped weights (``wts``), a trials run
folder (``run``, and an untouched twin ``run2`` to compare with), an object set (``objs``), the TOML settings given
with ``--config`` (``cfg``) and a BOP results CSV (``res.csv``). A case (``Case``) mutates one file of it (truncated,
emptied, binary garbage, a JSON value at any depth replaced by another shape or type, NaN/inf, huge or negative,
a key deleted, an image of the wrong size, bit depth or channels, a PLY without faces, NaN weights, ...) in a copy of
the corpus and runs one command that reads that file, in a child process under a time limit (``tests/zygote.py``
forks it from a process that imported the command line once). The verdict (``judge``):

- exit non-zero: exactly one stderr line and no traceback;
- exit zero: no traceback; the scores written within their ranges; and no "false OK": a mutation that surely breaks a
  file the command reads (``Mutation.bad``) is refused, and ``dataset check`` accepts what ``eval`` scored or
  ``train`` trained on;
- no hang (the time limit), and every file that existed before the command is as it was (a trials resume and
  ``report`` may rewrite the run's report and summary).

Cases are drawn from a fixed seed, so a case number always names the same file, mutation and command.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import io
import json
import math
import os
import random
import shutil
import threading
import tomllib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable

import numpy as np
from zygote import Outcome, Zygote


# -- the corpus ---------------------------------------------------------------------------------------------------

TRAIN_TOML = """\
[seg]
batch_size = 2
log_every = 1
lr = 0.01
[seg.model]
input_size = [48, 64]
[pose]
batch_size = 2
log_every = 1
[cls]
batch_size = 4
log_every = 1
"""
EVAL_TOML = """\
[eval]
min_visib_fract = 0.1
min_valid_points = 50
refiner_iterations = -1
depth_fit = true
"""
TRIAL_TOML = """\
min_blocks = 1
max_blocks = 2
sleep = true
[control]
dt = 0.04
speed = 0.4
pos_tol = 0.004
[firm_hold]
finger_wait = 10
"""
DATAGEN_TOML = """\
min_spacing = 0.03
blocks = [1, 2]
[workcell.hand_camera]
width = 64
fovy_deg = 45.0
"""
RESULTS_CSV = "scene_id,im_id,obj_id,score,R,t,time\n0,0,1,0.9,1 0 0 0 1 0 0 0 1,0 0 400,0.1\n"

SMALL = ["--workers", "1", "--no-progress"]


def build_corpus(root: Path, run: Callable[[list[str], Path], Outcome]) -> Path:
    """Write the corpus under ``root``/base (see the module docstring); ``run(argv, cwd)`` runs a command."""
    import trimesh

    from posegrasp import ASSETS

    base = root / "base"
    base.mkdir(parents=True)
    cfg = base / "cfg"
    cfg.mkdir()
    for name, text in (("train", TRAIN_TOML), ("eval", EVAL_TOML), ("trial", TRIAL_TOML), ("datagen", DATAGEN_TOML)):
        (cfg / f"{name}.toml").write_text(text)
    steps = [
        ["datagen", "--out", "ds", "--scenes", "2", "--views", "2", "--resolution", "64x48", "--blocks", "2", *SMALL],
        ["datagen", "--out", "ds", "--split", "test", "--scenes", "1", "--views", "2", "--resolution", "64x48",
         "--blocks", "2", *SMALL],
        ["trials", "--episodes", "2", "--seed", "0", "--perception", "oracle", "--out", "run", *SMALL],
        ["train", "seg", "--data", "ds", "--out", "trun", "--config", "cfg/train.toml", "--steps", "1",
         "--no-progress"],
    ]
    meshes = base / "meshes"
    meshes.mkdir()
    trimesh.creation.box(extents=(0.04, 0.03, 0.02)).export(meshes / "box.stl")
    trimesh.creation.cylinder(radius=0.015, height=0.05, sections=16).export(meshes / "cyl.ply")
    steps.append(["objects", "import", "meshes/box.stl", "meshes/cyl.ply", "--out", "objs", "--unit", "m",
                  "--no-progress"])
    for argv in steps:
        o = run(argv, base)
        assert o.rc == 0, (argv, o.stderr)
    shutil.rmtree(meshes)
    shutil.copytree(base / "run", base / "run2")
    shutil.copytree(ASSETS / "perception" / "model", base / "wts")
    (base / "res.csv").write_text(RESULTS_CSV)
    return base


# -- commands -----------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Command:
    """One reading command: its argv (``{out}`` is a fresh folder), whether it is slow, the file kinds it reads."""

    name: str
    argv: tuple[str, ...]
    heavy: bool
    kinds: tuple[str, ...]
    #: Scores or says OK: a success on data ``dataset check`` rejects is a false OK.
    vouches: bool = True
    #: Files a success may rewrite.
    may_rewrite: tuple[str, ...] = ()
    #: Files a success may append to (their complete lines kept as they were; a torn last line may go).
    may_append: tuple[str, ...] = ()


DS = ("bop_json", "camera_json", "models_info", "test_targets", "rgb", "depth", "mask", "model_ply", "datagen_json")
TRAIN_ARGS = ("--data", "ds", "--out", "{out}/t", "--config", "cfg/train.toml", "--steps", "1", "--no-progress")
TRIAL_ARGS = ("--episodes", "1", "--seed", "0", "--workers", "1", "--no-progress", "--out", "{out}/tr")
COMMANDS = [
    Command("check", ("dataset", "check", "ds"), False, DS),
    Command("show", ("dataset", "show", "ds", "--split", "{split}", "--scene", "{scene}", "--im", "{im}",
                     "--out", "{out}/v.png"), False, DS, vouches=False),
    Command("train-seg", ("train", "seg", *TRAIN_ARGS), True, DS + ("train_toml",)),
    Command("train-pose", ("train", "pose", *TRAIN_ARGS), True, DS + ("train_toml",)),
    Command("train-cls", ("train", "cls", *TRAIN_ARGS), True, DS + ("train_toml",)),
    Command("eval", ("eval", "--data", "ds", "--weights", "wts", "--out", "{out}/ev", "--config", "cfg/eval.toml",
                     "--max-images", "2", "--threads", "1", "--no-progress"), True,
            DS + ("weights_config", "safetensors", "eval_toml")),
    Command("perturb", ("perturb", "--weights", "wts", "--out", "{out}/p", "--rel-sigma", "0.01"), False,
            ("weights_config", "safetensors")),
    Command("trials-model", ("trials", "--perception", "model:wts", *TRIAL_ARGS), True,
            ("weights_config", "safetensors")),
    Command("train-resume", ("train", "seg", "--data", "ds", "--out", "trun", "--config", "cfg/train.toml", "--steps",
                             "2", "--resume", "--no-progress"), True,
            ("weights_config", "safetensors", "weights_state", "metrics_csv"),
            may_rewrite=("trun/seg/model.safetensors", "trun/seg/optimizer.safetensors", "trun/seg/state.json",
                         "trun/seg/config.json"), may_append=("trun/seg_metrics.csv",)),
    Command("trials-resume", ("trials", "--episodes", "2", "--seed", "0", "--perception", "oracle", "--out", "run",
                              "--workers", "1", "--no-progress"), False,
            ("campaign_json", "summary_json", "episodes", "timings"),
            may_rewrite=("run/report.html", "run/summary.json", "run/timings.jsonl"),  # a rerun's timings differ
            may_append=("run/episodes.jsonl",)),
    Command("report", ("report", "run"), False, ("campaign_json", "summary_json", "episodes", "timings"),
            vouches=False, may_rewrite=("run/report.html",)),
    Command("compare", ("compare", "run2", "run", "--out", "{out}/cmp.json"), False, ("campaign_json", "episodes")),
    Command("objects-show", ("objects", "show", "objs", "--out", "{out}/o.png"), False,
            ("objset_json", "object_json", "objset_ply", "objset_info"), vouches=False),
    Command("trials-objects", ("trials", "--objects", "objs", "--perception", "oracle", *TRIAL_ARGS), True,
            ("objset_json", "object_json", "objset_ply", "objset_info")),
    Command("datagen-objects", ("datagen", "--out", "{out}/d", "--objects", "objs", "--scenes", "1", "--views", "1",
                                "--resolution", "64x48", "--blocks", "1", *SMALL), False,
            ("objset_json", "object_json", "objset_ply", "objset_info")),
    Command("trials-config", ("trials", "--config", "cfg/trial.toml", "--perception", "oracle", *TRIAL_ARGS), True,
            ("trial_toml",)),
    Command("datagen-config", ("datagen", "--out", "{out}/d", "--config", "cfg/datagen.toml", "--scenes", "1",
                               "--views", "1", "--resolution", "64x48", *SMALL), False, ("datagen_toml",)),
    Command("trials-csv", ("trials", "--perception", "bop-csv:res.csv", *TRIAL_ARGS), True, ("results_csv",)),
]
BY_NAME = {c.name: c for c in COMMANDS}


def file_kind(rel: str) -> str | None:
    """The kind of the corpus file ``rel`` (a path below the corpus root), None for files no command reads."""
    p = Path(rel)
    top, name, parent = p.parts[0], p.name, p.parent.name
    if top == "ds":
        if name == "camera.json":
            return "camera_json"
        if name == "models_info.json":
            return "models_info"
        if name.startswith("test_targets"):
            return "test_targets"
        if name in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"):
            return "bop_json"
        if name.endswith(".json"):
            return "datagen_json"
        if p.suffix == ".ply":
            return "model_ply"
        return {"rgb": "rgb", "depth": "depth", "mask": "mask", "mask_visib": "mask"}.get(parent)
    if top in ("wts", "trun"):
        return {"config.json": "weights_config", "model.safetensors": "safetensors", "state.json": "weights_state",
                "optimizer.safetensors": "safetensors", "seg_metrics.csv": "metrics_csv"}.get(name)
    if top == "run":
        return {"campaign.json": "campaign_json", "summary.json": "summary_json", "episodes.jsonl": "episodes",
                "timings.jsonl": "timings"}.get(name)
    if top == "objs":
        if name == "objectset.json":
            return "objset_json"
        if name == "models_info.json":
            return "objset_info"
        return {"objects": "object_json", "models": "objset_ply"}.get(parent)
    if top == "cfg":
        return f"{p.stem}_toml"
    if name == "res.csv":
        return "results_csv"
    return None


def reads(cmd: Command, rel: str) -> bool:
    """Whether ``cmd`` reads the corpus file ``rel`` (a dataset's split files only by the commands of that split)."""
    p = Path(rel)
    if cmd.name == "perturb":  # the stages it perturbs (pose); it copies the others as they are
        return p.parts[:2] == ("wts", "pose")
    if p.parts[0] in ("wts", "trun"):
        return (p.parts[0] == "trun") == (cmd.name == "train-resume")
    if p.parts[0] == "ds" and len(p.parts) > 2 and p.parts[1] in ("train_pbr", "test"):
        if cmd.name.startswith("train"):
            return p.parts[1] == "train_pbr"
        if cmd.name == "eval":
            return p.parts[1] == "test"
    if cmd.name.startswith("train") and (p.parts[1:2] == ("models_eval",) or "test_targets" in p.name):
        return False
    if cmd.name == "eval" and rel == "ds/models_eval/models_info.json":  # for bop_toolkit; eval reads models/'s
        return False
    if cmd.name == "train-seg" and p.parent.name == "mask":  # seg trains on the visible masks
        return False
    return True


#: Kinds whose every value has one type (a number in place of a string is as wrong as a list in place of a table).
TYPED = {"bop_json", "camera_json", "models_info", "test_targets", "object_json", "objset_json", "campaign_json",
         "episodes", "weights_state"}
#: Kinds derived from others or only informative: a success after their mutation is no false OK.
UNVOUCHED = {"datagen_json", "summary_json", "timings", "metrics_csv"}

# -- mutations ----------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class Mutation:
    """What was done to the file (one line) and whether it surely leaves the file invalid."""

    what: str
    data: bytes
    bad: bool


def _walk_pick(rng: random.Random, doc: Any) -> list:
    """A random path into ``doc`` (keys and indices), stopping at each level with probability 0.35."""
    path: list = []
    node = doc
    while isinstance(node, (dict, list)) and node and rng.random() > 0.35:
        key = rng.choice(sorted(node, key=str)) if isinstance(node, dict) else rng.randrange(len(node))
        path.append(key)
        node = node[key]
    return path


VALUE_OPS = ("null", "list", "str", "number", "dict", "bool", "nan", "inf", "-inf", "huge", "negative", "delete",
             "bigint", "zero")


def _replacement(op: str, old: Any) -> Any:
    num = isinstance(old, (int, float)) and not isinstance(old, bool)
    return {"null": None, "list": [1, "x"], "str": "x", "number": 7, "dict": {"x": 1}, "bool": True,
            "nan": float("nan"), "inf": float("inf"), "-inf": float("-inf"),
            "huge": (old * 1e300 if num and old else 1e300), "negative": (-abs(old) - 1 if num else -1),
            "bigint": 10**12, "zero": 0}[op]


def _type(v: Any) -> str:
    return "number" if isinstance(v, (int, float)) and not isinstance(v, bool) else type(v).__name__


def _surely_bad(op: str, old: Any, typed: bool, root: bool = False) -> bool:
    """A replacement that no reader may accept: NaN/inf anywhere, a container swapped for another shape, or (in a
    ``typed`` file, one whose every value has a fixed type) a value of another type; null only as the whole file
    (elsewhere it may be an optional value's "none")."""
    if op in ("nan", "inf", "-inf"):
        return True
    if op == "delete" or (op == "null" and not root):
        return False
    new = _replacement(op, old)
    if isinstance(old, (dict, list)):
        return _type(new) != _type(old)
    return typed and _type(new) != _type(old)


def mutate_doc(rng: random.Random, doc: Any, allow_null: bool = True, typed: bool = False) -> tuple[Any, str, bool]:
    """``doc`` with one value at a random depth replaced (or its key deleted): (new doc, description, surely bad)."""
    doc = copy.deepcopy(doc)
    path = _walk_pick(rng, doc)
    ops = [o for o in VALUE_OPS if allow_null or o != "null"]
    op = rng.choice(ops if path else [o for o in ops if o != "delete"])
    if not path:
        old = doc
        return _replacement(op, old), f"root -> {op}", _surely_bad(op, old, typed, root=True)
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    old = parent[path[-1]]
    where = "/".join(map(str, path))
    if op == "delete":
        del parent[path[-1]]
        return doc, f"{where} deleted", False
    parent[path[-1]] = _replacement(op, old)
    return doc, f"{where} -> {op}", _surely_bad(op, old, typed)


def _bytes_op(rng: random.Random, data: bytes) -> Mutation | None:
    """Truncation, emptying or garbage, each a sure break (None: pick a content mutation instead)."""
    r = rng.random()
    if r < 0.12:
        n = rng.randrange(1, max(2, len(data) - 1))
        return Mutation(f"truncated to {n} of {len(data)} bytes", data[:n], True)
    if r < 0.18:
        return Mutation("empty file", b"", True)
    if r < 0.26:
        g = bytes(rng.randrange(256) for _ in range(rng.choice([1, 16, 600])))
        return Mutation(f"{len(g)} bytes of binary garbage", g, True)
    return None


def _json_dumps(doc: Any) -> bytes:
    return json.dumps(doc, indent=1).encode()


def mutate_json(rng: random.Random, data: bytes, typed: bool) -> Mutation:
    m = _bytes_op(rng, data)
    if m:
        return m
    doc, what, bad = mutate_doc(rng, json.loads(data), typed=typed)
    return Mutation(what, _json_dumps(doc), bad)


def mutate_jsonl(rng: random.Random, data: bytes, typed: bool) -> Mutation:
    lines = data.decode().splitlines()
    r = rng.random()
    if r < 0.1:
        cut = rng.randrange(1, len(data) - 1)
        return Mutation(f"truncated to {cut} bytes", data[:cut], False)  # a torn last line: what a kill leaves
    if r < 0.18:
        i = rng.randrange(len(lines))
        lines.insert(i, "\x00\xff garbage")
        return Mutation(f"garbage line before line {i + 1}", ("\n".join(lines) + "\n").encode("utf-8", "replace"), True)
    i = rng.randrange(len(lines))
    doc, what, bad = mutate_doc(rng, json.loads(lines[i]), typed=typed)
    lines[i] = json.dumps(doc, separators=(",", ":"), sort_keys=True)  # as the product writes records
    return Mutation(f"line {i + 1}: {what}", ("\n".join(lines) + "\n").encode(), bad)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(v)


def dump_toml(doc: dict, prefix: str = "") -> str:
    """A TOML text of ``doc`` (tables as ``[a.b]`` sections, inline tables inside arrays)."""
    out = [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for k, v in doc.items():
        if isinstance(v, dict):
            name = f"{prefix}.{json.dumps(k)}" if prefix else json.dumps(k)
            out.append(f"[{name}]")
            out.append(dump_toml(v, name))
    return "\n".join(out) + "\n"


def mutate_toml(rng: random.Random, data: bytes) -> Mutation:
    m = _bytes_op(rng, data)
    if m:
        if m.what.startswith("truncated"):  # a cut at a line end may leave valid TOML
            m.bad = not data[: len(m.data)].endswith(b"\n")
        if m.what == "empty file":  # no settings: the defaults
            m.bad = False
        return m
    doc = tomllib.loads(data.decode())
    for _ in range(20):
        new, what, bad = mutate_doc(rng, doc, allow_null=False, typed=True)
        if isinstance(new, dict):
            break
    else:
        return Mutation("empty settings", b"", False)
    return Mutation(what, dump_toml(new).encode(), bad)


def mutate_csv(rng: random.Random, data: bytes) -> Mutation:
    m = _bytes_op(rng, data)
    if m:
        m.bad = m.what != "empty file" and not (m.what.startswith("truncated") and data[:len(m.data)].endswith(b"\n"))
        return m
    rows = [line.split(",") for line in data.decode().splitlines()]
    r = rng.random()
    if r < 0.2:
        j = rng.randrange(len(rows[0]))
        for row in rows:
            del row[j]
        return Mutation(f"column {j} removed", ("\n".join(",".join(r) for r in rows) + "\n").encode(), True)
    i, j = rng.randrange(1, len(rows)), rng.randrange(len(rows[0]))
    val = rng.choice(["nan", "inf", "-1", "1e300", "x", "", "1.5"])
    cell = rows[i][j].split(" ")
    k = rng.randrange(len(cell))
    cell[k] = val
    rows[i][j] = " ".join(cell)
    bad = val in ("nan", "inf", "x", "", "1e300") or (j in (0, 1, 2) and val in ("-1", "1.5")) \
        or (j == 4 and val != "1.5")
    return Mutation(f"row {i} field {j} -> {val!r}", ("\n".join(",".join(r) for r in rows) + "\n").encode(), bad)


def mutate_image(rng: random.Random, data: bytes, kind: str, suffix: str) -> Mutation:
    from PIL import Image

    m = _bytes_op(rng, data)
    if m:
        return m
    im = np.asarray(Image.open(io.BytesIO(data)))
    op = rng.choice(["resize", "channels", "bitdepth", "zeros", "white", "halfjpeg"])
    if op == "halfjpeg":
        return Mutation("cut in half", data[: len(data) // 2], True)
    if op == "resize":
        h, w = im.shape[:2]
        h2, w2 = rng.choice([(h + 16, w), (h, w - 16), (w, h), (1, 1)])
        out = np.resize(im, (h2, w2, *im.shape[2:]))
        what, bad = f"resized to {w2}x{h2}", True
    elif op == "channels":
        out = np.dstack([im] * 3) if im.ndim == 2 else im[..., 0]
        if im.ndim == 3 and rng.random() < 0.5:
            out = np.dstack([im, np.full(im.shape[:2], 255, im.dtype)])
        what, bad = f"{im.ndim == 2 and 'grey to RGB' or 'channels changed'} ({out.shape})", kind != "rgb" or \
            out.ndim == 2 or out.shape[2] == 4
        if kind == "rgb" and out.ndim == 3 and out.shape[2] == 4:
            bad = False  # RGBA photos are read as RGB
    elif op == "bitdepth":
        out = (im // 256).astype(np.uint8) if im.dtype == np.uint16 else im.astype(np.uint16) * 257
        what, bad = f"{im.dtype} -> {out.dtype}", True
    elif op == "zeros":
        out = np.zeros_like(im)
        what, bad = "all zero", kind == "depth"
    else:
        out = np.full_like(im, np.iinfo(im.dtype).max)
        what, bad = "all white", kind in ("mask", "depth")
    import cv2

    ext = ".jpg" if suffix == ".jpg" else ".png"
    if ext == ".jpg" and (out.dtype != np.uint8 or (out.ndim == 3 and out.shape[2] == 4)):
        ext = ".png"  # PNG bytes under the .jpg name: readers go by the content
    return Mutation(what, cv2.imencode(ext, out)[1].tobytes(), bad)


def mutate_ply(rng: random.Random, data: bytes) -> Mutation:
    import trimesh

    m = _bytes_op(rng, data)
    if m:
        return m
    mesh = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    op = rng.choice(["nofaces", "nan", "scale", "header", "degenerate"])
    if op == "nofaces":
        return Mutation("no faces", trimesh.PointCloud(mesh.vertices).export(file_type="ply"), True)
    if op == "header":
        head, sep, body = data.partition(b"end_header\n")
        lines = head.split(b"\n")
        i = next(k for k, line in enumerate(lines) if line.startswith(b"element vertex"))
        n = int(lines[i].split()[-1])
        lines[i] = b"element vertex %d" % (n * 3 + 7)
        return Mutation("vertex count in the header too large", b"\n".join(lines) + sep + body, True)
    v = np.array(mesh.vertices, dtype=np.float64)
    if op == "nan":
        v[rng.randrange(len(v))] = np.nan
        what, bad = "a vertex NaN", True
    elif op == "scale":
        v *= rng.choice([1e-3, 1e3, 1e6])
        what, bad = "scaled", False
    else:
        v[:] = v[0]
        what, bad = "every vertex at one point", True
    return Mutation(what, trimesh.Trimesh(v, mesh.faces, process=False).export(file_type="ply"), bad)


def mutate_safetensors(rng: random.Random, data: bytes) -> Mutation:
    m = _bytes_op(rng, data)
    if m:
        return m
    n = int.from_bytes(data[:8], "little")
    header = json.loads(data[8:8 + n])
    op = rng.choice(["nan", "header", "drop", "inf"])
    if op == "header":
        doc, what, bad = mutate_doc(rng, header)
        h = json.dumps(doc).encode()
        return Mutation(f"header {what}", len(h).to_bytes(8, "little") + h + data[8 + n:], bad)
    from safetensors.numpy import load, save

    tensors = load(data)
    names = sorted(k for k, t in tensors.items() if t.dtype.kind == "f")
    if op == "drop":
        k = rng.choice(sorted(tensors))
        del tensors[k]
        return Mutation(f"tensor {k} removed", save(tensors), True)
    fill = np.nan if op == "nan" else np.inf
    if rng.random() < 0.5:
        for k in names:
            tensors[k] = np.full_like(tensors[k], fill)
        return Mutation(f"every tensor {op}", save(tensors), True)
    k = rng.choice(names)
    t = tensors[k].copy()
    t.reshape(-1)[0] = fill
    tensors[k] = t
    return Mutation(f"{k}[0] {op}", save(tensors), True)


def mutate(rng: random.Random, rel: str, kind: str, data: bytes) -> Mutation:
    """One seeded mutation of the file ``rel`` of kind ``kind`` holding ``data``."""
    suffix = Path(rel).suffix
    if kind in ("rgb", "depth", "mask"):
        return mutate_image(rng, data, kind, suffix)
    if suffix == ".ply":
        return mutate_ply(rng, data)
    if suffix == ".safetensors":
        return mutate_safetensors(rng, data)
    if suffix == ".jsonl":
        return mutate_jsonl(rng, data, kind in TYPED)
    if suffix == ".toml":
        return mutate_toml(rng, data)
    if suffix == ".csv":
        return mutate_csv(rng, data)
    return mutate_json(rng, data, kind in TYPED)


# -- cases --------------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Case:
    """Case ``number``: mutate the corpus file ``rel`` (seeded by the number), then run ``command``."""

    number: int
    rel: str
    kind: str
    command: str


def corpus_files(base: Path) -> dict[str, list[str]]:
    """The corpus files by kind (relative paths, sorted)."""
    kinds: dict[str, list[str]] = {}
    for p in sorted(base.rglob("*")):
        if p.is_file():
            rel = p.relative_to(base).as_posix()
            k = file_kind(rel)
            if k:
                kinds.setdefault(k, []).append(rel)
    return kinds


def draw_cases(base: Path, n: int, seed: int = 0, heavy_share: float = 0.25) -> list[Case]:
    """``n`` cases from ``seed``: first one per (file kind, command) pair until every kind and command is covered,
    then pairs drawn at random, a slow command's pair with weight ``heavy_share``."""
    files = corpus_files(base)
    pairs = sorted((k, c.name) for c in COMMANDS for k in c.kinds if k in files)
    rng = random.Random(seed)
    rng.shuffle(pairs)
    order: list[tuple[str, str]] = []
    kinds_left, cmds_left = {k for k, _ in pairs}, {c for _, c in pairs}
    while kinds_left or cmds_left:  # greedy cover: prefer pairs new in both, light commands first
        best = max(pairs, key=lambda p: ((p[0] in kinds_left) + (p[1] in cmds_left), not BY_NAME[p[1]].heavy))
        order.append(best)
        kinds_left.discard(best[0])
        cmds_left.discard(best[1])
    weights = [heavy_share if BY_NAME[c].heavy else 1.0 for _, c in pairs]
    while len(order) < n:
        order.append(rng.choices(pairs, weights)[0])
    cases = []
    for i, (kind, cmd) in enumerate(order[:n]):
        candidates = [f for f in files[kind] if reads(BY_NAME[cmd], f)] or files[kind]
        cases.append(Case(i, random.Random(f"{seed}:{i}").choice(candidates), kind, cmd))
    return cases


# -- running ------------------------------------------------------------------------------------------------------

def tree_hashes(root: Path) -> dict[str, str]:
    """Each regular file under ``root`` by its relative path: a hash of its bytes (of a file over 64 MiB, a sparse
    one a case made: its size and modification time)."""
    def sign(p: Path) -> str:
        st = p.stat()
        return f"{st.st_size}:{st.st_mtime_ns}" if st.st_size > 64 << 20 else hashlib.sha1(p.read_bytes()).hexdigest()

    return {p.relative_to(root).as_posix(): sign(p) for p in sorted(root.rglob("*"))
            if p.is_file()}


def _link_copy(base: Path, dest: Path) -> None:
    """A copy of the corpus whose files are hard links (a command writing in place shows up in the hashes)."""
    shutil.copytree(base, dest, copy_function=os.link)


def _show_args(rel: str) -> dict[str, str]:
    """The split, scene and image ``dataset show`` draws: the mutated file's own where it belongs to one."""
    p = Path(rel)
    split, scene, im = "train_pbr", "0", "0"
    if len(p.parts) > 3 and p.parts[1] in ("train_pbr", "test"):
        split, scene = p.parts[1], str(int(p.parts[2]))
        if p.parent.name in ("rgb", "depth", "mask", "mask_visib"):
            im = str(int(p.stem.split("_")[0]))
    elif len(p.parts) == 4 and p.parts[1] in ("train_pbr", "test"):
        split, scene = p.parts[1], str(int(p.parts[2]))
    return {"split": split, "scene": scene, "im": im}


def _scores_in_range(case_dir: Path, cmd: Command) -> str | None:
    """A problem with the scores a successful command wrote, or None."""
    def bad_ar(d: dict) -> bool:
        return any(not (0 <= v <= 1) for k, v in d.items() if k.startswith("ar") and isinstance(v, float)
                   and not (math.isnan(v) and d.get("targets") == 0))

    if cmd.name == "eval":
        m = json.loads((case_dir / "out" / "ev" / "metrics.json").read_text())
        pct = [v for k, v in m.items() if k != "bop19" and isinstance(v, (int, float)) and k != "time_per_image_s"]
        if any(not (0 <= v <= 100) for v in pct) or bad_ar(m["bop19"]) or any(bad_ar(b) for b in
                                                                                m["bop19"]["ar_by_visib"]):
            return f"score out of range in metrics.json: {m}"
    if cmd.name.startswith("trials") and cmd.name != "trials-resume":
        s = json.loads((case_dir / "out" / "tr" / "summary.json").read_text())
        if not (0 <= s["rate"] <= 1) or s["success"] > s["n"]:
            return f"summary out of range: rate {s['rate']}, {s['success']}/{s['n']}"
    return None


@dataclasses.dataclass
class Verdict:
    case: Case
    mutation: str
    rc: int
    seconds: float
    problem: str | None  # None: the command behaved
    category: str  # refused, accepted, traceback, hang, crash, stderr, false-ok, changed, range


class Fuzzer:
    """Runs cases against the corpus at ``base``, each in a fresh copy under ``work``."""

    def __init__(self, base: Path, work: Path, workers: int = 1, light_s: float = 90, heavy_s: float = 300):
        self.base, self.work = base, work
        self.zygotes = [Zygote() for _ in range(workers)]
        self.light_s, self.heavy_s = light_s, heavy_s
        self.base_hashes = tree_hashes(base)

    def close(self) -> None:
        for z in self.zygotes:
            z.close()

    def run_cases(self, cases: list, keep_failures: bool = False, progress: Callable[[Verdict], None] | None = None,
                  run: Callable | None = None) -> list[Verdict]:
        """Run ``cases`` on the workers: ``run(case, zygote, keep)`` (default ``run_case``) gives each verdict."""
        run = run or self.run_case
        free = list(self.zygotes)
        lock = threading.Lock()

        def one(case: Case) -> Verdict:
            with lock:
                z = free.pop()
            try:
                v = run(case, z, keep_failures)
            finally:
                with lock:
                    free.append(z)
            if progress:
                progress(v)
            return v

        with ThreadPoolExecutor(len(self.zygotes)) as pool:
            verdicts = list(pool.map(one, cases))
        return sorted(verdicts, key=lambda v: v.case.number)

    def run_case(self, case: Case, zygote: Zygote, keep: bool = False) -> Verdict:
        cmd = BY_NAME[case.command]
        d = self.work / f"case{case.number:05d}"
        if d.exists():
            shutil.rmtree(d)
        _link_copy(self.base, d)
        target = d / case.rel
        try:
            m = mutate(random.Random(f"mutation:{case.number}"), case.rel, case.kind, target.read_bytes())
        except Exception as e:  # the harness's own failure: reported, the other cases still run
            return Verdict(case, "(no mutation)", 0, 0.0, f"mutation failed: {e!r}", "harness")
        target.unlink()  # a file of its own, not a link into the corpus
        target.write_bytes(m.data)
        before = tree_hashes(d)
        kept = {rel: (d / rel).read_bytes() for rel in cmd.may_append}
        fill = {"out": "out", **_show_args(case.rel)}
        argv = [a.format(**fill) for a in cmd.argv]
        o = zygote.run(argv, d, self.heavy_s if cmd.heavy else self.light_s)
        problem, category = self._judge(case, cmd, m, o, d, before, zygote)
        for rel, old in kept.items():
            complete = old[:old.rfind(b"\n") + 1]
            if problem is None and o.rc == 0 and not (d / rel).read_bytes().startswith(complete):
                problem, category = f"{rel}: lines written before were lost or changed", "changed"
        if problem is None or not keep:
            shutil.rmtree(d, ignore_errors=True)
        return Verdict(case, m.what, o.rc, o.seconds, problem, category)

    def _judge(self, case: Case, cmd: Command, m: Mutation, o: Outcome, d: Path, before: dict,
               zygote: Zygote) -> tuple[str | None, str]:
        if o.hung:
            return f"no answer within {self.heavy_s if cmd.heavy else self.light_s:.0f} s", "hang"
        if "Traceback" in o.stderr:
            return o.stderr.strip().splitlines()[-1], "traceback"
        if o.rc < 0:
            return f"killed by signal {-o.rc}", "crash"
        after = tree_hashes(d)
        changed = sorted(k for k in before if after.get(k) != before[k]
                         and not (o.rc == 0 and k in cmd.may_rewrite + cmd.may_append))
        if changed:
            return f"changed {changed[:3]}", "changed"
        if o.rc != 0:
            lines = [x for x in o.stderr.splitlines() if x.strip()]
            if len(lines) != 1:
                return f"exit {o.rc} with {len(lines)} stderr lines: {o.stderr.strip()[-300:]!r}", "stderr"
            return None, "refused"
        rng_problem = _scores_in_range(d, cmd)
        if rng_problem:
            return rng_problem, "range"
        if cmd.vouches and reads(cmd, case.rel) and case.kind not in UNVOUCHED:
            if m.bad and not _unread_part(case, cmd, m):
                return f"accepted a broken file ({m.what})", "false-ok"
            if case.rel.startswith("ds/") and cmd.name != "check":
                split = Path(case.rel).parts[1] if Path(case.rel).parts[1] in ("train_pbr", "test") else None
                c = zygote.run(["dataset", "check", "ds", *(["--split", split] if split else [])], d, self.light_s)
                if c.rc != 0:
                    return f"{cmd.name} used data that dataset check rejects: {c.stderr.strip()[:200]}", "false-ok"
        return None, "accepted"


#: Parts of a file a command does not read: (kind, the mutated path's first key) -> the commands that do.
PARTS_READ_BY = {("weights_config", "train"): ("train-resume",),  # the training record
                 ("objset_json", "units"): (), ("objset_json", "frame"): (),  # prose for the reader
                 **{("train_toml", s): (f"train-{s}",) for s in ("seg", "pose", "cls", "refiner")}}


def _unread_part(case: Case, cmd: Command, m: Mutation) -> bool:
    """Whether the mutation is in a part of the file that ``cmd`` does not read (another stage's section, ...)."""
    key = m.what.split(" ")[0].split("/")[0]
    return (case.kind, key) in PARTS_READ_BY and cmd.name not in PARTS_READ_BY[case.kind, key]


def summarize(verdicts: list[Verdict]) -> dict[str, int]:
    counts = {"cases": len(verdicts)}
    for v in verdicts:
        counts[v.category] = counts.get(v.category, 0) + 1
    return counts


def format_report(verdicts: list[Verdict]) -> str:
    """The run's counts by category, the counts by command and file kind, then one line per failing case."""
    counts = summarize(verdicts)
    lines = ["fuzz: " + ", ".join(f"{k} {counts.get(k, 0)}" for k in
                                  ("cases", "refused", "accepted", "traceback", "hang", "crash", "stderr",
                                   "false-ok", "changed", "range", "slow", "harness"))]
    by_cmd: dict[str, int] = {}
    by_kind: dict[str, int] = {}
    for v in verdicts:
        by_cmd[v.case.command] = by_cmd.get(v.case.command, 0) + 1
        by_kind[v.case.kind] = by_kind.get(v.case.kind, 0) + 1
    lines.append("by command: " + ", ".join(f"{k} {n}" for k, n in sorted(by_cmd.items())))
    lines.append("by file kind: " + ", ".join(f"{k} {n}" for k, n in sorted(by_kind.items())))
    for v in verdicts:
        if v.problem:
            lines.append(f"case {v.case.number} [{v.category}] {v.case.command} {v.case.rel} ({v.mutation}): "
                         f"{v.problem}")
    return "\n".join(lines)
