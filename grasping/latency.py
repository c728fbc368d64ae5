"""Perception's latency: the seconds a look waits for the provider's estimates, which a cell's cycle time adds to the
arm's motion (picks per hour, ``compare``'s verdict on bin picking).

One figure per campaign, so that the episode records stay deterministic: declared (``TrialConfig.perception_latency``),
else the provider's own (``latency_s``: the oracles' is 0, they compute nothing), else measured: the median over the
campaign's episodes of their wall seconds in perception per look (``timings.jsonl``). ``summary.json`` holds it as
``perception_latency`` (``{"seconds", "how"}``); a run without one counts 0 s.
"""

from __future__ import annotations

import statistics
from pathlib import Path

from posegrasp.errors import UserError
from posegrasp.inputs import read_json


def looks(record: dict) -> int:
    """The looks (captures perceived) of an episode's JSON record: one per bin-picking attempt plus the look that
    ended the episode; one for the table tasks."""
    attempts = record.get("attempts")
    return len(attempts) + 1 if attempts is not None else 1


def campaign_latency(declared: float | None, provider: object, records: list[dict], timings: dict[int, dict]) -> dict:
    """The campaign's perception latency (s per look) and how it was found ("declared", "provider", "measured";
    "none" when nothing was measured): ``declared``, else ``provider.latency_s``, else the median per-look wall
    time in perception over ``records`` (JSON, by episode) and their ``timings`` (``timings.jsonl`` lines by
    episode)."""
    if declared is not None:
        return {"seconds": float(declared), "how": "declared"}
    own = getattr(provider, "latency_s", None)
    if own is not None:
        return {"seconds": float(own), "how": "provider"}
    per_look = [timings[r["episode"]]["wall_s"].get("perceive", 0.0) / looks(r) for r in records
                if r["episode"] in timings]
    if not per_look:
        return {"seconds": 0.0, "how": "none"}
    return {"seconds": round(statistics.median(per_look), 4), "how": "measured"}


def run_latency(path: str | Path) -> float:
    """The perception latency (s per look) of a trial run folder (or its episodes.jsonl) from its summary.json;
    0 when it has none."""
    from posegrasp.grasping.runfolder import SUMMARY  # (the run folder's settings import the tasks, which import this)

    p = Path(path)
    f = (p if p.is_dir() else p.parent) / SUMMARY
    try:
        seconds = read_json(f)["perception_latency"]["seconds"] if f.exists() else 0.0
    except (UserError, KeyError, TypeError):
        return 0.0
    return float(seconds) if isinstance(seconds, (int, float)) and 0.0 <= seconds < 1e6 else 0.0
