"""Option types of the command line: each parses one option's text, or raises a one-line ``UserError`` naming
the option, the bad value and what it should be. Output paths are checked without creating anything, so a
refused command leaves the disk as it was.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Callable

from posegrasp.errors import UserError


def positive_int(name: str, hi: int | None = None) -> Callable[[str], int]:
    """Option ``name``: an integer >= 1 (and <= ``hi``: a sanity bound on a count)."""
    return _int(name, 1, "a positive integer", hi)


def nonneg_int(name: str) -> Callable[[str], int]:
    """Option ``name``: an integer >= 0 (a seed: numpy's ``SeedSequence`` takes no negative one; an id)."""
    return _int(name, 0, "a non-negative integer")


def _int(name: str, lo: int, what: str, hi: int | None = None) -> Callable[[str], int]:
    what += "" if hi is None else f" up to {hi}"

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise UserError(f"{name} must be {what}, got {text!r}") from None
        if v < lo or hi is not None and v > hi:
            raise UserError(f"{name} must be {what}, got {v}")
        return v

    return parse


def number(name: str, lo: float | None = None, hi: float | None = None, open_lo: bool = False,
           open_hi: bool = False) -> Callable[[str], float]:
    """Option ``name``: a finite number in [lo, hi] (``open_lo`` / ``open_hi`` exclude the bound)."""
    lo_txt = "" if lo is None else f"{'>' if open_lo else '>='} {lo:g}"
    hi_txt = "" if hi is None else f"{'<' if open_hi else '<='} {hi:g}"
    want = " and ".join(t for t in (lo_txt, hi_txt) if t)

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise UserError(f"{name} must be a number, got {text!r}") from None
        bad_lo = lo is not None and (v <= lo if open_lo else v < lo)
        bad_hi = hi is not None and (v >= hi if open_hi else v > hi)
        if not math.isfinite(v) or bad_lo or bad_hi:
            raise UserError(f"{name} must be a finite number{' ' + want if want else ''}, got {text}")
        return v

    return parse


def workers_arg(text: str) -> int | str:
    """``--workers``: a number of local processes, or ``ray``."""
    return text if text == "ray" else positive_int("--workers (a number of processes, or 'ray')")(text)


def in_dir(name: str) -> Callable[[str], Path]:
    """Option ``name``: an existing folder to read."""

    def parse(text: str) -> Path:
        p = Path(text)
        if not text.strip() or not p.is_dir():
            why = "is empty" if not text.strip() else "is a file" if p.exists() else "does not exist"
            raise UserError(f"{name} {text!r} {why}; name an existing folder")
        return p

    return parse


def _writable_parent(name: str, p: Path, what: str) -> None:
    """The nearest existing folder above ``p`` must be a writable folder (``what`` ``p`` could then be created)."""
    parent = next(a for a in p.absolute().parents if a.exists())
    if not parent.is_dir():
        raise UserError(f"{name}: cannot create {what} {p}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserError(f"{name}: cannot create {what} {p}: folder {parent} is not writable")


def out_dir(name: str = "--out") -> Callable[[str], Path]:
    """Option ``name``: an output folder, existing or creatable (not created here)."""

    def parse(text: str) -> Path:
        if not text.strip():
            raise UserError(f"{name} is empty; name an output folder")
        p = Path(text)
        if p.exists():
            if not p.is_dir():
                raise UserError(f"{name} {p} is a file; name an output folder")
            if not os.access(p, os.W_OK | os.X_OK):
                raise UserError(f"{name} {p}: output folder is not writable; choose another --out")
        else:
            _writable_parent(name, p, "output folder")
        return p

    return parse


def out_file(name: str = "--out", suffixes: tuple[str, ...] = (), new: bool = False) -> Callable[[str], Path]:
    """Option ``name``: an output file name ending in one of ``suffixes`` (any if empty) in a writable folder;
    ``new``: it must not exist yet."""

    def parse(text: str) -> Path:
        if not text.strip():
            raise UserError(f"{name} is empty; name an output file")
        p = Path(text)
        if p.is_dir():
            example = p / ("out" + (suffixes or (".json",))[0])
            raise UserError(f"{name} {p} is a folder; name a file in it, e.g. {example}")
        if suffixes and p.suffix.lower() not in suffixes:
            raise UserError(f"{name} {p}: unsupported file type {p.suffix or '(none)'!r}; use {', '.join(suffixes)}")
        if new and p.exists():
            raise UserError(f"{name} {p} already exists; choose a new name")
        _writable_parent(name, p, "output file")
        return p

    return parse

