"""The settings reference, ``docs/reference/settings.md``, generated from the config dataclasses.

    python -m posegrasp.settings_doc > docs/reference/settings.md

Each part declares the settings its commands read in its command module: ``SETTINGS``, a tuple of dicts of
``SettingsRoot``'s fields. The page loads the command modules by name, as the command line does
(``posegrasp.cli.COMMAND_MODULES``), and lists the parts in ``--help``'s order. Each documented settings class
(what a ``--config`` TOML file or the Python API takes) is walked by introspection, nested dataclasses recursed into
their own TOML tables. A field's description is the ``#:`` comment block directly above it in its class's source
(read with ``ast``; an inherited field takes its base class's), its unit the first parenthesised unit of that
description (``(m)``, ``(deg)``, ...) or its name's suffix (``_deg``, ``_s``). ``undescribed`` lists the fields that
have no ``#:`` line yet; ``unreachable_configs`` the ``*Config`` dataclasses of the package that no root reaches.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import pkgutil
import re
import sys
import textwrap
import typing
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from posegrasp import ASSETS


@dataclass(frozen=True)
class SettingsRoot:
    """One settings class as a user meets it: ``title`` heading, ``target`` ``module:Class``, the TOML ``table`` its
    fields sit in (``""``: the file's top level; None: a Python-only class, no TOML), the ``command`` that reads it
    and a ``note``. A part's command module lists its own as ``SETTINGS``, a tuple of dicts of these fields."""

    title: str
    target: str
    table: str | None
    command: str
    note: str = ""

    def cls(self) -> type:
        module, name = self.target.split(":")
        return getattr(importlib.import_module(module), name)


def command_modules() -> tuple[str, ...]:
    """The command modules of the parts, in ``--help``'s order (loaded by name, as the command line loads them)."""
    from posegrasp.cli import COMMAND_MODULES

    return COMMAND_MODULES


@lru_cache(maxsize=None)
def roots() -> tuple[SettingsRoot, ...]:
    """Every part's documented settings classes: its command module's ``SETTINGS``, in ``--help``'s order."""
    return tuple(SettingsRoot(**entry) for name in command_modules()
                 for entry in getattr(importlib.import_module(name), "SETTINGS", ()))


#: Units recognised in a description's parentheses, e.g. ``#: Distance (m) beyond which ...``.
UNITS = {"m", "mm", "cm", "s", "ms", "deg", "rad", "px", "kg", "kg/m^3", "m/s", "rad/s", "m/s, rad/s", "1/s",
         "m^3", "grey levels", "wall s", "m, per axis"}
_SUFFIX_UNITS = (("_deg", "deg"), ("_s", "s"), ("_px", "px"), ("_m", "m"))


@lru_cache(maxsize=None)
def field_comments(cls: type) -> dict[str, str]:
    """The ``#:`` description of each field that ``cls`` itself declares (consecutive ``#:`` lines joined)."""
    try:
        lines, _ = inspect.getsourcelines(cls)
    except (OSError, TypeError):
        return {}
    tree = ast.parse(textwrap.dedent("".join(lines)))
    out: dict[str, str] = {}
    for node in tree.body[0].body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            text: list[str] = []
            i = node.lineno - 2  # the line above, 0-based
            while i >= 0 and lines[i].strip().startswith("#:"):
                text.insert(0, lines[i].strip()[2:].strip())
                i -= 1
            if text:
                out[node.target.id] = " ".join(text)
    return out


def description(cls: type, name: str) -> str:
    """The description of field ``name`` of ``cls``: its own ``#:`` comment, else the nearest base class's."""
    for klass in cls.__mro__:
        if name in getattr(klass, "__annotations__", {}):
            text = field_comments(klass).get(name)
            if text:
                return text
    return ""


def defining_class(cls: type, name: str) -> type:
    """The class of ``cls``'s MRO that declares field ``name`` first (the one whose ``#:`` line it lacks)."""
    return next(k for k in cls.__mro__ if name in getattr(k, "__annotations__", {}))


def unit_of(name: str, text: str) -> str:
    """The unit of a field: the first parenthesised unit of its description, else its name's suffix, else ''."""
    for m in re.finditer(r"\(([^()]*)\)", text):
        inner = m.group(1).strip()
        if inner in UNITS:
            return inner
        head = re.split(r"[;]| or |, (?!per)", inner)[0].strip()
        if head in UNITS:
            return head
    for suffix, unit in _SUFFIX_UNITS:
        if name.endswith(suffix):
            return unit
    return ""


def type_name(tp: Any) -> str:
    """A type as TOML sees it: ``float``, ``float[2]`` (a pair), ``int[]`` (any length), ``str | None``."""
    args = typing.get_args(tp)
    origin = typing.get_origin(tp)
    if origin in (tuple, list):
        if not args:
            return "[]"
        if origin is list or (len(args) == 2 and args[1] is Ellipsis):
            return f"{type_name(args[0])}[]"
        if len(set(args)) == 1:
            return f"{type_name(args[0])}[{len(args)}]"
        return "[" + ", ".join(type_name(a) for a in args) + "]"
    if args:  # a union
        return " | ".join("None" if a is type(None) else type_name(a) for a in args)
    return getattr(tp, "__name__", str(tp))


def strip_unit(text: str, unit: str) -> str:
    """The description without the parenthesised unit the default column shows."""
    return re.sub(r" ?\(" + re.escape(unit) + r"\)", "", text, count=1) if unit else text


def _shipped_path(text: str) -> str:
    """A default path inside the installed package shown as the repository's ``assets/...``."""
    return text.replace(str(ASSETS), "assets")


def toml_value(value: Any) -> str:
    """``value`` as TOML writes it (tuples as arrays, None as 'none'); a long array as its length."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (str, Path)):
        return '"' + _shipped_path(str(value)) + '"'
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (tuple, list)):
        text = "[" + ", ".join(toml_value(v) for v in value) + "]"
        return text if len(text) <= 40 else f"{len(value)} entries"
    return str(value)


def default_of(f: dataclasses.Field, parent: Any) -> Any:
    """The field's value in ``parent``, the parent's default instance (so nested defaults are the parent's)."""
    return getattr(parent, f.name)


def _cell(text: str) -> str:
    return text.replace("``", "`").replace("|", "\\|").replace("\n", " ")


def default_cell(tp: Any, value: Any, unit: str) -> str:
    """The default as TOML writes it, then its unit (``0.002 s``); the type, in parentheses, only where the value does
    not show it (unset, an empty or long array, a union): ``none (float, m)``, ``[] (int[])``."""
    text = toml_value(value)
    union = typing.get_origin(tp) not in (tuple, list) and len(typing.get_args(tp)) > 1
    if value is None or text == "[]" or text.endswith(" entries") or union:
        kinds = [k for k in type_name(tp).split(" | ") if k not in ("None", "Path")]
        extra = ", ".join([" | ".join(kinds)] + ([unit] if unit else []))
        return f"{text} ({extra})"
    return f"{text} {unit}".strip()


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading (as ``tests/test_docs.py`` computes it)."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


class _Writer:
    """Builds the markdown: one section per root, one table per (nested) dataclass, repeats linked to the first."""

    def __init__(self) -> None:
        self.out: list[str] = []
        self.seen: dict[tuple[type, str], str] = {}  # (class, defaults) -> heading anchor
        self.inherited: dict[tuple[type, str, str], tuple[str, str]] = {}  # (base, field, default) -> (title, anchor)
        self.slugs: dict[str, int] = {}
        self.first: dict[type, tuple[str, Any, str]] = {}  # class -> (title, defaults, anchor) of its first table

    def heading(self, level: int, text: str) -> str:
        slug = github_slug(text)
        n = self.slugs.get(slug, 0)
        self.slugs[slug] = n + 1
        self.out += [f"{'#' * level} {text}", ""]
        return slug if n == 0 else f"{slug}-{n}"

    def table(self, cls: type, instance: Any, path: list[str], root: SettingsRoot, lead: str = "") -> None:
        if root.table is None:
            title = f"`{'.'.join([root.cls().__name__, *path])}`" + (f" (`{cls.__name__}`)" if path else "")
        else:
            parts = [p for p in [root.table, *path] if p]
            title = f"`[{'.'.join(parts)}]`" if parts else "Top-level keys"
            title += f" (`{cls.__name__}`)"
        key = (cls, repr(instance))
        if key in self.seen:
            self.heading(3, title)
            self.out += [f"The same fields and defaults as [{cls.__name__}](#{self.seen[key]}).", ""]
            return
        first = self.first.get(cls)
        if first is not None and not any(dataclasses.is_dataclass(t) for t in typing.get_type_hints(cls).values()):
            changed = [f"`{f.name}` = {toml_value(getattr(instance, f.name))}" for f in dataclasses.fields(cls)
                       if getattr(instance, f.name) != getattr(first[1], f.name)]
            self.heading(3, title)
            name = first[0].split(" (")[0]
            self.out += [f"{(lead or cls.__name__).rstrip('.')}: the fields of [{name}](#{first[2]}), "
                         f"with {', '.join(changed)}.", ""]
            return
        anchor = self.heading(3, title)
        self.seen[key] = anchor
        self.first.setdefault(cls, (title, instance, anchor))
        doc = inspect.getdoc(cls) or ""
        first = lead or re.split(r"(?<=\.)\s", doc.split("\n\n")[0].replace("\n", " ").replace("``", "`").strip())[0]
        if first:
            self.out += [first, ""]
        hints = typing.get_type_hints(cls)
        nested: list[tuple[dataclasses.Field, Any]] = []
        rows = ["key|default|description", "-|-|-"]
        shared: dict[tuple[str, str], list[str]] = {}  # inherited keys listed before: (title, anchor) -> names
        for f in dataclasses.fields(cls):
            value = default_of(f, instance)
            if dataclasses.is_dataclass(hints[f.name]):
                nested.append((f, value))
                continue
            base = defining_class(cls, f.name)
            if base is not cls:  # inherited unchanged: list it once per default
                where = self.inherited.setdefault((base, f.name, repr(value)), (title, anchor))
                if where != (title, anchor):
                    shared.setdefault(where, []).append(f"`{f.name}`")
                    continue
            text = description(cls, f.name)
            unit = unit_of(f.name, text)
            cells = [f.name, default_cell(hints[f.name], value, unit), strip_unit(text, unit) or "-"]
            rows.append("|".join(_cell(c) for c in cells))
        if len(rows) > 2:
            self.out += rows + [""]
        for (where, link), names in shared.items():
            self.out += [f"Also {', '.join(names)}, as in {where.split(' (')[0]} [above](#{link}).", ""]
        for f, value in nested:
            self.table(type(value), value, [*path, f.name], root, description(cls, f.name))


def render() -> str:
    """The whole ``docs/reference/settings.md``."""
    w = _Writer()
    w.out += [
        "# Settings reference",
        "",
        "<!-- Generated by `python -m posegrasp.settings_doc > docs/reference/settings.md` from the `#:` comments above the",
        "     config dataclass fields. Edit those, then regenerate. -->",
        "",
        "Put the keys you change in a TOML file and pass it with `--config`; keys left out keep the default below, "
        "nested tables are TOML tables (`[seg.model]`). Unknown keys, wrong types and out-of-range values are refused "
        "before anything runs. Units: SI (m, s, rad) unless the default names one.",
        "",
        " · ".join(f"[{root.title}](#{github_slug(root.title)})" for root in roots()),
        "",
    ]
    for root in roots():
        w.heading(2, root.title)
        w.out += [f"{root.command}. {root.note}".strip(), ""]
        w.table(root.cls(), root.cls()(), [], root)
    return "\n".join(w.out).rstrip() + "\n"


def walk(cls: type) -> list[tuple[type, str]]:
    """Every (class, field) that ``cls`` holds, nested dataclasses recursed (each class once)."""
    out: list[tuple[type, str]] = []
    todo, done = [cls], set()
    while todo:
        klass = todo.pop(0)
        if klass in done:
            continue
        done.add(klass)
        hints = typing.get_type_hints(klass)
        instance = klass()
        for f in dataclasses.fields(klass):
            if dataclasses.is_dataclass(hints[f.name]):
                todo.append(type(getattr(instance, f.name)))
            else:
                out.append((klass, f.name))
    return out


def undescribed() -> list[str]:
    """``Class.field`` of every documented field without a ``#:`` description (named by its declaring class)."""
    missing = {f"{defining_class(k, n).__name__}.{n}" for root in roots() for k, n in walk(root.cls())
               if not description(k, n)}
    return sorted(missing)


def unreachable_configs(excused: set[str] | frozenset[str] = frozenset()) -> list[str]:
    """``*Config`` dataclasses of the core and of the parts' packages (their top-level modules) that no root reaches,
    but those named in ``excused`` (``module.Class``: built in code, never read from a file or passed in)."""
    walked = [k for root in roots() for k, _ in walk(root.cls())]
    reached = {f"{b.__module__}.{b.__qualname__}" for k in walked for b in k.__mro__}
    packages = dict.fromkeys(["posegrasp", *(".".join(name.split(".")[:2]) for name in command_modules())])
    found = set()
    for package in packages:
        pkg = importlib.import_module(package)
        for info in pkgutil.iter_modules(pkg.__path__, package + "."):
            if info.ispkg or info.name == __name__ or info.name.rpartition(".")[2].startswith("_"):
                continue  # (``_name``: a compiled part, loaded with ctypes, not a Python module)
            module = importlib.import_module(info.name)
            for obj in vars(module).values():
                if inspect.isclass(obj) and dataclasses.is_dataclass(obj) and obj.__module__ == module.__name__ \
                        and obj.__name__.endswith("Config"):
                    found.add(f"{obj.__module__}.{obj.__qualname__}")
    return sorted(found - reached - set(excused))


def main() -> int:
    sys.stdout.write(render())
    return 0


if __name__ == "__main__":
    sys.exit(main())
