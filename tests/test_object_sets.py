"""``--objects SET``: an object set imported from meshes the test makes drives ``scene``, ``datagen`` and ``trials``;
the dataset holds the set's models and passes ``dataset check``, the runs record their set, and resuming or
comparing across sets is refused with one line and nothing changed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from helpers import refused
from test_bad_input import snapshot

from posegrasp import bop
from posegrasp.catalog import DEFAULT_SET, load_catalog, set_record
from posegrasp.cli import main
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.tasks import with_set
from posegrasp.grasping.tasks.standing import standing_R


@pytest.fixture(scope="module")
def parts(tmp_path_factory) -> Path:
    """Two convex parts (no CoACD, fast): a bar as OBJ in metres and a post as STL in millimetres, lying on its side."""
    d = tmp_path_factory.mktemp("meshes")
    trimesh.creation.box([0.05, 0.03, 0.025]).export(d / "bar.obj")
    post = trimesh.creation.cylinder(0.015, 0.04, sections=24)
    post.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])).apply_scale(1000.0)
    post.export(d / "post.stl")
    out = d / "parts"
    assert main(["objects", "import", str(d / "bar.obj"), str(d / "post.stl"), "--unit", "m", "mm", "--out", str(out),
                 "--no-progress"]) == 0
    return out


@pytest.mark.slow
def test_the_catalogue_loads_a_set_and_its_upright_data(parts):
    cat = load_catalog(parts)
    assert list(cat) == ["bar", "post"] and [b.obj_id for b in cat.values()] == [1, 2]
    assert cat["bar"].mass == pytest.approx(1050.0 * 0.05 * 0.03 * 0.025, rel=1e-6)
    assert set_record(parts)["name"] == "parts" and set_record(parts)["sha256"] != set_record()["sha256"]
    assert set_record()["path"] == str(DEFAULT_SET)
    roundabout = parts.parent / ".." / parts.parent.name / "parts"
    assert with_set(TrialConfig(), roundabout).scene.workcell.objects == str(parts)  # absolute, for the workers
    # an imported set holds firmly in every task, the shipped blocks in kitting and stack; a campaign's own wins
    assert with_set(TrialConfig(), parts).firm_hold_tasks == ("pick-place", "kitting", "stack")
    assert with_set(TrialConfig()).firm_hold_tasks == ("kitting", "stack", "bin-pick")
    assert with_set(TrialConfig(firm_hold_tasks=("stack",)), parts).firm_hold_tasks == ("stack",)


def test_scene_draws_from_the_set(parts, tmp_path):
    out = tmp_path / "scene"
    assert main(["scene", "--objects", str(parts), "--blocks", "3", "--resolution", "64x48", "--out", str(out)]) == 0
    types = {b["type"] for b in json.loads((out / "scene.json").read_text())["blocks"]}
    assert types and types <= {"bar", "post"}


def test_datagen_on_a_set_passes_dataset_check_and_stays_on_its_set(parts, tmp_path, capsys):
    ds = tmp_path / "ds"
    args = ["datagen", "--out", str(ds), "--scenes", "1", "--views", "2", "--resolution", "64x48", "--blocks", "2",
            "--workers", "1", "--no-progress"]
    assert main([*args, "--objects", str(parts)]) == 0
    for f in (parts / "models").iterdir():  # the set's models, byte for byte
        assert (ds / "models" / f.name).read_bytes() == f.read_bytes()
    assert sorted(p.name for p in (ds / "models").iterdir()) == sorted(p.name for p in (parts / "models").iterdir())
    gt = bop.load_scene_gt(bop.scene_dir(ds, "train_pbr", 0) / "scene_gt.json")
    assert {o for anns in gt.values() for o, _ in anns} <= {1, 2}
    settings = json.loads((ds / "train_pbr" / "datagen_config.json").read_text())
    assert settings["config"]["workcell"]["objects"] == str(parts)
    capsys.readouterr()
    assert main(["dataset", "check", str(ds)]) == 0
    before = snapshot(ds)
    refused(capsys, [*args, "--scenes", "2"], "was generated from another object set")  # the shipped blocks
    assert snapshot(ds) == before


@pytest.mark.slow
def test_trials_record_their_set_and_compare_refuses_another(parts, tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    trial = ["trials", "--episodes", "1", "--seed", "3", "--workers", "1", "--no-progress"]
    assert main([*trial, "--objects", str(parts), "--out", str(a)]) == 0
    rec = set_record(parts)
    assert json.loads((a / "campaign.json").read_text())["objects"] == rec
    assert json.loads((a / "summary.json").read_text())["objects"] == rec
    assert "object set</td><td>parts (" in (a / "report.html").read_text()
    capsys.readouterr()
    before = snapshot(a)
    refused(capsys, [*trial, "--out", str(a)], "holds a campaign on the object set parts")  # resumed on the blocks
    assert snapshot(a) == before
    assert main([*trial, "--out", str(b)]) == 0
    assert json.loads((b / "campaign.json").read_text())["objects"]["name"] == "blocks"
    capsys.readouterr()
    refused(capsys, ["compare", str(a), str(b)], "run A ran on the object set parts")
    refused(capsys, ["compare", str(b / "episodes.jsonl"), str(a)], "and run B on parts")
    assert main(["compare", str(a), str(a / "episodes.jsonl")]) == 0


def test_a_set_that_cannot_serve_the_stack_task_is_refused(tmp_path, capsys):
    cone = trimesh.creation.cone(0.02, 0.04, sections=24)  # a pointed top: nothing stacks on it
    cone.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0])).export(tmp_path / "cone.obj")
    cones = tmp_path / "cones"
    assert main(["objects", "import", str(tmp_path / "cone.obj"), "--out", str(cones), "--no-progress"]) == 0
    cone = load_catalog(cones)["cone"]  # made apex down: it stands on its base, the set's upright quat turns it so
    assert not cone.flat_top and cone.upright_down[2] == pytest.approx(1.0)
    np.testing.assert_allclose(standing_R(cone) @ cone.upright_down, [0.0, 0.0, -1.0], atol=1e-6)
    capsys.readouterr()
    refused(capsys, ["trials", "--task", "stack", "--objects", str(cones), "--episodes", "1", "--out",
                     str(tmp_path / "r")], "task stack needs an object type with a flat top")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("edit", [
    lambda man, obj: man["objects"][0].update(file="/etc/hostname"),
    lambda man, obj: man["objects"][0].update(file="../objectset.json"),
    lambda man, obj: obj.update(model="../../blocks/models/obj_000001.ply"),
    lambda man, obj: obj.update(model=7),
])
def test_a_set_naming_a_file_outside_its_folder_is_refused(tmp_path, edit):
    import shutil

    from posegrasp.errors import DatasetError
    from posegrasp.objset import load_object_set

    root = tmp_path / "set"
    shutil.copytree(DEFAULT_SET, root)
    man = json.loads((root / "objectset.json").read_text())
    obj_file = root / man["objects"][0]["file"]
    obj = json.loads(obj_file.read_text())
    edit(man, obj)
    (root / "objectset.json").write_text(json.dumps(man))
    obj_file.write_text(json.dumps(obj))
    with pytest.raises(DatasetError, match="is not a file inside the set folder"):
        load_object_set(root)
