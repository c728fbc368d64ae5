"""The instance classifier's crop cache: ``ClsDataset``'s crops (N, C, S, S) float16 in one ``.npy`` file, with a
``.json`` beside it holding their labels and the key they were computed for (``perception.data.ClsDataset``)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from posegrasp import bop
from posegrasp import io as pio


def fingerprint(records: list[bop.ImageRecord]) -> str:
    """sha256 of the records' ids, cameras and annotated poses: a dataset generated anew in the same place differs."""
    h = hashlib.sha256()
    for r in records:
        h.update(np.array([r.scene_id, r.im_id], dtype=np.int64).tobytes() + np.asarray(r.camera.K, float).tobytes())
        for g in r.instances:
            h.update(np.int64(g.obj_id).tobytes() + np.asarray(g.T_cam_obj, float).tobytes())
    return h.hexdigest()


def read_crop_cache(path: Path, key: dict) -> tuple[np.ndarray, list[int]] | None:
    """``ClsDataset``'s cached crops (N, C, S, S) float16 (a read-only memory map) and labels, or None when ``path``
    does not hold crops computed for ``key``."""
    meta = path.with_suffix(".json")
    if not (meta.exists() and path.exists()):
        return None
    info = json.loads(meta.read_text())
    if info.get("key") != json.loads(json.dumps(key)):
        return None
    crops = np.load(path, mmap_mode="r")
    return (crops, info["labels"]) if len(crops) == len(info["labels"]) else None


def write_crop_cache(path: Path, key: dict, crops: list[np.ndarray], labels: list[int]
                     ) -> tuple[np.ndarray, list[int]]:
    """Write ``crops`` to ``path`` (one array, filled crop by crop) and the labels and ``key`` beside it, each file
    atomically, the ``.json`` last; returns them as ``read_crop_cache`` does."""
    def fill(tmp: Path) -> None:
        out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16, shape=(len(crops), *crops[0].shape))
        with open(tmp, "r+b") as f:  # the disk space taken now: a full disk is an OSError here, not a SIGBUS later
            os.posix_fallocate(f.fileno(), 0, os.fstat(f.fileno()).st_size)
        for i, x in enumerate(crops):
            out[i] = x
        out.flush()
        del out

    path.with_suffix(".json").unlink(missing_ok=True)  # the old key must not outlive its crops
    pio.atomic_write(path, fill)
    pio.write_json(path.with_suffix(".json"), {"key": key, "labels": labels}, indent=None)
    return np.load(path, mmap_mode="r"), labels
