"""posegrasp: a simulation testbed for vision-guided robotic grasping."""

from pathlib import Path

__version__ = "0.1.0"

#: Repository assets (block catalogue, scene settings, shipped weights).
ASSETS = Path(__file__).resolve().parents[1] / "assets"
