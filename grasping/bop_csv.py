"""Pose estimates from a BOP results file: ``--perception bop-csv:RESULTS.csv``.

Any BOP method run offline on a campaign's captures (``--export-captures``, ``grasping.captures``) gives a results
CSV (``scene_id,im_id,obj_id,score,R,t,time``; R row-major, t in mm); this provider replays it: for the capture
``(scene_id, im_id)`` = (episode, one of its task's ``looks``) it returns that frame's rows as estimates
(``T_cam_obj`` in metres), in file order; a frame without rows is a frame where nothing was detected.

The file is checked when the campaign starts (``read_rows``, ``check_rows``), a one-line DatasetError naming the line
for: a wrong header, a field that is not a number or not finite (NaN), an R that is not a rotation (orthonormal,
det +1, within 1e-3), a translation less than ``MIN_Z_MM`` in front of the camera (metres written instead of mm;
or behind the camera) or farther than ``grasping.perception.MAX_TRANSLATION_M``, an obj_id not in the object set,
an exact duplicate (same scene_id, im_id and obj_id and the very same R and t as an earlier row; several rows of
one object in one image are otherwise allowed: BOP images may hold several instances), and a row for a frame no
episode of the campaign captures (scene_id >= the episodes, or an im_id not among the task's looks).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from posegrasp import bop
from posegrasp.bop import results as bop_results
from posegrasp.bop.check import rotation_problem
from posegrasp.catalog import catalog_by_id
from posegrasp.errors import DatasetError, ProviderError
from posegrasp.grasping.perception import MAX_TRANSLATION_M, ROT_TOL, Estimate, Observation

#: A row whose translation is less than this far in front of the camera (mm) is refused: no camera sees an object
#: there, and it is what metres written in the mm column look like.
MIN_Z_MM = 10.0


@dataclass(frozen=True)
class BopCsvProvider:
    """The rows of the BOP results file ``path`` for the observed frame (``obs.scene_id``, ``obs.im_id``)."""

    path: str
    objects: str = ""  # the object set whose ids the rows must use

    @property
    def name(self) -> str:
        return f"bop-csv:{self.path}"

    def rows(self) -> list[bop_results.PoseResult]:
        """Every row of the file, checked (cached per process while the file is unchanged)."""
        return _load(self.path, self.objects, _stamp(self.path))[0]

    def estimate(self, obs: Observation, seed: int) -> list[Estimate]:
        """The file's rows for the frame (``seed`` unused): obj_id, T_cam_obj (m), score."""
        frames = _load(self.path, self.objects, _stamp(self.path))[1]
        return [Estimate(r.obj_id, r.T_cam_obj.copy(), r.score) for r in frames.get((obs.scene_id, obs.im_id), ())]


def from_spec(args: str | None, objects: str = "") -> BopCsvProvider:
    """The provider for ``--perception bop-csv:RESULTS.csv`` (``args``: the file), its rows checked."""
    if not args:
        raise ProviderError("perception 'bop-csv' needs a results file: bop-csv:RESULTS.csv")
    provider = BopCsvProvider(str(Path(args).expanduser().resolve()), objects)
    provider.rows()
    return provider


def check_rows(provider: object, episodes: int, task: str, ims: tuple[int, ...]) -> None:
    """A DatasetError when a ``BopCsvProvider``'s file has rows for frames no episode of a campaign of ``episodes``
    episodes of the task named ``task`` captures (its looks ``ims``; any other provider: nothing to check)."""
    if not isinstance(provider, BopCsvProvider):
        return
    named = " or ".join(_runs(ims))
    for n, r in enumerate(provider.rows(), start=2):
        if r.scene_id >= episodes or r.im_id not in ims:
            raise DatasetError(f"{provider.path} line {n}: scene_id {r.scene_id}, im_id {r.im_id} is no frame of this "
                               f"campaign (scene_id = episode, 0-{episodes - 1}; im_id {named} in "
                               f"the {task} task); replay the file with the --episodes and --task it was exported with")


def _runs(ims: tuple[int, ...]) -> list[str]:
    """``ims`` (ascending) as runs of consecutive ids: ``(0, 1, 2, 7, 8)`` -> ``["0-2", "7", "8"]``."""
    out: list[list[int]] = []
    for i in ims:
        if out and i == out[-1][1] + 1:
            out[-1][1] = i
        else:
            out.append([i, i])
    return [r for a, b in out for r in ([f"{a}-{b}"] if b > a + 1 else map(str, range(a, b + 1)))]


def _stamp(path: str) -> tuple[int, int]:
    try:
        st = Path(path).stat()
    except OSError:
        raise DatasetError(f"results file {path} does not exist") from None
    return st.st_mtime_ns, st.st_size


@functools.lru_cache(maxsize=4)
def _load(path: str, objects: str, stamp: tuple[int, int]
          ) -> tuple[list[bop_results.PoseResult], dict[tuple[int, int], list[bop_results.PoseResult]]]:
    """The checked rows of ``path`` and the rows of each frame (``stamp``: the file's mtime and size)."""
    rows = bop_results.read_results_csv(path)
    known = catalog_by_id(objects)
    seen: dict[tuple, int] = {}
    frames: dict[tuple[int, int], list[bop_results.PoseResult]] = {}
    for n, r in enumerate(rows, start=2):
        problem = _row_problem(r, known)
        key = (r.scene_id, r.im_id, r.obj_id, r.T_cam_obj.tobytes())
        if problem is None and key in seen:
            problem = f"duplicates line {seen[key]} (same scene_id, im_id, obj_id, R and t)"
        if problem:
            raise DatasetError(f"{path} line {n}: {problem}")
        seen[key] = n
        frames.setdefault((r.scene_id, r.im_id), []).append(r)
    return rows, frames


def _row_problem(r: bop_results.PoseResult, known: dict) -> str | None:
    """What makes one row unusable, or None."""
    if r.obj_id not in known:
        return f"obj_id {r.obj_id} is not in the object set (ids {', '.join(str(k) for k in sorted(known))})"
    bad_R = rotation_problem(r.T_cam_obj[:3, :3], ROT_TOL)
    if bad_R:
        return f"R {bad_R}"
    t_mm = r.T_cam_obj[:3, 3] / bop.MM
    if t_mm[2] < MIN_Z_MM:
        return (f"t = {' '.join(f'{v:.6g}' for v in t_mm)} is {t_mm[2]:.6g} mm in front of the camera (< {MIN_Z_MM:g}):"
                " BOP results give t in mm, not metres")
    if np.abs(t_mm).max() > MAX_TRANSLATION_M / bop.MM or np.linalg.norm(t_mm) > MAX_TRANSLATION_M / bop.MM:
        return f"t = {' '.join(f'{v:.6g}' for v in t_mm)} mm is over {MAX_TRANSLATION_M:g} m from the camera"
    return None
