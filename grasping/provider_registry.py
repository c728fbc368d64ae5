"""Perception providers by name: ``make_provider(spec)`` builds the provider a ``--perception`` value names.

- ``oracle`` and ``noisy-oracle[:TRANS_M,ROT_DEG]``: ``grasping.perception``;
- ``model[:RUN]``: the learned network, ``grasping.model_provider``, imported (with torch) only when asked for;
- ``depth-icp[:SETTINGS.toml]``: the training-free estimator of any object set, ``grasping.depth_icp_provider``;
- ``bop-csv:RESULTS.csv``: a BOP results file's estimates for the campaign's captures, ``grasping.bop_csv``;
- ``py:MODULE_OR_FILE:FACTORY[:ARGS]``: a plug-in, ``FACTORY(ARGS)`` of an importable module or a ``.py`` file;
- ``NAME[:ARGS]`` registered by an installed package in the entry-point group ``posegrasp.perception``
  (``NAME = "module:factory"``); a built-in name wins over an installed one.

A plug-in's factory gets ARGS (the text after its name, or None) and, if it has a parameter named ``objects``, the
object set's folder (absolute); it returns a ``grasping.perception.Provider``. A plug-in is loaded, built and asked
for estimates in a child process of its own, once per process (``grasping.plugin_host``; ``docs/estimators.md``).
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.metadata
import inspect
import os
import sys
from pathlib import Path
from types import ModuleType
from typing import Callable

from posegrasp.catalog import set_root
from posegrasp.errors import ProviderError, UserError
from posegrasp.grasping.perception import Provider, noisy_oracle_from_spec, oracle_from_spec
from posegrasp.grasping.plugin_host import IsolatedProvider, _why


def _model(args: str | None, objects: str) -> Provider:
    from posegrasp.grasping.model_provider import from_spec

    return from_spec(args, objects)


def _depth_icp(args: str | None, objects: str) -> Provider:
    from posegrasp.grasping.depth_icp_provider import from_spec

    return from_spec(args, objects)


def _bop_csv(args: str | None, objects: str) -> Provider:
    from posegrasp.grasping.bop_csv import from_spec

    return from_spec(args, objects)


#: Provider factories by name; each gets the text after ``name:`` (or None) and the object set's folder
#: (``WorkcellConfig.objects``; ``""``: the shipped blocks), which the oracles need not know.
FACTORIES: dict[str, Callable[[str | None, str], Provider]] = {
    "oracle": lambda args, objects: oracle_from_spec(args),
    "noisy-oracle": lambda args, objects: noisy_oracle_from_spec(args),
    "model": _model,
    "depth-icp": _depth_icp,
    "bop-csv": _bop_csv,
    "ppf": lambda args, objects: importlib.import_module("posegrasp.grasping.ppf_provider").from_spec(args, objects),
}


#: The entry-point group in which installed packages register provider factories by name.
ENTRY_POINT_GROUP = "posegrasp.perception"


#: Wall seconds a plug-in may take to load and per estimate when the caller names no limit
#: (``TrialConfig.perception_timeout_s``'s default).
PLUGIN_TIMEOUT_S = 60.0


def make_provider(spec: str, objects: str = "", timeout_s: float | None = None) -> Provider:
    """A provider from ``name[:ARGS]`` (``oracle``, ``noisy-oracle:0.005,5``, ``model:RUN``,
    ``py:MODULE_OR_FILE:FACTORY[:ARGS]`` or an installed name) for scenes of the object set ``objects`` (a set
    folder; ``""``: the shipped blocks). A plug-in runs in a process of its own (``grasping.plugin_host``), with
    ``timeout_s`` wall seconds to load and per estimate (0: no limit; None: as before, else ``PLUGIN_TIMEOUT_S``).
    Raises a one-line ProviderError when it cannot be built."""
    name, _, args = spec.partition(":")
    if name in FACTORIES:
        return FACTORIES[name](args or None, objects)
    if name == "py" or name in installed_providers():
        if name == "py":
            _plugin_parts(spec)  # a malformed spec says so before any process starts
        provider = _isolated(spec, objects, PLUGIN_TIMEOUT_S if timeout_s is None else timeout_s)
        if timeout_s is not None:
            provider.timeout_s = timeout_s
        return provider
    installed = ", ".join(sorted(installed_providers())) or f"none (entry-point group {ENTRY_POINT_GROUP})"
    raise ProviderError(f"unknown perception {spec!r}; choose one of: {', '.join(sorted(FACTORIES))}, "
                        f"py:MODULE_OR_FILE:FACTORY[:ARGS]; installed: {installed}")


def canonical_spec(spec: str) -> str:
    """``spec`` with a ``py:`` plug-in file's path made absolute, so that workers and later runs find it."""
    for name in ("bop-csv:", "depth-icp:", "ppf:"):  # the results or settings file's path absolute too
        if spec.startswith(name) and spec[len(name):]:
            return name + str(Path(spec[len(name):]).expanduser().resolve())
    if not spec.startswith("py:"):
        return spec
    target, factory, args = _plugin_parts(spec)
    if not _is_file(target):
        return spec
    return ":".join(["py", str(Path(target).expanduser().resolve()), factory] + ([args] if args is not None else []))


@functools.lru_cache(maxsize=1)
def installed_providers() -> dict[str, importlib.metadata.EntryPoint]:
    """The provider factories installed packages register (entry-point group ``posegrasp.perception``), by name
    (read once per process)."""
    return {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


def _plugin_parts(spec: str) -> tuple[str, str, str | None]:
    """MODULE_OR_FILE, FACTORY and ARGS (None if absent) of ``py:MODULE_OR_FILE:FACTORY[:ARGS]``."""
    target, _, rest = spec[3:].partition(":")
    factory, sep, args = rest.partition(":")
    if not target or not factory.isidentifier():
        raise ProviderError(f"perception {spec!r} is not py:MODULE_OR_FILE:FACTORY[:ARGS], e.g. "
                            "py:examples/providers/depth_only.py:make_provider")
    return target, factory, args if sep else None


def _is_file(target: str) -> bool:
    return target.endswith(".py") or "/" in target or os.sep in target


#: The plug-ins started in this process, by spec and object set.
_STARTED: dict[tuple[str, str], IsolatedProvider] = {}


def _isolated(spec: str, objects: str, timeout_s: float) -> IsolatedProvider:
    """The plug-in ``spec`` in its own process, started once per process and object set (a failed start is
    tried again by the next call)."""
    if (spec, objects) not in _STARTED:
        _STARTED[spec, objects] = IsolatedProvider(spec, objects, timeout_s, _plugin)
    return _STARTED[spec, objects]


@functools.lru_cache(maxsize=8)
def _plugin(spec: str, objects: str) -> Provider:
    """The provider a ``py:`` spec or an installed name builds (once per process and object set)."""
    name, _, args = spec.partition(":")
    if name == "py":
        target, attr, args = _plugin_parts(spec)
        module = _load_file(spec, target) if _is_file(target) else _import(spec, target)
        factory = getattr(module, attr, None)
        if not callable(factory):
            raise ProviderError(f"perception {spec!r}: {target} has no callable {attr!r}")
    else:
        try:
            factory = installed_providers()[name].load()
        except Exception as e:
            raise ProviderError(f"perception {spec!r}: loading the installed entry point "
                                f"{installed_providers()[name].value!r} failed: {_why(e)}") from None
    try:
        kw = {"objects": str(set_root(objects))} if "objects" in inspect.signature(factory).parameters else {}
    except (TypeError, ValueError):  # no signature to read (a builtin): ARGS only
        kw = {}
    try:
        provider = factory(args or None, **kw)
    except UserError as e:
        raise ProviderError(f"perception {spec!r}: {e}") from None
    except Exception as e:
        raise ProviderError(f"perception {spec!r}: its factory raised {_why(e)}") from None
    if not callable(getattr(provider, "estimate", None)) or not isinstance(getattr(provider, "name", None), str):
        raise ProviderError(f"perception {spec!r}: the factory returned a {type(provider).__name__}, not a provider "
                            "(it needs a str 'name' and an 'estimate(obs, seed)' method; docs/estimators.md)")
    return provider


def _import(spec: str, module: str) -> ModuleType:
    """The importable ``module``, or a UserError."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name is not None and (module == e.name or module.startswith(e.name + ".")):
            raise ProviderError(f"perception {spec!r}: no module named {module!r}; install it, add its folder to "
                                "PYTHONPATH or give the path of its .py file") from None
        raise ProviderError(f"perception {spec!r}: importing {module} failed: {_why(e)}") from None
    except Exception as e:
        raise ProviderError(f"perception {spec!r}: importing {module} failed: {_why(e)}") from None


def _load_file(spec: str, target: str) -> ModuleType:
    """The module of the ``.py`` file ``target``, loaded once per process under a name made from its path."""
    path = Path(target).expanduser().resolve()
    if not path.is_file():
        raise ProviderError(f"perception {spec!r}: no file {path}; give the path of a .py file or an importable module")
    name = f"posegrasp_plugin_{hashlib.sha256(str(path).encode()).hexdigest()[:12]}"
    if name in sys.modules:
        return sys.modules[name]
    module = ModuleType(name)
    module.__file__ = str(path)
    sys.modules[name] = module  # (dataclasses and pickling look a class's module up there)
    try:  # compiled here, so that no __pycache__ is written beside the user's file
        exec(compile(path.read_bytes(), str(path), "exec"), module.__dict__)
    except Exception as e:
        del sys.modules[name]
        raise ProviderError(f"perception {spec!r}: importing {path} failed: {_why(e)}") from None
    return module
