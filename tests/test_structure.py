"""The package's shape, held: modules and functions small enough to read, few parameters (a settings object
instead of loose values), one meaning per public class name, every settings class of one convention, and the
layers of ``docs/architecture.md`` (the core imports no part; sim, perception and objects only the core; datagen
sim and the core; only grasping and the command line import grasping)."""

from __future__ import annotations

import ast
import dataclasses
import functools
import importlib
from collections import defaultdict
from pathlib import Path

from tests.test_packaging import _imports, _modules

#: Longest module (lines), function (lines) and parameter list (not counting ``self``/``cls``).
MAX_MODULE_LINES, MAX_FUNCTION_LINES, MAX_PARAMETERS = 500, 80, 8
#: What each layer may import besides itself (the core: ``posegrasp``'s own folder).
ALLOWED = {"core": {"core"}, "sim": {"core"}, "perception": {"core"}, "objects": {"core"},
           "datagen": {"core", "sim"}, "grasping": {"core", "sim", "perception", "objects", "datagen"},
           "assets": {"core"}}
#: The command line's entry point loads every part's subcommands by name.
ENTRY = "posegrasp.cli"


def layer(module: str) -> str:
    """The layer of a dotted module name: a part (``sim``, ...) or ``core``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ALLOWED and parts[1] != "core" else "core"


@functools.lru_cache(maxsize=1)
def _trees() -> dict[str, tuple[Path, ast.Module]]:
    return {name: (path, ast.parse(path.read_text(), str(path))) for name, path in _modules().items()}


def _functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node


def test_modules_are_short() -> None:
    long = [f"{p} ({n} lines)" for p, n in ((p, len(p.read_text().splitlines())) for p, _ in _trees().values())
            if n > MAX_MODULE_LINES]
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_functions_are_short() -> None:
    long = [f"{p}:{f.lineno} {f.name} ({f.end_lineno - f.lineno + 1} lines)" for p, tree in _trees().values()
            for f in _functions(tree) if f.end_lineno - f.lineno + 1 > MAX_FUNCTION_LINES]
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


def parameter_count(f: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Parameters of ``f``, ``*args`` and ``**kwargs`` included, ``self`` and ``cls`` not."""
    a = f.args
    names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    return len([n for n in names if n not in ("self", "cls")]) + bool(a.vararg) + bool(a.kwarg)


def test_few_parameters() -> None:
    many = [f"{p}:{f.lineno} {f.name} ({parameter_count(f)})" for p, tree in _trees().values()
            for f in _functions(tree) if parameter_count(f) > MAX_PARAMETERS]
    assert not many, f"functions with more than {MAX_PARAMETERS} parameters (take a settings object): {many}"


def test_public_class_names_are_unique() -> None:
    where = defaultdict(list)
    for name, (_, tree) in _trees().items():
        for node in tree.body:
            if isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                where[node.name].append(name)
    twice = {k: v for k, v in where.items() if len(v) > 1}
    assert not twice, f"public class names defined more than once: {twice}"


def layer_violations() -> list[str]:
    """Each import that crosses the layers the wrong way, as 'file:line: module imports target'."""
    mods = _modules()
    bad = []
    for name, (path, tree) in _trees().items():
        if name == ENTRY:
            continue
        for node in _imports(tree):
            targets = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if node.level == 0 else []
            for t in targets:
                if not t.startswith("posegrasp"):
                    continue
                while t and t not in mods:
                    t = t.rpartition(".")[0]
                if t and layer(t) != layer(name) and layer(t) not in ALLOWED[layer(name)]:
                    bad.append(f"{path}:{node.lineno}: {name} imports {t}")
    return bad


def test_layers_hold() -> None:
    bad = layer_violations()
    assert not bad, "imports across the layers (docs/architecture.md):\n" + "\n".join(bad)


def test_settings_are_frozen_and_checked() -> None:
    """Every dataclass whose name ends in ``Config`` is a ``@settings`` class: frozen, its ranges checked when
    built."""
    loose = []
    for name in _modules():
        if name.startswith("posegrasp.assets"):
            continue
        mod = importlib.import_module(name)
        for obj in vars(mod).values():
            if isinstance(obj, type) and obj.__module__ == name and obj.__name__.endswith("Config") \
                    and dataclasses.is_dataclass(obj):
                frozen = obj.__dataclass_params__.frozen
                checked = getattr(getattr(obj, "__post_init__", None), "__qualname__", "").startswith("settings.")
                if not (frozen and checked):
                    loose.append(f"{name}.{obj.__name__}")
    assert not loose, f"settings classes not declared with @settings: {loose}"
