"""A trial run folder's files: their names, the JSON-lines records and the campaign they belong to.

``episodes.jsonl`` and ``timings.jsonl`` hold one JSON line (sorted keys, no spaces) per finished episode,
appended as episodes finish; a reader drops a torn last line left by a kill. ``campaign.json`` records what
the episodes were made with (seed, perception, ``TrialConfig``, calibrated camera mount); ``summary.json``
holds the campaign's statistics (``grasping.stats.summarise``).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Iterable

from posegrasp import inputs
from posegrasp.catalog import set_record
from posegrasp.config import from_dict
from posegrasp.errors import DatasetError, UserError
from posegrasp.grasping.config import TrialConfig, config_record
from posegrasp.grasping.record import EpisodeRecord
from posegrasp.io import atomic_write, dumps_json, write_json
from posegrasp.outputs import Record

EPISODES, TIMINGS, SUMMARY, CAMPAIGN = "episodes.jsonl", "timings.jsonl", "summary.json", "campaign.json"
#: What marks a campaign's folder (``posegrasp.outputs``): its campaign record, or its episode records.
RECORDS = (Record(CAMPAIGN, ("seed", "perception")), Record(EPISODES, ("episode",)))


def _line(rec: dict) -> str:
    return json.dumps(rec, sort_keys=True, separators=(",", ":")) + "\n"


def read_records(path: Path) -> dict[int, dict]:
    """Complete records of a (possibly torn) JSON-lines file, by episode index; a DatasetError naming the line
    for a complete line that is not a record."""
    return {i: rec for i, (_, rec) in _numbered(path).items()}


def read_episodes(path: Path) -> dict[int, tuple[dict, EpisodeRecord]]:
    """The complete episode records of an ``episodes.jsonl`` by episode index, each as read and as checked
    (``EpisodeRecord.from_json``); a one-line DatasetError naming the file, line and key of a malformed one."""
    out = {}
    for i, (n, rec) in _numbered(path).items():
        try:
            out[i] = rec, EpisodeRecord.from_json(rec, f"{path} line {n}")
        except UserError as e:
            raise DatasetError(f"{e}; the record is corrupt: rerun the trials into a new --out") from None
    return out


def _numbered(path: Path) -> dict[int, tuple[int, dict]]:
    """``read_records`` with each record's line number (from 1)."""
    out: dict[int, tuple[int, dict]] = {}
    if not os.path.lexists(path):
        return out
    lines = inputs.read_text(path, "jsonl", DatasetError).splitlines(keepends=True)
    for n, line in enumerate(lines, start=1):
        if not line.endswith("\n"):
            break  # torn last line of a killed run
        try:
            rec = inputs.parse_json(line, f"{path} line {n}", DatasetError)
        except DatasetError:
            rec = None
        episode = rec.get("episode") if isinstance(rec, dict) else None
        if not isinstance(episode, int) or isinstance(episode, bool) or episode < 0:
            raise DatasetError(f"{path} line {n} is not an episode record (a JSON object with an integer "
                               f"\"episode\"); the file is corrupt: rerun the trials into a new --out")
        if episode in out:
            raise DatasetError(f"{path} line {n} repeats episode {episode} of line {out[episode][0]}; the file is "
                               "corrupt: rerun the trials into a new --out")
        out[episode] = n, rec
    return out


def write_records(path: Path, records: Iterable[dict]) -> None:
    """Atomically (re)write a JSON-lines file with ``records``, in the given order."""
    atomic_write(path, lambda p: p.write_text("".join(_line(r) for r in records)))


def append_record(f: IO[str], rec: dict, sync: bool = False) -> None:
    """Append one record to an open JSON-lines file and flush it (to the disk as well when ``sync``)."""
    f.write(_line(rec))
    f.flush()
    if sync:
        os.fsync(f.fileno())


@dataclass(frozen=True)
class Campaign:
    """What a run folder's episodes were made with (``campaign.json``); mixing campaigns in a folder is refused."""

    seed: int
    perception: str
    config: TrialConfig
    T_gripper_cam: tuple[tuple[float, ...], ...]  # calibrated mount used by the planner, row-major 4x4
    objects: dict | None = None  # the object set as recorded (``catalog.set_record``); None: the config's set now

    def set_record(self) -> dict:
        """Name, path and sha256 of the object set the campaign runs on (``catalog.set_record``)."""
        return self.objects or set_record(self.config.scene.workcell.objects)

    def to_json(self) -> dict:
        """The ``campaign.json`` content."""
        return {"seed": self.seed, "perception": self.perception, "config": config_record(self.config),
                "T_gripper_cam": self.T_gripper_cam, "objects": self.set_record()}


def read_campaign(run_dir: Path) -> Campaign:
    """The campaign of a run folder; fields added to ``TrialConfig`` since it was written take their defaults."""
    path = run_dir / CAMPAIGN
    data = read_json_object(path)
    try:
        mount = tuple(tuple(_number(v) for v in row) for row in data["T_gripper_cam"])
        if len(mount) != 4 or any(len(row) != 4 for row in mount):
            raise ValueError
        objects = data.get("objects")  # absent in runs made before object sets: the shipped blocks
        seed, perception, config = data["seed"], data["perception"], data["config"]
        if type(seed) is not int or seed < 0 or not isinstance(perception, str) or not isinstance(config, dict) \
                or not (objects is None or isinstance(objects, dict) and all(isinstance(objects.get(k), str)
                                                                       for k in ("name", "path", "sha256"))):
            raise ValueError
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{path} is corrupt (needs seed, perception, config and a 4x4 T_gripper_cam); "
                           "rerun the trials into a new --out") from None
    return Campaign(seed, perception, from_dict(TrialConfig, config, where=f"{path} config"), mount,
                    dict(objects) if isinstance(objects, dict) else None)


def _number(v: object) -> float:
    """``v`` if it is a finite JSON number (a ValueError if not)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(v)
    return float(v)


def read_json_object(path: Path) -> dict:
    """The JSON object in ``path``, or a DatasetError naming the file."""
    if not os.path.lexists(path):
        raise DatasetError(f"{path} is missing: give a folder written by 'posegrasp trials --out'")
    try:
        data = inputs.read_json(path, DatasetError)
    except DatasetError as e:
        raise DatasetError(f"{path} is not readable JSON ({inputs.reason(e, path)}); rerun the trials into a new "
                           "--out") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path} is not a JSON object; rerun the trials into a new --out")
    return data


def check_campaign(out: Path, campaign: Campaign) -> None:
    """Refuse to mix two campaigns in one folder; record this one if the folder has none."""
    path = out / CAMPAIGN
    if not path.exists():
        write_json(path, campaign.to_json())
        return
    old = read_json_object(path)
    if isinstance(old.get("config"), dict):  # fields added to TrialConfig since it was written: their defaults
        old["config"] = config_record(from_dict(TrialConfig, old["config"], where=f"{path} config"))
    new = json.loads(dumps_json(campaign.to_json()))
    old.setdefault("objects", set_record(""))  # runs made before object sets ran on the shipped blocks
    old = json.loads(dumps_json(old))
    was = old["objects"] if isinstance(old["objects"], dict) else {}
    if was.get("sha256") != new["objects"]["sha256"]:
        raise DatasetError(f"{out} holds a campaign on the object set {was.get('name')} ({was.get('path')}), not on "
                           f"{new['objects']['path']}; use another --out, or --objects {was.get('path')} to resume")
    if old != new:
        keys = sorted(k for k in new if old.get(k) != new[k])
        raise DatasetError(f"{out} holds a different campaign (differs in {', '.join(keys)}); "
                           "use another --out or the same settings to resume")
