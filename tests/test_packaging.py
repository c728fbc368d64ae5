"""One import name: the package installs as ``posegrasp`` only, its modules import without cycles, and
perception stays free of the simulator (it also runs on real camera data)."""

from __future__ import annotations

import ast
import functools
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import networkx as nx
import pytest

import posegrasp

ROOT = Path(__file__).resolve().parents[1]
#: Package name -> folder, as pyproject.toml maps them.
PACKAGES = {"posegrasp": "posegrasp", "posegrasp.sim": "sim", "posegrasp.datagen": "datagen",
            "posegrasp.perception": "perception", "posegrasp.perception.depth_fit": "perception/depth_fit",
            "posegrasp.grasping": "grasping", "posegrasp.objects": "objects", "posegrasp.assets": "assets"}
PARTS = ("sim", "datagen", "perception", "grasping", "objects")


def _modules() -> dict[str, Path]:
    """Every module of the package and of its subpackages (folders with an ``__init__.py``), by dotted name."""
    mods = {}
    for pkg, folder in PACKAGES.items():
        root = ROOT / folder
        for f in sorted(root.rglob("*.py")):
            parts = f.relative_to(root).with_suffix("").parts
            if all((root.joinpath(*parts[:i]) / "__init__.py").is_file() for i in range(1, len(parts))):
                mods[".".join((pkg, *parts)).removesuffix(".__init__")] = f
    return mods


def _imports(tree: ast.AST):
    """The import statements of a module, those inside functions included; not those under ``if TYPE_CHECKING:``,
    which never run (they name types for annotations only)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            todo.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        todo.extend(ast.iter_child_nodes(node))


@functools.lru_cache(maxsize=1)
def import_graph() -> nx.DiGraph:
    """Module -> module edges for every import statement of the package that runs, those inside functions
    included."""
    mods = _modules()
    g = nx.DiGraph()
    g.add_nodes_from(mods)
    for name, path in mods.items():
        for node in _imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in mods else node.module
                           for a in node.names]
            else:
                continue
            for t in targets:
                while t and t not in mods:  # `import posegrasp.sim.camera as c` -> the module itself
                    t = t.rpartition(".")[0]
                if t and t != name:
                    g.add_edge(name, t)
    return g


def test_no_import_cycles() -> None:
    cycles = sorted(sorted(c) for c in nx.strongly_connected_components(import_graph()) if len(c) > 1)
    assert not cycles, f"import cycles: {cycles}"


def test_perception_never_imports_the_simulator() -> None:
    g = import_graph()
    for mod in [m for m in g if m.startswith("posegrasp.perception")]:
        bad = [d for d in nx.descendants(g, mod) if d.split(".")[1:2] and d.split(".")[1] in ("sim", "datagen", "grasping")]
        assert not bad, f"{mod} imports (perhaps through others) {sorted(bad)}"


def _python(code: str, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def test_one_top_level_name(tmp_path: Path) -> None:
    ok = _python("import posegrasp.sim, posegrasp.perception, posegrasp.grasping, posegrasp.datagen", tmp_path)
    assert ok.returncode == 0, ok.stderr
    for name in PARTS:
        r = _python(f"import {name}", tmp_path)
        assert r.returncode != 0 and "No module named" in r.stderr, f"'import {name}' works: {r.stdout}{r.stderr}"


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A wheel built by pip from a copy of the checkout's sources (so no stale build/ folder can leak in)."""
    src = tmp_path_factory.mktemp("src")
    shutil.copy(ROOT / "pyproject.toml", src)
    for folder in PACKAGES.values():
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"),
                        dirs_exist_ok=True)  # (a subpackage's folder lies inside its parent's)
    out = tmp_path_factory.mktemp("wheel")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(out),
                        str(src)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    (whl,) = out.glob("posegrasp-*.whl")
    return whl


@pytest.mark.slow
def test_wheel_holds_one_package_and_its_assets(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names} == {"posegrasp", "posegrasp-0.1.0.dist-info"}
    for pkg in PACKAGES:
        assert f"{pkg.replace('.', '/')}/__init__.py" in names
    assets = {n.removeprefix("posegrasp/assets/") for n in names if n.startswith("posegrasp/assets/")}
    shipped = {str(p.relative_to(posegrasp.ASSETS)) for p in posegrasp.ASSETS.rglob("*")
               if p.is_file() and "__pycache__" not in p.parts}
    assert shipped <= assets, f"assets missing from the wheel: {sorted(shipped - assets)}"
    assert "posegrasp/datagen/datagen.toml" in names


@pytest.mark.slow
def test_installed_wheel_runs_from_any_folder(wheel: Path, tmp_path: Path) -> None:
    """Installed (not editable) into a fresh target, the wheel finds its assets and runs a command elsewhere."""
    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), str(wheel)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    code = ("import sys, posegrasp; from posegrasp.cli import main; "
            "assert posegrasp.__file__.startswith(sys.argv[1]), posegrasp.__file__; "
            "sys.exit(main(['scene', '--seed', '3', '--blocks', '2', '--resolution', '160x120', '--out', 'out']))")
    r = subprocess.run([sys.executable, "-c", code, str(site)], cwd=work, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert (work / "out" / "scene.json").exists() and (work / "out" / "rgb.png").exists()


@pytest.mark.parametrize("code, status, stderr", [("None", 0, ""), ("3", 3, ""), ("'no such run'", 1, "no such run\n")])
def test_the_program_exits_with_its_status_after_its_exit_handlers_and_output(code: str, status: int,
                                                                               stderr: str) -> None:
    """``entry`` ends the process at once (``exit_now``), but as ``sys.exit`` would: the status, the exit handlers
    run, buffered output written."""
    script = ("import atexit, sys\nfrom posegrasp import cli\natexit.register(print, 'handler ran')\n"
              f"print('buffered', end=' ')\ncli.main = lambda: sys.exit({code})\ncli.entry()\n")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert (r.returncode, r.stdout, r.stderr) == (status, "buffered handler ran\n", stderr)
