"""Typed settings: frozen dataclasses (``@settings``) whose fields declare their ranges (``within``), checked when
an instance is built, in code or from TOML (``from_dict``, ``load_toml``: unknown keys and wrong types are user
errors too); ``override`` applies CLI flags. A class's ``RENAMED`` ({old key: new key}) keeps files that use a
renamed key readable, with a notice on stderr naming the new key."""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import tomllib
import typing
from pathlib import Path
from typing import Any, TypeVar

from posegrasp import inputs
from posegrasp.errors import ConfigError

C = TypeVar("C")


def from_dict(cls: type[C], data: dict[str, Any], where: str = "config") -> C:
    """Build dataclass ``cls`` from a (nested) dict, checking key names and value types."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table, got {type(data).__name__}")
    data = renamed(data, getattr(cls, "RENAMED", {}), where)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; valid keys are {sorted(names)}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        kwargs[key] = check_range(fields[key], _coerce(hints[key], value, f"{where}.{key}"), f"{where}.{key}")
    missing = [f.name for f in dataclasses.fields(cls) if f.init and f.name not in data
               and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"{where}: missing key(s) {missing}")
    try:
        return cls(**kwargs)
    except ConfigError as e:  # a check across fields (``__post_init__``): name the file
        raise ConfigError(f"{where}: {e}") from None


def renamed(data: dict[str, Any], names: dict[str, str], where: str) -> dict[str, Any]:
    """``data`` with its keys named in ``names`` (old -> new) under their new names, each noticed on stderr; a
    ConfigError when a key is given under both names."""
    for old in (k for k in names if k in data):
        if names[old] in data:
            raise ConfigError(f"{where}: '{old}' and '{names[old]}' are one setting; keep '{names[old]}'")
        print(f"posegrasp: note: {where}: '{old}' is now named '{names[old]}'", file=sys.stderr)
    return {names.get(k, k): v for k, v in data.items()}


def settings(cls: type[C]) -> type[C]:
    """Class decorator for a settings class: a frozen dataclass whose fields' ``within`` ranges are checked when an
    instance is built (a ``ConfigError`` naming the class, field and value), then its own ``__post_init__`` (checks
    across fields). Every settings class of the package is one."""
    own = cls.__dict__.get("__post_init__", getattr(cls, "__post_init__", None))

    def __post_init__(self: Any) -> None:
        for f in dataclasses.fields(self):
            check_range(f, getattr(self, f.name), f"{type(self).__name__}.{f.name}")
        if own is not None:
            own(self)

    cls.__post_init__ = __post_init__  # type: ignore[attr-defined]
    return dataclasses.dataclass(frozen=True)(cls)


def within(lo: float, hi: float) -> dict[str, Any]:
    """Field metadata bounding a number (or each number of a tuple) to [lo, hi]:
    ``width: int = field(default=640, metadata=within(16, 4096))``; ``from_dict`` and ``override`` enforce it."""
    return {"range": (lo, hi)}


def check_range(f: dataclasses.Field, value: Any, where: str) -> Any:
    """``value`` of field ``f`` if it lies in the field's ``within`` bounds (if any), else a ConfigError."""
    lo, hi = f.metadata.get("range", (None, None))
    if lo is None or value is None:
        return value
    values = value if isinstance(value, (list, tuple)) else [value]
    if not all(lo <= v <= hi for v in values):
        raise ConfigError(f"{where} = {value!r} is out of range: use {lo:g} to {hi:g}")
    return value


def _coerce(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where)
    if origin is typing.Union or str(origin) == "<class 'types.UnionType'>":
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(args[0], value, where)
    if origin in (tuple, list):
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            if origin is not tuple or args[1:] != (Ellipsis,) or isinstance(value, dict):
                raise ConfigError(f"{where}: expected a list, got {value!r}")
            value = [value]  # one value of a setting that takes several (a campaign.json written before it did)
        inner = args[0] if args else Any
        out = [_coerce(inner, v, where) for v in value]
        return tuple(out) if origin is tuple else out
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if tp in (int, str, bool) and not isinstance(value, tp) or (tp is int and isinstance(value, bool)):
        raise ConfigError(f"{where}: expected {tp.__name__}, got {value!r}")
    return value


def load_toml(cls: type[C], path: str | Path | None, section: str | None = None,
              sections: tuple[str, ...] = (), renamed_sections: dict[str, str] | None = None) -> C:
    """Load ``cls`` from a TOML file (optionally one ``[section]`` of it); defaults when ``path`` is None. A file
    of several ``sections`` (the tables it may hold: a typo such as ``[sge]`` is refused, not ignored), some of
    them perhaps under an old name (``renamed_sections``: old -> new)."""
    if path is None:
        return cls()
    data = read_toml(path)
    data = renamed(data, renamed_sections or {}, str(path))
    unknown = sorted(set(data) - set(sections)) if sections else []
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {unknown}; valid sections are {sorted(sections)}")
    if section is not None:
        data = data.get(section, {})
    return from_dict(cls, data, where=str(path))


def read_toml(path: str | Path) -> dict[str, Any]:
    """The TOML document of the settings file ``path`` (a bounded regular file: ``posegrasp.inputs``), or a
    one-line ConfigError naming it."""
    path = Path(path)
    if not os.path.lexists(path):
        raise ConfigError(f"config file {path} does not exist")
    raw = inputs.read_bytes(path, "toml", ConfigError)
    try:
        return inputs.parse_toml(raw.decode("utf-8"), f"config file {path}", ConfigError)
    except UnicodeDecodeError:
        raise ConfigError(f"config file {path} is not UTF-8 text; save it as a UTF-8 TOML file") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {path} is not valid TOML: {e}") from None


def override(cfg: C, **changes: Any) -> C:
    """Copy of ``cfg`` with the non-None ``changes`` applied (CLI flags override the file)."""
    fields = {f.name: f for f in dataclasses.fields(cfg)}
    return dataclasses.replace(cfg, **{k: check_range(fields[k], v, k) for k, v in changes.items() if v is not None})
