"""Bad input to every subcommand: a one-line error naming the problem, exit 2 (1 where a checker reports
invalid data), no traceback, and the folders as they were (nothing written, nothing changed).

The CLI runs in-process (``posegrasp.cli.main``) on one tiny generated dataset shared by the module.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from helpers import refused
from posegrasp import ASSETS
from posegrasp.cli import main
from posegrasp.grasping.record import EpisodeRecord

SHIPPED_MODEL = ASSETS / "perception" / "model"


def snapshot(root: Path) -> dict[str, bytes | None] | None:
    """Every folder (None) and file (its bytes) under ``root``; None if ``root`` does not exist."""
    if not root.exists():
        return None
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Two scenes of two 64x48 views: a valid BOP dataset, never modified by the tests."""
    root = tmp_path_factory.mktemp("bad_input") / "ds"
    assert main(["datagen", "--out", str(root), "--scenes", "2", "--views", "2", "--resolution", "64x48",
                 "--blocks", "2", "--workers", "1", "--no-progress"]) == 0
    return root


@pytest.fixture
def copy(dataset, tmp_path) -> Path:
    """A copy of the dataset that a test may corrupt."""
    return Path(shutil.copytree(dataset, tmp_path / "copy"))


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    path.write_text(json.dumps(edit(data) or data))


def _first_gt(data: dict) -> dict:
    return data[sorted(data, key=int)[0]][0]


# -- datagen: refused before anything is written ----------------------------------------------------------------

def _toml(tmp_path: Path, text: str | bytes) -> Path:
    p = tmp_path / "c.toml"
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    return p


@pytest.mark.parametrize("argv, words", [
    (["--seed", "-1"], "--seed must be a non-negative integer"),
    (["--scenes", "0"], "--scenes must be a positive integer"),
    (["--views", "two"], "--views must be a positive integer"),
    (["--workers", "0"], "--workers"),
    (["--blocks", "5-2"], "--blocks '5-2'"),
    (["--blocks", "500"], "do not fit"),
    (["--resolution", "0x0"], "out of range"),
    (["--split", "val"], "invalid choice"),
    (["--colour", "red"], "unrecognized arguments: --colour"),
    (["--config", "/nonexistent.toml"], "does not exist"),
])
def test_datagen_bad_options(capsys, tmp_path, argv, words):
    out = tmp_path / "out"
    refused(capsys, ["datagen", "--out", out, "--scenes", "1", "--views", "1", *argv], words)
    assert not out.exists()


@pytest.mark.parametrize("text, words", [
    (b"\xff\xfe width = 1\n", "not UTF-8"),
    ("[workcell.hand_camera]\nwidth = 0\n", "hand_camera.width = 0 is out of range"),
    ("[workcell.hand_camera]\nfovy_deg = 0\n", "hand_camera.fovy_deg = 0.0 is out of range"),
    ("min_spacing = nan\n", "min_spacing: expected a finite number"),
    ("min_spacing = 'wide'\n", "min_spacing: expected a finite number"),
    ("blocks = [1, 'x']\n", "blocks: expected int"),
    ("colour = 1\n", "unknown key(s) ['colour']"),
    ("block_types = ['dodecahedron']\n", "unknown block type(s) ['dodecahedron']"),
    ("[views\n", "not valid TOML"),
])
def test_datagen_bad_config_file(capsys, tmp_path, text, words):
    out = tmp_path / "out"
    refused(capsys, ["datagen", "--out", out, "--config", _toml(tmp_path, text)], words)
    assert not out.exists()


def test_datagen_config_naming_a_folder(capsys, tmp_path):
    refused(capsys, ["datagen", "--out", tmp_path / "out", "--config", tmp_path], "is not a file")
    assert snapshot(tmp_path) == {}


@pytest.mark.parametrize("out, words", [("", "--out is empty"), ("file", "is a file"),
                                        ("file/sub", "cannot create output folder")])
def test_datagen_bad_out(capsys, tmp_path, out, words):
    (tmp_path / "file").write_text("x")
    before = snapshot(tmp_path)
    refused(capsys, ["datagen", "--out", str(tmp_path / out) if out else "", "--scenes", "1"], words)
    assert snapshot(tmp_path) == before


def test_datagen_other_settings_change_nothing(capsys, dataset):
    before = snapshot(dataset)
    refused(capsys, ["datagen", "--out", dataset, "--scenes", "2", "--views", "3", "--resolution", "64x48",
                     "--blocks", "2", "--no-progress"], "generated with other settings")
    assert snapshot(dataset) == before


def test_datagen_fewer_scenes_keeps_the_stats(capsys, copy):
    stats = copy / "train_pbr" / "datagen_stats.json"
    before = stats.read_bytes()
    assert json.loads(before)["scenes"] == 2
    assert main(["datagen", "--out", str(copy), "--scenes", "1", "--views", "2", "--resolution", "64x48",
                 "--blocks", "2", "--no-progress"]) == 0
    assert "all 2 scenes already complete" in capsys.readouterr().out
    assert stats.read_bytes() == before


# -- dataset check / show -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, words", [
    (["--depth-tol-mm", "nan"], "--depth-tol-mm must be a finite number > 0"),
    (["--depth-tol-mm", "-1"], "--depth-tol-mm must be a finite number > 0"),
    (["--max-images", "0"], "--max-images must be a positive integer"),
    (["--split", "val"], "split 'val' not found"),
])
def test_check_bad_options(capsys, dataset, argv, words):
    refused(capsys, ["dataset", "check", dataset, *argv], words)


def test_check_missing_folder(capsys, tmp_path):
    refused(capsys, ["dataset", "check", tmp_path / "none"], "does not exist")


def _check_finds(capsys, root: Path, words: str) -> None:
    """``dataset check`` exits 1 and lists a problem holding ``words``; it never says OK."""
    rc = main(["dataset", "check", str(root)])
    out, err = capsys.readouterr()
    assert rc == 1 and words in out and "OK" not in out and "Traceback" not in err, out


def test_check_reports_a_scene_gt_that_is_not_an_object(capsys, copy):
    gt = copy / "train_pbr" / "000000" / "scene_gt.json"
    gt.write_text(json.dumps(list(json.loads(gt.read_text()).values())))
    _check_finds(capsys, copy, "scene_gt.json: expected a JSON object keyed by image id, got [")


def test_check_flags_camera_translation_in_metres(capsys, copy):
    def metres(cams):
        for c in cams.values():
            c["cam_t_w2c"] = [v / 1000 for v in c["cam_t_w2c"]]
    _edit_json(copy / "train_pbr" / "000001" / "scene_camera.json", metres)
    _check_finds(capsys, copy, "cam_t_w2c")


def test_check_flags_a_malformed_camera_rotation(capsys, copy):
    _edit_json(copy / "train_pbr" / "000000" / "scene_camera.json", lambda c: c["0"].update(cam_R_w2c=[1, 0]))
    _check_finds(capsys, copy, "im 0 'cam_R_w2c': expected a list of 9 finite numbers")


@pytest.mark.parametrize("argv, words", [
    (["--out", "x.bmp"], "unsupported file type '.bmp'"),
    (["--out", ""], "--out is empty"),
    (["--out", "."], "is a folder"),
    (["--scene", "-1"], "--scene must be a non-negative integer"),
    (["--scene", "7"], "scene 7 is not in"),
    (["--im", "9"], "image 9 is not in scene 0"),
])
def test_show_bad_options(capsys, dataset, tmp_path, monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    base = {"--scene": "0", "--im": "0", "--out": "x.png"}
    base.update(dict(zip(argv[::2], argv[1::2])))
    refused(capsys, ["dataset", "show", dataset, *[x for kv in base.items() for x in kv]], words)
    assert snapshot(tmp_path) == {}


# -- trials, compare, report on corrupt run folders ---------------------------------------------------------------

def _record(i: int, ok: bool = True) -> dict:
    return {"episode": i, "seed": 0, "outcome": "success" if ok else "failure", "failure": None if ok else "slip",
            "target": {"type": "cube"}}


def _run_folder(path: Path, lines: list[str], campaign: str | None = None) -> Path:
    """A trial run folder holding ``lines`` in episodes.jsonl and a campaign.json (the default oracle campaign,
    or the ``campaign`` text)."""
    from posegrasp.grasping.calibration import load_hand_eye
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.runfolder import Campaign
    from posegrasp.io import dumps_json

    path.mkdir(parents=True)
    (path / "episodes.jsonl").write_text("".join(f"{x}\n" for x in lines))
    cfg = TrialConfig()
    mount = tuple(tuple(float(v) for v in row) for row in load_hand_eye(cfg.hand_eye))
    (path / "campaign.json").write_text(campaign if campaign is not None else
                                        dumps_json(Campaign(0, "oracle", cfg, mount).to_json()))
    return path


NO_EPISODE = json.dumps({"seed": 0, "outcome": "success"})


@pytest.mark.parametrize("lines, campaign, words", [
    ([NO_EPISODE], None, "episodes.jsonl line 1 is not an episode record"),
    ([json.dumps(_record(0)), "[1, 2]"], None, "episodes.jsonl line 2 is not an episode record"),
    ([json.dumps(_record(0))], "{\"seed\": 0,", "campaign.json is not readable JSON"),
    ([json.dumps(_record(0))], "[]", "campaign.json is not a JSON object"),
])
def test_trials_refuse_a_corrupt_run_folder(capsys, tmp_path, lines, campaign, words):
    run = _run_folder(tmp_path / "run", lines, campaign)
    before = snapshot(run)
    refused(capsys, ["trials", "--out", run, "--episodes", "2", "--workers", "1", "--no-progress"], words)
    assert snapshot(run) == before


@pytest.mark.parametrize("argv, words", [
    (["--perception", "sonar"], "unknown perception 'sonar'; choose one of: "),
    (["--perception", "sonar"], "oracle, ppf, py:MODULE_OR_FILE:FACTORY[:ARGS]; installed: "),
    (["--perception", "noisy-oracle:far"], "are not TRANS_M,ROT_DEG"),
    (["--perception", "model:/nonexistent"], "must hold seg/ and pose/"),
    (["--episodes", "0"], "--episodes must be a positive integer"),
    (["--seed", "-3"], "--seed must be a non-negative integer"),
    (["--workers", "two"], "--workers"),
])
def test_trials_bad_options(capsys, tmp_path, argv, words):
    refused(capsys, ["trials", "--out", tmp_path / "run", "--episodes", "1", *argv], words)
    assert snapshot(tmp_path) == {}


#: A plug-in file with a good factory and three bad ones (``--perception py:FILE:FACTORY``).
PLUGIN = """class P:
    name = "p"

    def estimate(self, obs, seed):
        return []

def make(args):
    return P()

def broken(args):
    raise ValueError("no weights at\\n" + str(args))

def nothing(args):
    return 42

not_callable = 3
"""


@pytest.mark.parametrize("spec, words", [
    ("py:no_such_module_xyz:make", "no module named 'no_such_module_xyz'"),
    ("py:{d}/missing.py:make", "no file"),
    ("py:{d}/plugin.py:nope", "has no callable 'nope'"),
    ("py:{d}/plugin.py:not_callable", "has no callable 'not_callable'"),
    ("py:{d}/plugin.py:broken:/w", "its factory raised ValueError: no weights at /w"),
    ("py:{d}/plugin.py:nothing", "the factory returned a int, not a provider"),
    ("py:{d}/syntax.py:make", "syntax.py failed: SyntaxError"),
    ("py:{d}/plugin.py", "is not py:MODULE_OR_FILE:FACTORY[:ARGS]"),
    ("py::make", "is not py:MODULE_OR_FILE:FACTORY[:ARGS]"),
])
def test_trials_unbuildable_plugins(capsys, tmp_path, spec, words):
    d = tmp_path / "plug"
    d.mkdir()
    (d / "plugin.py").write_text(PLUGIN)
    (d / "syntax.py").write_text("def make(:\n")
    before = snapshot(tmp_path)
    refused(capsys, ["trials", "--out", tmp_path / "run", "--episodes", "1", "--perception", spec.format(d=d)], words)
    assert snapshot(tmp_path) == before


def test_trials_unreadable_weights(capsys, tmp_path):
    weights = Path(shutil.copytree(SHIPPED_MODEL, tmp_path / "w", ignore=shutil.ignore_patterns("*.safetensors")))
    for stage in ("seg", "pose"):
        (weights / stage / "model.safetensors").write_bytes(b"not a tensor file")
    before = snapshot(tmp_path)
    refused(capsys, ["trials", "--out", tmp_path / "run", "--perception", f"model:{weights}"], "corrupt")
    assert snapshot(tmp_path) == before


def test_trials_unreadable_hand_eye_calibration(capsys, tmp_path):
    (tmp_path / "he.json").write_text("{}")
    cfg = _toml(tmp_path, f"hand_eye = '{tmp_path / 'he.json'}'\n")
    before = snapshot(tmp_path)
    refused(capsys, ["trials", "--out", tmp_path / "run", "--config", cfg], "4x4 T_gripper_cam")
    assert snapshot(tmp_path) == before


def test_compare_refuses_a_record_without_episode(capsys, tmp_path):
    a = _run_folder(tmp_path / "a", [json.dumps(EpisodeRecord(0, 0, 1, 1, "oracle").to_json())])
    b = _run_folder(tmp_path / "b", [NO_EPISODE])
    before = snapshot(tmp_path)
    refused(capsys, ["compare", a, b], "episodes.jsonl line 1 is not an episode record")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("argv, words", [
    (["--out", "."], "is a folder"),
    (["--out", "file/sub.json"], "cannot create output file"),
    (["--out", "x.csv"], "unsupported file type '.csv'"),
    (["--alpha", "1.5"], "--alpha must be a finite number > 0 and < 1"),
    (["--alpha", "nan"], "--alpha must be a finite number"),
])
def test_compare_bad_options(capsys, tmp_path, monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    a = _run_folder(tmp_path / "a", [json.dumps(EpisodeRecord(0, 0, 1, 1, "oracle").to_json())])
    (tmp_path / "file").write_text("x")
    before = snapshot(tmp_path)
    refused(capsys, ["compare", a, a, *argv], words)
    assert snapshot(tmp_path) == before


def test_compare_a_folder_without_episodes(capsys, tmp_path):
    refused(capsys, ["compare", tmp_path, tmp_path], "holds no trial episodes")


@pytest.mark.parametrize("lines, campaign, words", [
    ([NO_EPISODE], None, "line 1 is not an episode record"),
    ([json.dumps(_record(0))], "{\"seed\": 0}", "campaign.json is corrupt"),
    ([json.dumps(_record(0))], None, "episodes.jsonl line 1: missing field(s) ['scene_seed', 'n_blocks', 'perception']"),
    ([json.dumps(EpisodeRecord(0, 0, 1, 1, "oracle").to_json())], None, "summary.json is corrupt"),
])
def test_report_refuses_a_corrupt_run_folder(capsys, tmp_path, lines, campaign, words):
    run = _run_folder(tmp_path / "run", lines, campaign)
    (run / "summary.json").write_text("{}")
    before = snapshot(run)
    refused(capsys, ["report", run], words)
    assert snapshot(run) == before


# -- eval, train, perturb -----------------------------------------------------------------------------------------

def _eval(capsys, data: Path, out: Path, words: str, *argv) -> None:
    before = snapshot(data)
    refused(capsys, ["eval", "--data", data, "--weights", SHIPPED_MODEL, "--split", "train_pbr", "--out", out,
                     "--no-progress", *argv], words)
    assert snapshot(data) == before


@pytest.mark.parametrize("corrupt, words", [
    (lambda gt: list(gt.values()), "scene_gt.json: expected a JSON object keyed by image id, got ["),
    (lambda gt: _first_gt(gt).update(cam_R_m2c=[float("nan")] * 9), "scene_gt.json: expected valid JSON (NaN"),
    (lambda gt: _first_gt(gt).update(cam_t_m2c=[v / 1000 for v in _first_gt(gt)["cam_t_m2c"]]),
     "looks like metres"),
    (lambda gt: _first_gt(gt).update(obj_id=99), "obj_id 99 is not in models/models_info.json"),
])
def test_eval_validates_ground_truth_first(capsys, copy, tmp_path, corrupt, words):
    gt = copy / "train_pbr" / "000000" / "scene_gt.json"
    data = json.loads(gt.read_text())
    gt.write_text(json.dumps(corrupt(data) or data))
    _eval(capsys, copy, tmp_path / "ev", words)
    assert not (tmp_path / "ev").exists()


@pytest.mark.parametrize("argv, words", [
    (["--max-images", "0"], "--max-images must be a positive integer"),
    (["--out", "file"], "is a file; name an output folder"),
    (["--out", ""], "--out is empty"),
    (["--split", "val"], "split 'val' not found"),
    (["--threads", "100000"], "threads = 100000 is out of range"),
])
def test_eval_bad_options(capsys, dataset, tmp_path, argv, words):
    (tmp_path / "file").write_text("x")
    opts = dict(zip(argv[::2], argv[1::2]))
    out = opts.pop("--out", "ev")
    _eval(capsys, dataset, tmp_path / out if out else "", words, *[x for kv in opts.items() for x in kv])
    assert snapshot(tmp_path) == {"file": b"x"}


def test_eval_missing_data(capsys, tmp_path):
    refused(capsys, ["eval", "--data", tmp_path / "none", "--weights", SHIPPED_MODEL], "--data")


@pytest.mark.parametrize("argv, words", [
    (["train", "seg", "--steps", "0"], "--steps must be a positive integer"),
    (["train", "lid"], "invalid choice: 'lid'"),
    (["perturb", "--weights", SHIPPED_MODEL, "--rel-sigma", "nan"], "--rel-sigma must be a finite number >= 0"),
    (["perturb", "--weights", "/nonexistent", "--rel-sigma", "0.1"], "--weights '/nonexistent' does not exist"),
])
def test_train_and_perturb_bad_options(capsys, dataset, tmp_path, argv, words):
    extra = ["--data", dataset] if argv[0] == "train" else []
    refused(capsys, [*argv, *extra, "--out", tmp_path / "run"], words)
    assert snapshot(tmp_path) == {}


@pytest.mark.parametrize("text, words", [
    ("[seg]\nlr = 'fast'\n", "lr: expected a finite number"),
    ("[sge]\nlr = 0.1\n", "unknown section(s) ['sge']; valid sections are ['cls', 'eval', 'pose', 'refiner', 'seg']"),
])
def test_train_config_of_the_wrong_type_or_a_misspelt_table(capsys, dataset, tmp_path, text, words):
    cfg = _toml(tmp_path, text)
    refused(capsys, ["train", "seg", "--data", dataset, "--out", tmp_path / "run", "--config", cfg], words)
    assert not (tmp_path / "run").exists()


def test_eval_config_with_a_misspelt_table(capsys, dataset, tmp_path):
    cfg = _toml(tmp_path, "[evl]\nthreads = 1\n")
    refused(capsys, ["eval", "--data", dataset, "--weights", SHIPPED_MODEL, "--out", tmp_path / "ev", "--config",
                     cfg], "unknown section(s) ['evl']")
    assert not (tmp_path / "ev").exists()


# -- the program, scene and calibrate -----------------------------------------------------------------------------

@pytest.mark.parametrize("argv, words", [
    ([], "the following arguments are required: command"),
    (["fly"], "invalid choice: 'fly'"),
    (["scene", "--seed", "-1", "--out", "o"], "--seed must be a non-negative integer"),
    (["scene", "--blocks", "0", "--out", "o"], "--blocks must be a positive integer"),
    (["calibrate", "--out", "."], "is a folder"),
    (["calibrate", "--out", "he.txt"], "unsupported file type '.txt'"),
    (["calibrate", "--out", "he.json", "--poses", "2"], "--poses must be at least 3"),
])
def test_program_bad_options(capsys, tmp_path, monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    refused(capsys, argv, words)
    assert snapshot(tmp_path) == {}


# -- object sets (--objects) --------------------------------------------------------------------------------------

def _bad_set(tmp_path: Path, kind: str, dataset: Path) -> Path:
    """An ``--objects`` value that is no usable object set, made from a copy of the shipped one as ``kind`` says."""
    from posegrasp.catalog import DEFAULT_SET

    if kind == "missing":
        return tmp_path / "none"
    if kind == "dataset":
        return dataset
    root = Path(shutil.copytree(DEFAULT_SET, tmp_path / "set", ignore=shutil.ignore_patterns("*.py", "__pycache__")))
    if kind == "no object file":
        (root / "objects" / "obj_000003.json").unlink()
    elif kind == "inconsistent":
        _edit_json(root / "objects" / "obj_000002.json", lambda d: d.update(name="rod"))
    elif kind == "other model":
        shutil.copy(root / "models" / "obj_000001.ply", root / "models" / "obj_000002.ply")
    return root


OBJECT_COMMANDS = {
    "scene": ["scene", "--resolution", "64x48"],
    "datagen": ["datagen", "--scenes", "1", "--views", "1", "--resolution", "64x48", "--workers", "1", "--no-progress"],
    "trials": ["trials", "--episodes", "1", "--workers", "1", "--no-progress"],
}


@pytest.mark.parametrize("command", OBJECT_COMMANDS)
@pytest.mark.parametrize("kind, words", [
    ("missing", "does not exist"),
    ("dataset", "is a BOP dataset, not an object set"),
    ("no object file", "obj_000003.json is missing"),
    ("inconsistent", "says obj_id 2 'rod', the manifest 2 'long_cuboid'"),
    ("other model", "obj_000002.ply does not match its models_info.json entry"),
])
def test_objects_that_are_no_object_set(capsys, dataset, tmp_path, command, kind, words):
    objects = _bad_set(tmp_path / "in", kind, dataset)
    before, data_before = snapshot(tmp_path), snapshot(dataset)
    refused(capsys, [*OBJECT_COMMANDS[command], "--objects", objects, "--out", tmp_path / "out"], words)
    assert snapshot(tmp_path) == before and snapshot(dataset) == data_before


# -- trials: a BOP results file (--perception bop-csv:) and the capture export options -----------------------------

CSV_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
CSV_ROW = "0,0,1,0.9,1 0 0 0 1 0 0 0 1,10 -20 500,-1"


@pytest.mark.parametrize("lines, words", [
    (["scene_id,im_id,obj_id,score,R,t", CSV_ROW], "line 1: the header must be scene_id,im_id,obj_id,score,R,t,time"),
    ([], "line 1: the header must be"),
    ([CSV_HEADER, "0,0,1,0.9,1 0 0 0 1 0 0 0 1,10 -20 5e2x,-1"], "line 2: t '10 -20 5e2x' is not 3 finite numbers"),
    ([CSV_HEADER, "0,0,1,nan,1 0 0 0 1 0 0 0 1,10 -20 500,-1"], "line 2: score 'nan' is not 1 finite number"),
    ([CSV_HEADER, "0,0,1,0.9,1 0 0 0 1 0 0 0 NaN,10 -20 500,-1"], "line 2: R '1 0 0 0 1 0 0 0 NaN' is not 9 finite"),
    ([CSV_HEADER, "0,0,1,0.9,1 0 0 0 1 0,10 -20 500,-1"], "line 2: R '1 0 0 0 1 0' is not 9 finite numbers"),
    ([CSV_HEADER, "0,0,1,0.9,1 0 0 0 1 0 0 0 1,10 -20 500"], "line 2: expected 7 fields"),
    ([CSV_HEADER, "0.5,0,1,0.9,1 0 0 0 1 0 0 0 1,10 -20 500,-1"], "line 2: scene_id '0.5' is not a non-negative integer"),
    ([CSV_HEADER, "0,0,1,0.9,1 0 0 0 2 0 0 0 1,10 -20 500,-1"], "line 2: R is not orthonormal"),
    ([CSV_HEADER, "0,0,1,0.9,1 0 0 0 -1 0 0 0 1,10 -20 500,-1"], "line 2: R has determinant -1"),
    ([CSV_HEADER, "0,0,1,0.9,1 0 0 0 1 0 0 0 1,0.01 -0.02 0.5,-1"], "BOP results give t in mm, not metres"),
    ([CSV_HEADER, "0,0,1,0.9,1 0 0 0 1 0 0 0 1,10 -20 -500,-1"], "line 2: t = 10 -20 -500 is -500 mm in front"),
    ([CSV_HEADER, "0,0,1,0.9,1 0 0 0 1 0 0 0 1,10 -20 500000,-1"], "mm is over 5 m from the camera"),
    ([CSV_HEADER, "0,0,1,0.9,1 0 0 0 1 0 0 0 1,1e300 -20 500,-1"], "mm is over 5 m from the camera"),
    ([CSV_HEADER, "0,0,99,0.9,1 0 0 0 1 0 0 0 1,10 -20 500,-1"], "line 2: obj_id 99 is not in the object set"),
    ([CSV_HEADER, CSV_ROW, "0,0,2,0.9,1 0 0 0 1 0 0 0 1,10 -20 500,-1", CSV_ROW.replace("0.9", "0.1")],
     "line 4: duplicates line 2 (same scene_id, im_id, obj_id, R and t)"),
    ([CSV_HEADER, CSV_ROW, "", CSV_ROW], "line 3: empty line"),
    ([CSV_HEADER, CSV_ROW.replace("0,0,1", "5,0,1")], "line 2: scene_id 5, im_id 0 is no frame of this campaign"),
    ([CSV_HEADER, CSV_ROW.replace("0,0,1", "0,1,1")], "im_id 1 is no frame of this campaign (scene_id = episode, 0-1; "
                                                      "im_id 0 in the pick-place task)"),
])
def test_trials_bad_bop_results_file(capsys, tmp_path, lines, words):
    (tmp_path / "r.csv").write_text("".join(f"{x}\n" for x in lines))
    before = snapshot(tmp_path)
    refused(capsys, ["trials", "--out", tmp_path / "run", "--episodes", "2", "--perception",
                     f"bop-csv:{tmp_path / 'r.csv'}"], words)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("spec, words", [("bop-csv", "needs a results file"), ("bop-csv:{d}/none.csv", "does not exist"),
                                         ("bop-csv:{d}", "cannot read results file")])
def test_trials_missing_bop_results_file(capsys, tmp_path, spec, words):
    before = snapshot(tmp_path)
    refused(capsys, ["trials", "--out", tmp_path / "run", "--perception", spec.format(d=tmp_path)], words)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("argv, words", [
    (["--captures-only"], "--captures-only needs --export-captures DIR"),
    (["--captures-only", "--export-captures", "{d}/ex", "--out", "{d}/run"], "drop --out"),
    (["--export-captures", "{d}/run", "--out", "{d}/run"], "is the --out folder"),
    (["--export-captures", "{d}/ex"], "--out is required"),
    (["--export-captures", "{d}/ex", "--out", "{d}/run", "--sweep-noise"], "not --sweep-noise"),
    (["--export-captures", "{d}/file", "--out", "{d}/run"], "--export-captures {d}/file is a file"),
])
def test_trials_bad_export_options(capsys, tmp_path, argv, words):
    (tmp_path / "file").write_text("x")
    before = snapshot(tmp_path)
    refused(capsys, ["trials", "--episodes", "1", *[a.format(d=tmp_path) for a in argv]], words.format(d=tmp_path))
    assert snapshot(tmp_path) == before
