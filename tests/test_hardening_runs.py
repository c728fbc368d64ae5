"""Run folders, settings, records and plug-ins under hostile input: nothing finished is lost, no foreign folder is
written into, every bad setting or record is one line naming the file and key, and a plug-in that exits, crashes,
changes directory or hangs fails its episode (or the campaign's start) with one line naming it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from helpers import run_cli
from posegrasp.config import from_dict
from posegrasp.errors import ConfigError, PosegraspError, WeightsError
from posegrasp.grasping.config import TrialConfig
from posegrasp.perception.checkpoint import load_model, read_state
from posegrasp.perception.train_seg import SegTrainConfig
from posegrasp.perception.training import checked_state

ROOT = Path(__file__).resolve().parents[1]

#: A plug-in misbehaving as ``$EVIL`` says at import, as ARGS says in its factory, and by episode in estimate.
EVIL = '''
import ctypes, os, sys, time


def misbehave(mode):
    if mode == "exit":
        os._exit(3)
    if mode == "sysexit":
        sys.exit(7)
    if mode == "segv":
        ctypes.string_at(0)
    if mode == "sleep":
        time.sleep(3600)
    if mode == "chdir":
        os.chdir(os.environ["ELSEWHERE"])


misbehave(os.environ.get("EVIL", ""))

class P:
    name = "evil"

    def estimate(self, obs, seed):
        misbehave(["exit", "sysexit", "segv", "sleep", "chdir"][obs.scene_id])
        return []

def make(args):
    misbehave(args)
    return P()
'''


def _one_line_error(run, *words: str) -> str:
    """The single stderr line of a refused command, checked for ``words``."""
    assert run.returncode == 2, (run.returncode, run.stderr[-2000:])
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr[-2000:]
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def _trials(out: Path, episodes: int, *extra: str, **kw):
    return run_cli("trials", "--episodes", str(episodes), "--workers", "1", "--no-progress", "--blocks", "1",
                   "--out", str(out), *extra, **kw)


@pytest.fixture(scope="module")
def run2(tmp_path_factory) -> Path:
    """A finished 2-episode oracle campaign."""
    out = tmp_path_factory.mktemp("run") / "r"
    assert _trials(out, 2).returncode == 0
    return out


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_resume_never_drops_finished_episodes_nor_adopts_records(run2, tmp_path):
    run = tmp_path / "r"
    shutil.copytree(run2, run)
    before = _snapshot(run)
    _one_line_error(_trials(run, 1), "finished episodes up to 1", "--episodes 2 or more")
    assert _snapshot(run) == before
    (run / "campaign.json").unlink()
    before = _snapshot(run)
    _one_line_error(_trials(run, 2), "no campaign.json")
    assert _snapshot(run) == before


@pytest.mark.parametrize("key, value", [("scene_seed", 0), ("n_blocks", -4), ("seed", 3)])
def test_resume_refuses_a_record_its_campaign_did_not_draw(run2, tmp_path, key, value):
    run = tmp_path / "r"
    shutil.copytree(run2, run)
    lines = (run / "episodes.jsonl").read_text().splitlines()
    rec = json.loads(lines[1])
    rec[key] = value
    (run / "episodes.jsonl").write_text("\n".join([lines[0], json.dumps(rec)]) + "\n")
    before = _snapshot(run)
    _one_line_error(_trials(run, 2), "episode 1 of", "does not re-simulate")
    assert _snapshot(run) == before


def test_writing_commands_refuse_folders_and_files_they_did_not_write(tmp_path):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    for args in (("trials", "--episodes", "1", "--out", str(foreign)),
                 ("trials", "--sweep-noise", "--episodes", "1", "--out", str(foreign)),
                 ("datagen", "--scenes", "1", "--views", "1", "--out", str(foreign)),
                 ("scene", "--out", str(foreign))):
        _one_line_error(run_cli(*args), str(foreign), "not written by this command")
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]
    other = tmp_path / "other.json"
    other.write_text('{"mine": 1}')
    _one_line_error(run_cli("calibrate", "--out", str(other), "--poses", "3"), "not a hand-eye calibration")
    assert other.read_text() == '{"mine": 1}'


def test_eval_and_capture_exports_refuse_folders_they_did_not_write(tmp_path, tiny_bop):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    dataset = _snapshot(tiny_bop)
    model = ROOT / "assets" / "perception" / "model"
    for out in (foreign, tiny_bop / "train_pbr", tiny_bop):  # a stranger's folder, a dataset and its own split
        _one_line_error(run_cli("eval", "--data", str(tiny_bop), "--weights", str(model), "--split", "train_pbr",
                                "--out", str(out), "--no-progress"), str(out), "not written by this command")
    for args in (("--export-captures", str(foreign), "--out", str(tmp_path / "r")),
                 ("--captures-only", "--export-captures", str(tiny_bop))):
        _one_line_error(run_cli("trials", "--episodes", "1", "--workers", "1", "--no-progress", *args),
                        "not written by this command")
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"] and not (tmp_path / "r").exists()
    assert _snapshot(tiny_bop) == dataset


def test_scene_rewrites_its_own_folder(tmp_path):
    for _ in range(2):
        run = run_cli("scene", "--seed", "1", "--blocks", "1", "--resolution", "64x48", "--out", str(tmp_path / "s"))
        assert run.returncode == 0, run.stderr
    assert (tmp_path / "s" / "scene.json").is_file()


@pytest.mark.parametrize("toml, words", [
    ("[control]\ndt = 0\n", ["control.dt", "out of range"]),
    ("[control]\ndt = nan\n", ["control.dt", "finite"]),
    ("[control]\ndt = \"fast\"\n", ["control.dt", "number"]),
    ("min_blocks = 1000\n", ["min_blocks", "out of range"]),
])
def test_trial_settings_are_typed_and_bounded(tmp_path, toml, words):
    cfg = tmp_path / "t.toml"
    cfg.write_text(toml)
    _one_line_error(_trials(tmp_path / "r", 1, "--config", str(cfg)), str(cfg), *words)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("data, key", [
    ({"batch_size": 0}, "batch_size"), ({"batch_size": 100000}, "batch_size"), ({"threads": 100000}, "threads"),
    ({"workers": -1}, "workers"), ({"model": {"input_size": [100000, 100000]}}, "model.input_size"),
    ({"lr": float("inf")}, "lr"), ({"steps": True}, "steps"),
])
def test_training_settings_are_bounded(data, key):
    with pytest.raises(ConfigError, match=rf"^seg.toml.{key}"):
        from_dict(SegTrainConfig, data, "seg.toml")


def test_a_seg_batch_leaving_batch_norm_one_value_is_refused(tmp_path, tiny_bop):
    cfg = tmp_path / "seg.toml"
    cfg.write_text("[seg]\nbatch_size = 1\n[seg.model]\ninput_size = [32, 32]\n")
    run = run_cli("train", "seg", "--data", str(tiny_bop), "--out", str(tmp_path / "run"), "--config", str(cfg),
                  "--steps", "1", "--no-progress")
    _one_line_error(run, str(cfg), "batch_size = 1 with model.input_size = [32, 32]", "batch normalisation")
    assert not (tmp_path / "run").exists()
    from_dict(SegTrainConfig, {"batch_size": 1, "model": {"input_size": [64, 32]}})  # two values per channel
    from_dict(SegTrainConfig, {"batch_size": 1, "model": {"input_size": [32, 32], "batch_norm": False}})


def test_counts_on_the_command_line_are_bounded(tmp_path):
    _one_line_error(run_cli("datagen", "--views", "1000000000", "--out", str(tmp_path / "d")), "--views", "10000")
    _one_line_error(run_cli("datagen", "--views", "1e9", "--out", str(tmp_path / "d")), "--views")
    _one_line_error(_trials(tmp_path / "r", 1, "--noise", "rotation"), "--noise", "--sweep-noise")
    assert not (tmp_path / "d").exists() and not (tmp_path / "r").exists()


def test_training_state_is_checked_before_resuming():
    fresh = {"step": 0, "lr": 0.01, "best_val_dis": None, "decayed": False}
    ok = {"step": 40, "lr": 0.005, "best_val_dis": 0.02, "decayed": True, "elapsed_s": 3.5}
    assert checked_state(ok, fresh, Path("state.json")) == ok
    for bad, key in (({"step": -5}, "step"), ({"step": 2.5}, "step"), ({"lr": "fast"}, "lr"),
                     ({"lr": float("nan")}, "lr"), ({"decayed": 1}, "decayed"), ({"elapsed_s": -1.0}, "elapsed_s"),
                     ({"best_val_dis": "x"}, "best_val_dis")):
        with pytest.raises(WeightsError, match=rf"state.json: {key} = "):
            checked_state({**ok, **bad}, fresh, Path("state.json"))
    with pytest.raises(WeightsError, match="'lr' is missing"):
        checked_state({"step": 3}, fresh, Path("state.json"))


@pytest.fixture(scope="module")
def tiny_bop(tmp_path_factory) -> Path:
    """Two scenes of two 64x48 views made by datagen."""
    root = tmp_path_factory.mktemp("ds") / "ds"
    run = run_cli("datagen", "--out", str(root), "--scenes", "2", "--views", "2", "--resolution", "64x48", "--blocks",
                  "2", "--workers", "1", "--no-progress")
    assert run.returncode == 0, run.stderr[-2000:]
    return root


@pytest.mark.slow
def test_train_resume_with_a_bad_state_keeps_the_metrics(tmp_path, tiny_bop):
    cfg = tmp_path / "seg.toml"
    cfg.write_text("[seg]\nsteps = 2\nbatch_size = 2\nlog_every = 1\ncheckpoint_every = 1\neval_every = 100\n"
                   "[seg.model]\ninput_size = [64, 64]\nwidth = 0.05\n")
    out = tmp_path / "run"
    first = run_cli("train", "seg", "--data", str(tiny_bop), "--out", str(out), "--config", str(cfg),
                    "--no-progress")
    assert first.returncode == 0, first.stderr[-2000:]
    metrics = (out / "seg_metrics.csv").read_bytes()
    state = out / "seg" / "state.json"
    good = state.read_bytes()
    (out / "seg_metrics.csv").write_bytes(b"\x8f\x00")
    run = run_cli("train", "seg", "--data", str(tiny_bop), "--out", str(out), "--config", str(cfg), "--steps", "3",
                  "--resume", "--no-progress")
    _one_line_error(run, "seg_metrics.csv is not a metrics CSV")
    assert state.read_bytes() == good and (out / "seg_metrics.csv").read_bytes() == b"\x8f\x00"
    (out / "seg_metrics.csv").write_bytes(metrics)
    for bad in ('{"step": -5, "lr": 0.01}', '{"step": "2", "lr": 0.01}', '{"step": 2, "lr": NaN}', "[]"):
        state.write_text(bad)
        run = run_cli("train", "seg", "--data", str(tiny_bop), "--out", str(out), "--config", str(cfg),
                      "--steps", "3", "--resume", "--no-progress")
        _one_line_error(run, "state.json")
        assert (out / "seg_metrics.csv").read_bytes() == metrics


def test_object_set_numbers_are_checked(tmp_path):
    for key, value, words in (("mass_kg", float("nan"), "mass_kg = NaN"), ("friction", "high", 'friction = "high"'),
                              ("rgba", [1, 0, 0], "rgba"),
                              ("collision_volume_ratio", float("inf"), "collision_volume_ratio = Infinity")):
        root = tmp_path / key
        shutil.copytree(ROOT / "assets" / "blocks", root, ignore=shutil.ignore_patterns("*.py"))
        obj = root / "objects" / "obj_000001.json"
        d = json.loads(obj.read_text())
        d[key] = value
        obj.write_text(json.dumps(d))
        _one_line_error(_trials(tmp_path / f"r_{key}", 1, "--objects", str(root)), str(obj), words)
        assert not (tmp_path / f"r_{key}").exists()


@pytest.mark.parametrize("edit, words", [(lambda m: m.update(version=True), "version True is not"),
                                         (lambda m: m.update(objects={"1": "cube"}), "objects must be a list"),
                                         (lambda m: m["objects"][0].update(obj_id="1"), "an integer obj_id")])
def test_object_set_manifest_is_typed(tmp_path, edit, words):
    from posegrasp.errors import DatasetError
    from posegrasp.objset import load_object_set

    root = tmp_path / "set"
    shutil.copytree(ROOT / "assets" / "blocks", root, ignore=shutil.ignore_patterns("*.py"))
    man = json.loads((root / "objectset.json").read_text())
    edit(man)
    (root / "objectset.json").write_text(json.dumps(man))
    with pytest.raises(DatasetError, match=words):
        load_object_set(root)
    (root / "objectset.json").write_text("[]")
    with pytest.raises(DatasetError, match="expected a JSON object, got list"):
        load_object_set(root)


def test_non_finite_weights_are_refused(tmp_path):
    src = ROOT / "assets" / "perception" / "model" / "seg"
    ckpt = tmp_path / "seg"
    shutil.copytree(src, ckpt)
    tensors = load_file(ckpt / "model.safetensors")
    name = sorted(k for k, t in tensors.items() if t.is_floating_point())[0]
    tensors[name] = torch.full_like(tensors[name], float("nan"))
    save_file(tensors, ckpt / "model.safetensors")
    with pytest.raises(WeightsError, match=rf"tensor '{name}' has \d+ of \d+ values NaN or infinite"):
        load_model(ckpt)


@pytest.mark.parametrize("file, text, words", [
    ("config.json", None, "version = 2; expected 1"), ("config.json", b"\xff\x00", "UTF-8 JSON text"),
    ("config.json", '{"version": -Infinity}', "-Infinity is not a JSON number"),
    ("config.json", '{"format": "posegrasp-perception", "version": 1, "stage": "seg", "train": -1}',
     "train = -1; expected a JSON object"),
    ("state.json", '{"step": NaN}', "NaN is not a JSON number"), ("state.json", b"\x9c", "UTF-8 JSON text")])
def test_checkpoint_json_is_strict(tmp_path, file, text, words):
    ckpt = tmp_path / "seg"
    shutil.copytree(ROOT / "assets" / "perception" / "model" / "seg", ckpt)
    p = ckpt / file
    if text is None:
        p.write_text(p.read_text().replace('"version": 1', '"version": 2'))
    else:
        p.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(WeightsError, match=words):
        load_model(ckpt) if file == "config.json" else read_state(ckpt)



@pytest.mark.parametrize("stage, key", [("pose", "head_widths"), ("seg", "up_channels"), ("cls", "widths")])
def test_a_layer_of_width_zero_is_refused_before_a_module_is_built(tmp_path, recwarn, stage, key):
    ckpt = tmp_path / stage
    shutil.copytree(ROOT / "assets" / "perception" / "model" / stage, ckpt)
    cfg = json.loads((ckpt / "config.json").read_text())
    cfg["model"][key][-1] = 0
    (ckpt / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(PosegraspError, match=rf"{key} = .* is out of range: use 1 to 4096"):
        load_model(ckpt)
    assert not [w for w in recwarn if "zero-element" in str(w.message)]  # torch's warning: a module was built

def test_compare_checks_every_record(run2, tmp_path):
    run = tmp_path / "r"
    shutil.copytree(run2, run)
    lines = (run / "episodes.jsonl").read_text().splitlines()
    rec = json.loads(lines[0])
    rec["target"] = 7
    (run / "episodes.jsonl").write_text("\n".join([json.dumps(rec), *lines[1:]]) + "\n")
    _one_line_error(run_cli("compare", str(run2), str(run)), "episodes.jsonl line 1", "target")
    rec["target"] = {"type": "cube"}  # a target without its other fields
    (run / "episodes.jsonl").write_text("\n".join([json.dumps(rec), *lines[1:]]) + "\n")
    for cmd in (("compare", str(run2), str(run)), ("report", str(run))):
        _one_line_error(run_cli(*cmd), "episodes.jsonl line 1", "target: missing key(s) ['instance', 'class_ok'")


@pytest.mark.parametrize("edit", [lambda c: c.update(perception=7), lambda c: c.update(seed=-1),
                                  lambda c: c["T_gripper_cam"][0].__setitem__(0, "1"), lambda c: c.update(objects=[]),
                                  lambda c: c.update(objects={"name": "blocks", "path": -1, "sha256": "0"})])
def test_a_mistyped_campaign_is_refused(run2, tmp_path, edit):
    run = tmp_path / "r"
    shutil.copytree(run2, run)
    campaign = json.loads((run / "campaign.json").read_text())
    edit(campaign)
    (run / "campaign.json").write_text(json.dumps(campaign))
    before = _snapshot(run)
    _one_line_error(run_cli("compare", str(run2), str(run)), "campaign.json is corrupt")
    _one_line_error(_trials(run, 2), str(run), "campaign")
    assert _snapshot(run) == before


def test_report_names_the_line_of_a_malformed_record(run2, tmp_path):
    run = tmp_path / "r"
    shutil.copytree(run2, run)
    lines = (run / "episodes.jsonl").read_text().splitlines()
    for edit, words in ((lambda r: r.pop("outcome"), "missing field(s) ['outcome']"),
                        (lambda r: r.update(outcome="maybe"), "outcome = \"maybe\""),
                        (lambda r: r.update(outcome="failure", failure="bad luck"), "failure = \"bad luck\"")):
        rec = json.loads(lines[1])
        edit(rec)
        (run / "episodes.jsonl").write_text("\n".join([lines[0], json.dumps(rec)]) + "\n")
        _one_line_error(run_cli("report", str(run)), "episodes.jsonl line 2", words)


@pytest.mark.parametrize("mode, words", [
    ("exit", "exited with status 3"), ("sysexit", "raised SystemExit: 7"), ("segv", "crashed (signal SIGSEGV)"),
    ("sleep", "did not finish within 3 s (TrialConfig.perception_timeout_s)")])
def test_a_plugin_failing_at_import_stops_the_start_in_one_line(tmp_path, mode, words):
    (tmp_path / "evil.py").write_text(EVIL)
    cfg = tmp_path / "t.toml"
    cfg.write_text("perception_timeout_s = 3.0\n")
    run = _trials(tmp_path / "r", 1, "--config", str(cfg), "--perception", f"py:{tmp_path / 'evil.py'}:make",
                  env={**_env(), "EVIL": mode}, timeout=120)
    _one_line_error(run, "evil.py:make", words)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("factory, words", [("exit", "exited with status 3"), ("segv", "SIGSEGV"),
                                            ("sleep", "did not finish within 3 s")])
def test_a_plugin_failing_in_its_factory_stops_the_start_in_one_line(tmp_path, factory, words):
    (tmp_path / "evil.py").write_text(EVIL)
    cfg = tmp_path / "t.toml"
    cfg.write_text("perception_timeout_s = 3.0\n")
    run = _trials(tmp_path / "r", 1, "--config", str(cfg), "--perception", f"py:{tmp_path / 'evil.py'}:make:{factory}",
                  env=_env(), timeout=120)
    _one_line_error(run, f"evil.py:make:{factory}", "loading it (import and factory)", words)


@pytest.mark.slow
@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_plugin_exiting_crashing_or_hanging_in_estimate_fails_its_episode(tmp_path, workers):
    (tmp_path / "evil.py").write_text(EVIL)
    cfg = tmp_path / "t.toml"
    cfg.write_text("perception_timeout_s = 3.0\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    run = run_cli("trials", "--episodes", "5", "--workers", workers, "--no-progress", "--blocks", "1", "--config",
                  str(cfg), "--perception", f"py:{tmp_path / 'evil.py'}:make", "--out", "r",
                  env={**_env(), "ELSEWHERE": str(elsewhere)}, cwd=cwd, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    recs = [json.loads(line) for line in (cwd / "r" / "episodes.jsonl").read_text().splitlines()]
    assert [r["failure"] for r in recs] == ["perception error"] * 4 + ["no detection"]
    for r, words in zip(recs, ["exited with status 3 in estimate", "raised SystemExit: 7",
                               "crashed (signal SIGSEGV) in estimate", "did not answer within 3 s"]):
        assert r["perception_error"].startswith("provider 'evil' ") and words in r["perception_error"], r
    assert list(elsewhere.iterdir()) == [] and (cwd / "r" / "summary.json").is_file()  # the chdir moved nothing


def _env() -> dict[str, str]:
    import os

    return dict(os.environ)
