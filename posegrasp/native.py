"""The package's compiled parts (C built by ``setup.py`` with the package), loaded with ctypes."""

from __future__ import annotations

import ctypes
import importlib.machinery
from pathlib import Path

from posegrasp.errors import PosegraspError


def library(folder: Path, name: str, what: str) -> ctypes.CDLL:
    """The compiled library ``name`` (``name*.so``) in ``folder``; PosegraspError naming ``what`` it holds when it
    was not built."""
    found = [folder / f"{name}{x}" for x in importlib.machinery.EXTENSION_SUFFIXES if (folder / f"{name}{x}").exists()]
    if not found:
        raise PosegraspError(f"{what} ({name}*.so) are missing from {folder}: install posegrasp with pip (`make setup` "
                             "or `pip install -e .`), which builds them")
    return ctypes.CDLL(str(found[0]))
