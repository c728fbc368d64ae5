"""Broken BOP datasets: ``dataset check``, ``dataset show``, ``train`` and ``eval`` all refuse them with one line on
stderr naming the file, exit non-zero, print no traceback and change nothing already written; ``eval`` writes all
its outputs or none, never a score out of range; generated datasets hold what bop_toolkit's ``eval_bop19_pose.py``
opens.

One tiny generated dataset (train_pbr: 2 scenes of 2 views; test: 1 scene of 2 views; 64x48 px) shared by the module;
each test corrupts a copy.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from posegrasp import ASSETS, bop
from posegrasp.cli import main

SHIPPED_MODEL = ASSETS / "perception" / "model"
SCENE = Path("train_pbr/000000")


def snapshot(root: Path) -> dict[str, bytes | None]:
    """Every folder (None) and file (its bytes) under ``root``."""
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("validation") / "ds"
    for split, scenes in (("train_pbr", "2"), ("test", "1")):
        assert main(["datagen", "--out", str(root), "--split", split, "--scenes", scenes, "--views", "2",
                     "--resolution", "64x48", "--blocks", "2", "--workers", "1", "--no-progress"]) == 0
    return root


@pytest.fixture
def copy(dataset, tmp_path) -> Path:
    return Path(shutil.copytree(dataset, tmp_path / "copy"))


def _write(path: Path, value) -> None:
    path.write_bytes(value if isinstance(value, bytes) else json.dumps(value).encode())


def _first(d: dict):
    return d[sorted(d, key=int)[0]]


def _commands(root: Path, out: Path, split: str = "train_pbr") -> dict[str, list[str]]:
    return {"check": ["dataset", "check", str(root)],
            "show": ["dataset", "show", str(root), "--split", split, "--scene", "0", "--im", "0",
                     "--out", str(out / "show.png")],
            "train": ["train", "seg", "--data", str(root), "--out", str(out / "run"), "--steps", "1", "--no-progress"],
            "eval": ["eval", "--data", str(root), "--weights", str(SHIPPED_MODEL), "--split", split,
                     "--out", str(out / "ev"), "--no-progress"]}


def _refused(capsys, root: Path, out: Path, words: str, commands: tuple[str, ...], split: str = "train_pbr") -> None:
    """Each command: non-zero exit, exactly one stderr line holding ``words``, no traceback, nothing changed in the
    dataset, nothing written to ``out``."""
    before = snapshot(root)
    out.mkdir(exist_ok=True)
    for name in commands:
        rc = main(_commands(root, out, split)[name])
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert rc != 0, (name, err)
        assert len(lines) == 1 and "Traceback" not in err, (name, err)
        assert words in lines[0], (name, lines[0])
        assert snapshot(root) == before, name
        assert snapshot(out) == {}, name


ALL = ("check", "show", "train", "eval")


def _cut(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])


def _png(path: Path, img: np.ndarray) -> None:
    path.write_bytes(cv2.imencode(".png", img)[1].tobytes())


# -- JSON files -----------------------------------------------------------------------------------------------------

JSON_CASES = [
    # camera.json
    ("camera.json", None, "camera.json: expected a JSON object, got null"),
    ("camera.json", [1, 2], "camera.json: expected a JSON object, got [1, 2]"),
    ("camera.json", "camera", "camera.json: expected a JSON object, got 'camera'"),
    ("camera.json", b"\x89\xff\x00garbage", "camera.json: expected UTF-8 JSON text, got binary data"),
    ("camera.json", lambda c: c.update(width=-320), "camera.json: 'width': expected an integer in [1, 100000], got -320"),
    ("camera.json", lambda c: c.pop("fx"), "camera.json: expected a key 'fx'"),
    ("camera.json", lambda c: c.update(fy="500"), "camera.json: 'fy': expected a finite number in (0, 100000]"),
    ("camera.json", lambda c: c.update(cx=float("nan")), "camera.json: expected valid JSON (NaN is not a JSON number)"),
    # models_info.json
    ("models/models_info.json", lambda m: _first(m).update(diameter=1e300),
     "'diameter': expected a finite number in [1, 100000], got 1e+300"),
    ("models/models_info.json", lambda m: _first(m).update(diameter=0.05), "this looks like metres"),
    ("models/models_info.json", lambda m: _first(m).update(size_x="big"), "'size_x': expected a finite number"),
    ("models/models_info.json", lambda m: _first(m).pop("min_y"), "expected a key 'min_y'"),
    ("models/models_info.json", [], "models_info.json: expected a JSON object keyed by obj id, got []"),
    # the scene's labels
    (f"{SCENE}/scene_gt.json", [{"obj_id": 1}], "scene_gt.json: expected a JSON object keyed by image id, got [{"),
    (f"{SCENE}/scene_gt.json", "gt", "scene_gt.json: expected a JSON object keyed by image id, got 'gt'"),
    (f"{SCENE}/scene_gt.json", None, "scene_gt.json: expected a JSON object keyed by image id, got null"),
    (f"{SCENE}/scene_gt.json", lambda g: _first(g)[0].update(obj_id="one"),
     "scene_gt.json: im 0 gt 0 'obj_id': expected an integer"),
    (f"{SCENE}/scene_gt.json", lambda g: _first(g)[0].pop("cam_t_m2c"), "scene_gt.json: im 0 gt 0: expected a key 'cam_t_m2c'"),
    (f"{SCENE}/scene_gt.json", lambda g: _first(g)[0].update(cam_R_m2c=[1, 0, 0]),
     "im 0 gt 0 'cam_R_m2c': expected a list of 9 finite numbers"),
    (f"{SCENE}/scene_gt.json", b"\x00\x01\x02\xfe", "scene_gt.json: expected UTF-8 JSON text, got binary data"),
    (f"{SCENE}/scene_gt.json", b'{"0": [', "scene_gt.json: expected valid JSON"),
    (f"{SCENE}/scene_gt.json", lambda g: g.update({"x": []}), "scene_gt.json: image x: expected keys that are integer ids"),
    (f"{SCENE}/scene_camera.json", lambda c: _first(c).pop("cam_K"), "scene_camera.json: im 0: expected a key 'cam_K'"),
    (f"{SCENE}/scene_camera.json", lambda c: _first(c).update(depth_scale=-1),
     "im 0 'depth_scale': expected a finite number in (0, 1000]"),
    (f"{SCENE}/scene_gt_info.json", lambda i: _first(i)[0].update(visib_fract=1.5),
     "im 0 gt 0 'visib_fract': expected a finite number in [0, 1], got 1.5"),
    (f"{SCENE}/scene_gt_info.json", lambda i: _first(i).pop(),
     "scene_gt_info.json: im 0: expected 2 entries as in scene_gt.json, got 1"),
]


@pytest.mark.parametrize("rel, value, words", JSON_CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(JSON_CASES)])
def test_corrupt_json_is_refused_by_every_reader(capsys, copy, tmp_path, rel, value, words):
    path = copy / rel
    if callable(value):
        data = json.loads(path.read_text())
        value(data)
        _write(path, data)
    else:
        _write(path, value)
    _refused(capsys, copy, tmp_path / "out", words, ALL)


# -- images ---------------------------------------------------------------------------------------------------------

def _rgb(root: Path) -> Path:
    return next((root / SCENE / "rgb").glob("000000.*"))


IMAGE_CASES = {
    "jpeg cut in half": (lambda r: _cut(_rgb(r)), "expected an 8-bit colour (or grey) PNG/JPEG, got a truncated"),
    "png depth cut in half": (lambda r: _cut(r / SCENE / "depth/000000.png"), "got a truncated or corrupt file"),
    "rgb of the wrong size": (lambda r: _rgb(r).write_bytes(cv2.imencode(".jpg", np.zeros((24, 32, 3), np.uint8))[1]
                                                            .tobytes()), "expected 64x48 px as camera.json, got 32x24"),
    "rgb as depth": (lambda r: _png(r / SCENE / "depth/000000.png", np.full((48, 64, 3), 90, np.uint8)),
                     "depth/000000.png: expected a 16-bit single-channel PNG (value x depth_scale = mm), got 8-bit, "
                     "3 channels"),
    "8-bit depth": (lambda r: _png(r / SCENE / "depth/000000.png", np.full((48, 64), 90, np.uint8)),
                    "got 8-bit, 1 channel"),
    "all-zero depth": (lambda r: _png(r / SCENE / "depth/000000.png", np.zeros((48, 64), np.uint16)),
                       "depth/000000.png: expected depth measurements, got an image of zeros"),
    "missing visible mask": (lambda r: (r / SCENE / "mask_visib/000000_000000.png").unlink(),
                             "mask_visib/000000_000000.png: expected an 8-bit single-channel PNG (it does not exist)"),
    "all-white visible mask": (lambda r: _png(r / SCENE / "mask_visib/000000_000000.png",
                                              np.full((48, 64), 255, np.uint8)), "got every pixel set"),
    "mask of the wrong size": (lambda r: _png(r / SCENE / "mask/000000_000001.png", np.zeros((10, 10), np.uint8)),
                               "mask/000000_000001.png: expected 64x48 px as camera.json, got 10x10"),
}


@pytest.mark.parametrize("case", sorted(IMAGE_CASES))
def test_bad_images_are_refused_by_every_reader(capsys, copy, tmp_path, case):
    """Among them: ``train`` never trains on a truncated JPEG or without a mask, ``eval`` never scores an 8-bit or
    empty depth image or a missing or full visible mask."""
    corrupt, words = IMAGE_CASES[case]
    corrupt(copy)
    _refused(capsys, copy, tmp_path / "out", words, ALL)


# -- models -----------------------------------------------------------------------------------------------------------

def _scaled_models_eval(root: Path, factor: float) -> None:
    import trimesh

    for p in sorted(bop.models_eval_dir(root).glob("*.ply")):
        m = trimesh.load(p, force="mesh", process=False)
        m.apply_scale(factor)
        p.write_bytes(m.export(file_type="ply"))


def test_a_ply_without_faces_is_refused(capsys, copy, tmp_path):
    import trimesh

    p = bop.model_path(copy, sorted(bop.load_models_info(copy))[0])
    p.write_bytes(trimesh.PointCloud(trimesh.load(p, force="mesh").vertices).export(file_type="ply"))
    _refused(capsys, copy, tmp_path / "out", f"{p.name}: expected a triangle mesh, got", ("check", "train", "eval"))


def test_models_eval_in_metres_is_refused(capsys, copy, tmp_path):
    _scaled_models_eval(copy, 1e-3)
    _refused(capsys, copy, tmp_path / "out", "extent differs from models/obj_", ("check", "eval"))
    assert "looks like metres" in " ".join(main_output(capsys, copy))


def main_output(capsys, root: Path) -> list[str]:
    main(["dataset", "check", str(root)])
    return capsys.readouterr().out.split()


# -- BOP 2019 targets --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("value, words", [
    (None, "test_targets_bop19.json: expected a JSON list of targets, got null"),
    (lambda t: t[0].update(inst_count=10 ** 9), "entry 0 'inst_count': expected an integer in [1, 10000]"),
    (lambda t: t[0].update(inst_count=t[0]["inst_count"] + 5), "'inst_count': expected"),
    (lambda t: t.append(dict(t[0])), "expected each (scene_id, im_id, obj_id) once"),
    (lambda t: t[0].update(im_id=77), "entry 0 (scene 0 im 77 obj"),
])
def test_bad_targets_are_refused(capsys, copy, tmp_path, value, words):
    path = bop.targets_path(copy)
    if callable(value):
        rows = json.loads(path.read_text())
        value(rows)
        _write(path, rows)
    else:
        _write(path, value)
    _refused(capsys, copy, tmp_path / "out", words, ("check", "eval"), split="test")


# -- eval's outputs ---------------------------------------------------------------------------------------------------

def test_eval_writes_all_or_nothing(tmp_path, monkeypatch):
    from posegrasp import io as pio
    from posegrasp.perception.evaluate import write_all

    out = tmp_path / "ev"
    write_all(out, {"instances.csv": b"a\n", "metrics.json": b"{}\n"})
    before = snapshot(tmp_path)
    real = pio.write_bytes

    def full_disk(path, data, fsync=True):
        if Path(path).name == "metrics.json":
            raise OSError(28, "No space left on device")
        return real(path, data, fsync)

    monkeypatch.setattr(pio, "write_bytes", full_disk)
    with pytest.raises(OSError):
        write_all(out, {"instances.csv": b"b\n", "per_object.csv": b"c\n", "metrics.json": b"{1}\n"})
    assert snapshot(tmp_path) == before


def test_eval_never_writes_a_score_out_of_range():
    from posegrasp.perception.evaluate import check_score_ranges

    check_score_ranges({"ar": 0.5, "per_object": {"1": {"ar": float("nan")}}, "overall": {"ADD_AUC": 99.0}})
    with pytest.raises(RuntimeError, match="score ar = 7.89 outside"):
        check_score_ranges({"ar": 7.89})
    with pytest.raises(RuntimeError, match=r"by_visib.0.ar_mssd = -0.1"):
        check_score_ranges({"by_visib": [{"ar_mssd": -0.1}]})
    with pytest.raises(RuntimeError, match="mIoU"):
        check_score_ranges({"segmentation": {"mIoU": 101.0}})


# -- BOP conformance ----------------------------------------------------------------------------------------------------

def _ply_header(path: Path) -> list[str]:
    data = path.read_bytes()
    return data[:data.index(b"end_header")].decode("ascii").splitlines()


def test_bop_toolkit_eval_files_are_present_and_well_formed(capsys, dataset):
    """What ``scripts/eval_bop19_pose.py`` (``eval_calc_errors.py``, ``eval_calc_scores.py``) opens, with
    ``model_type = "eval"``: models_eval/obj_*.ply (vertices and faces as its ``inout.load_ply`` reads them) and
    models_eval/models_info.json, test_targets_bop19.json, and per target scene scene_gt.json, scene_gt_info.json,
    scene_camera.json (cam_K, depth_scale) and depth/<im>.png (16-bit, for VSD); camera.json gives the image size to
    register in its dataset_params."""
    assert main(["dataset", "check", str(dataset)]) == 0
    capsys.readouterr()
    infos = bop.load_models_info(dataset)
    eval_infos = bop.load_models_info(bop.models_eval_dir(dataset) / "models_info.json")
    assert sorted(eval_infos) == sorted(infos)
    for oid, info in infos.items():
        assert eval_infos[oid].diameter == pytest.approx(info.diameter)
        assert len(eval_infos[oid].symmetries_discrete) == len(info.symmetries_discrete)
        head = _ply_header(bop.models_eval_dir(dataset) / f"obj_{oid:06d}.ply")
        assert head[0] == "ply" and head[1].split()[1] in ("ascii", "binary_little_endian")
        vertex = next(i for i, line in enumerate(head) if line.startswith("element vertex"))
        assert [line.split()[-1] for line in head[vertex + 1:vertex + 4]] == ["x", "y", "z"]
        face = next(line for line in head if line.startswith("element face"))
        assert int(face.split()[-1]) > 0
        assert any(line.startswith("property list") and line.split()[-1] in ("vertex_indices", "vertex_index")
                   for line in head)
    rows = json.loads(bop.targets_path(dataset).read_text())
    assert rows and all(set(r) == {"scene_id", "im_id", "obj_id", "inst_count"} for r in rows)
    for r in rows:
        sd = bop.scene_dir(dataset, "test", r["scene_id"])
        cams = json.loads((sd / "scene_camera.json").read_text())
        cam = cams[str(r["im_id"])]
        assert len(cam["cam_K"]) == 9 and cam["depth_scale"] > 0
        gt = json.loads((sd / "scene_gt.json").read_text())[str(r["im_id"])]
        info = json.loads((sd / "scene_gt_info.json").read_text())[str(r["im_id"])]
        assert len(gt) == len(info) and sum(g["obj_id"] == r["obj_id"] for g in gt) >= r["inst_count"]
        depth = cv2.imread(str(bop.image_path(sd, "depth", r["im_id"])), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16 and depth.any()
    cam = json.loads(bop.camera_path(dataset).read_text())
    assert (cam["width"], cam["height"]) == (64, 48)


def test_check_requires_models_eval_models_info(capsys, copy, tmp_path):
    (bop.models_eval_dir(copy) / "models_info.json").unlink()
    _refused(capsys, copy, tmp_path / "out", "models_eval/models_info.json: missing; bop_toolkit's eval_bop19_pose.py",
             ("check",))


def test_merge_renumbers_the_scenes_of_several_datasets_into_one_valid_root(capsys, dataset, tmp_path):
    out = tmp_path / "merged"
    assert main(["dataset", "merge", str(out), f"{dataset}:train_pbr", f"{dataset}:test"]) == 0
    assert bop.list_scenes(out, "train_pbr") == [0, 1, 2]
    for new, (split, old) in enumerate((("train_pbr", 0), ("train_pbr", 1), ("test", 0))):
        for name in ("scene_gt.json", "scene_camera.json"):
            assert (bop.scene_dir(out, "train_pbr", new) / name).read_bytes() == \
                (bop.scene_dir(dataset, split, old) / name).read_bytes()
    origin = json.loads((bop.split_dir(out, "train_pbr") / "merged_from.json").read_text())
    assert [(o["split"], o["source_scene_id"]) for o in origin] == [("train_pbr", 0), ("train_pbr", 1), ("test", 0)]
    capsys.readouterr()
    assert main(["dataset", "check", str(out), "--split", "train_pbr"]) == 0


@pytest.mark.parametrize("case, words", [("camera", "differs from"), ("split", "has no split 'val'"),
                                         ("splits", "name one as"), ("exists", "already exists")])
def test_merge_refuses_bad_sources_and_writes_nothing(capsys, copy, tmp_path, case, words):
    out = tmp_path / "merged"
    sources = {"camera": [f"{copy.parent / 'other'}:test"], "split": [f"{copy}:val"], "splits": [str(copy)],
               "exists": [f"{copy}:test"]}[case]
    if case == "camera":
        other = Path(shutil.copytree(copy, copy.parent / "other"))
        cam = json.loads(bop.camera_path(other).read_text())
        _write(bop.camera_path(other), {**cam, "fx": cam["fx"] * 2})
    if case == "exists":
        out.mkdir()
    before = snapshot(tmp_path)
    rc = main(["dataset", "merge", str(out), f"{copy}:test", *sources])
    lines = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(lines) == 1 and words in lines[0], lines
    assert snapshot(tmp_path) == before


def test_a_pool_of_workers_finds_what_one_process_finds_in_the_same_order(copy):
    from posegrasp.bop.check import CheckOptions, check_dataset

    for scene in ("train_pbr/000000", "train_pbr/000001"):  # a problem in each scene: a visible pixel count off by one
        info = json.loads((copy / scene / "scene_gt_info.json").read_text())
        _first(info)[0]["px_count_visib"] += 1
        _write(copy / scene / "scene_gt_info.json", info)
    opts = CheckOptions(model_depth=False)
    one, pool = (check_dataset(copy, opts=opts, workers=n) for n in (1, 2))
    assert [p[:16] for p in one.problems] == ["train_pbr/000000"] * 2 + ["train_pbr/000001"] * 2
    assert pool == one
    capped = check_dataset(copy, opts=CheckOptions(model_depth=False, max_problems=1), workers=2)
    assert capped.problems == one.problems[:1] and capped.stopped_early
