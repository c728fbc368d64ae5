"""posegrasp: a simulation testbed for vision-guided robotic grasping."""

from pathlib import Path

from posegrasp import assets as _assets

__version__ = "0.1.0"

#: The shipped assets (block catalogue, scene settings, calibration, weights), installed inside the package.
ASSETS = Path(_assets.__file__).resolve().parent
