"""BOP results files: pose estimates as ``scene_id,im_id,obj_id,score,R,t,time`` rows (R row-major, t in mm), written
losslessly and read back with every row checked."""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Iterable

import numpy as np

from posegrasp import inputs
from posegrasp import io as pio
from posegrasp.errors import DatasetError

RESULTS_HEADER = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")
#: Longest line (characters) a result may take.
MAX_LINE = 4096


@dataclass
class PoseResult:
    """One pose estimate for the BOP results CSV: T_cam_obj (4x4 m), score, time (s, -1 unknown)."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    T_cam_obj: np.ndarray
    time: float = -1.0


def results_csv(results: Iterable[PoseResult]) -> bytes:
    """BOP results as CSV bytes: ``scene_id,im_id,obj_id,score,R,t,time``; R row-major, t in mm, space-separated.
    Lossless: R and the score as the shortest decimals that read back as the same floats, t as those of the
    metres with the decimal point moved (``read_results_csv`` gives back the very same poses)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(RESULTS_HEADER)
    for r in results:
        T = np.asarray(r.T_cam_obj, dtype=np.float64)
        w.writerow([r.scene_id, r.im_id, r.obj_id, repr(float(r.score)),
                    " ".join(repr(x) for x in T[:3, :3].ravel().tolist()),
                    " ".join(format(Decimal(repr(x)).scaleb(3), "f") for x in T[:3, 3].tolist()), f"{r.time:.6f}"])
    return buf.getvalue().encode()


def write_results_csv(path: str | Path, results: Iterable[PoseResult]) -> Path:
    """Atomically write BOP results (``results_csv``)."""
    return pio.write_bytes(path, results_csv(results))


def read_results_csv(path: str | Path) -> list[PoseResult]:
    """A BOP results CSV (header ``scene_id,im_id,obj_id,score,R,t,time``; t in mm) as PoseResults (m), in file
    order. A DatasetError naming the line for a wrong header, a missing field, a negative or non-integer id or a
    number that does not parse or is not finite; R is not checked to be a rotation here."""
    p = Path(path)
    if not os.path.lexists(p):
        raise DatasetError(f"results file {p} does not exist")
    try:
        lines = inputs.read_text(p, "csv", DatasetError).splitlines()
    except DatasetError as e:
        raise DatasetError(f"cannot read results file {p}: {inputs.reason(e, p)}") from None
    header = [h.strip() for h in lines[0].split(",")] if lines else []
    if tuple(header) != RESULTS_HEADER:
        raise DatasetError(f"{p} line 1: the header must be {','.join(RESULTS_HEADER)} (BOP results format), got "
                           f"{','.join(header)!r}")
    while len(lines) > 1 and not lines[-1].strip():  # blank lines at the end
        lines.pop()
    out = []
    for n, line in enumerate(lines[1:], start=2):  # result i is on line i + 2
        if len(line) > MAX_LINE:
            raise DatasetError(f"{p} line {n}: {len(line)} characters, more than a result's {MAX_LINE}")
        try:
            out.append(_result(next(csv.reader([line]), [])))
        except (ValueError, csv.Error) as e:
            raise DatasetError(f"{p} line {n}: {e}") from None
    return out


def _result(row: list[str]) -> PoseResult:
    """One results row (fields as text) -> PoseResult; ValueError saying what is wrong."""
    if not "".join(row).strip():
        raise ValueError("empty line")
    if len(row) != len(RESULTS_HEADER):
        raise ValueError(f"expected {len(RESULTS_HEADER)} fields ({','.join(RESULTS_HEADER)}), got {len(row)}")
    ids = []
    for name, text in zip(RESULTS_HEADER[:3], row[:3]):
        if not (text.strip().isascii() and text.strip().isdigit()):
            raise ValueError(f"{name} {text!r} is not a non-negative integer")
        ids.append(int(text))
    nums = {name: _numbers(name, text, count) for name, text, count in zip(RESULTS_HEADER[3:], row[3:], (1, 9, 3, 1))}
    T = np.eye(4)
    T[:3, :3] = np.array([float(v) for v in nums["R"]]).reshape(3, 3)
    T[:3, 3] = [float(v.scaleb(-3)) for v in nums["t"]]  # mm -> m, rounded once
    return PoseResult(*ids, float(nums["score"][0]), T, float(nums["time"][0]))


def _numbers(name: str, text: str, count: int) -> list[Decimal]:
    """``count`` space-separated finite numbers of field ``name``, exactly as written; ValueError otherwise."""
    try:
        v = [Decimal(x) for x in text.split()]
    except InvalidOperation:
        v = []
    if len(v) != count or not all(x.is_finite() and math.isfinite(float(x)) for x in v):
        shown = text if len(text) <= 60 else text[:57] + "..."
        raise ValueError(f"{name} {shown!r} is not {count} finite number{'s' if count > 1 else ''}")
    return v
