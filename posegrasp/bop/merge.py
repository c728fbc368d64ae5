"""``posegrasp dataset merge``: one BOP root holding the scenes of several, renumbered, to train on them together.

``datagen`` refuses to add scenes made with other settings (another ``--scene``, seed or object count) to a root,
and ``trials --export-captures`` writes a root of its own: a training set that mixes tote, pile and tabletop scenes
and the robot's looks is their merge. The sources must share ``models/models_info.json`` and ``camera.json`` (the
same object set and image size); the merged root takes ``models/``, ``models_eval/`` and ``camera.json`` from the
first and the scenes of each source split in order, numbered from 0. ``merged_from.json`` in the split folder says
which source scene each became. The root is written beside its place and renamed into it at the end: a failed or
killed merge leaves nothing.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from posegrasp import bop, inputs
from posegrasp.errors import DatasetError, UserError
from posegrasp.io import write_json, writing_into

#: The root's files every source must have byte for byte as the first has them.
SHARED = ("models/models_info.json", "camera.json")


def parse_source(text: str) -> tuple[Path, str | None]:
    """``ROOT`` or ``ROOT:SPLIT`` -> (root, split or None: the root's only split)."""
    root, sep, split = text.rpartition(":")
    return (Path(root), split) if sep and split and "/" not in split else (Path(text), None)


def source_split(root: Path, split: str | None) -> str:
    """The split of ``root`` to merge: ``split``, or its only one; ``DatasetError`` naming what is missing."""
    from posegrasp.bop.check import find_splits

    if not root.is_dir():
        raise DatasetError(f"dataset folder {root} does not exist")
    splits = find_splits(root)
    if split is None:
        if len(splits) != 1:
            raise DatasetError(f"{root} has splits {splits or 'none'}; name one as {root}:SPLIT")
        return splits[0]
    if split not in splits:
        raise DatasetError(f"{root} has no split {split!r} (it has {splits or 'none'})")
    return split


def merge_datasets(out: str | Path, sources: list[tuple[Path, str | None]], split: str = "train_pbr") -> int:
    """Write the BOP root ``out`` (which must not exist) with the scenes of every ``(root, split)`` of ``sources``
    in ``out/<split>``, numbered in order from 0; returns the number of scenes."""
    out = Path(out)
    if os.path.lexists(out):
        raise UserError(f"{out} already exists; give a new folder to merge into")
    picked = [(root, source_split(root, s)) for root, s in sources]
    first = picked[0][0]
    for root, _ in picked:
        for name in SHARED:
            if not os.path.lexists(root / name):
                raise DatasetError(f"{root / name} does not exist; each source must be a BOP root with models")
            if inputs.read_bytes(root / name, "json", DatasetError) != inputs.read_bytes(first / name, "json",
                                                                                          DatasetError):
                raise DatasetError(f"{root / name} differs from {first / name}; merge datasets of one object set "
                                   "and one image size")
    with writing_into(out.parent):
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
        try:
            os.chmod(tmp, 0o755)  # mkdtemp makes it private; the root it becomes is a dataset like any other
            for name in ("models", "models_eval"):
                if (first / name).is_dir():
                    _copy_tree(first / name, tmp / name)
            shutil.copy2(first / "camera.json", tmp / "camera.json")
            origin = []
            for root, s in picked:
                for sid in bop.list_scenes(root, s):
                    _copy_tree(bop.scene_dir(root, s, sid), bop.scene_dir(tmp, split, len(origin)))
                    origin.append({"scene_id": len(origin), "source": str(root), "split": s, "source_scene_id": sid})
            write_json(bop.split_dir(tmp, split) / "merged_from.json", origin)
            os.replace(tmp, out)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return len(origin)


def _copy_tree(src: Path, dst: Path) -> None:
    """Copy the files under ``src`` to ``dst``, the first error raised as it is (``shutil.copytree`` gathers them
    into one without an errno: a full disk would not read as one)."""
    for p in sorted(src.rglob("*")):
        if p.is_file():
            (dst / p.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(p, dst / p.relative_to(src))
