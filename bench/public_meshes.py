"""Import public meshes from robosuite's and pybullet_data's object meshes, timed, and print the per-part table.

The meshes come from the packages' wheels (not installed in the project): unpack them and name the folders, e.g.
``unzip robosuite-1.5.2-*.whl 'robosuite/models/assets/objects/meshes/*'`` and
``unzip pybullet-3.2.7-*.whl 'pybullet_data/*'``, then

    .venv/bin/python bench/public_meshes.py --robosuite DIR/robosuite/models/assets/objects/meshes \
        --pybullet DIR/pybullet_data --out runs/public8 [--all] [--timeout 600]

Without ``--all`` it imports the chosen eight (``CHOSEN``) into one object set ``--out`` (one
``posegrasp objects import`` call, the way a user would) and then, to time them, each on its own. With ``--all``
it imports every mesh in ``MESHES`` on its own, each under ``OUT/parts/NAME``. Each import runs the real command
line in a subprocess under ``--timeout`` seconds; the table gives per part the file, unit and scale, imported or
the refusal, the repairs, the volume change, the workcell warnings, the size and the wall seconds, with the load
average (other processes on the machine slow the imports; say so when you quote the figures). With ``--all --check``
each imported part is then dropped into a scene (``posegrasp scene``), made into a 3-scene dataset that
``posegrasp dataset check`` must pass, and picked in 10 oracle pick-place episodes, under ``OUT/checks/NAME``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Mesh:
    """One public mesh: its package (``robosuite`` or ``pybullet``), path in the package's folder, ``--unit``,
    ``--scale``, set name, and why a scale other than the file's own is used (empty when none is)."""

    package: str
    path: str
    unit: str
    scale: float
    name: str
    scaled: str = ""


#: Every public mesh that describes a solid object, with the unit and scale it is imported at. A URDF carries its
#: mesh's scale and colour; ``scaled`` says where the real size would not suit the workcell (the Jaco hand opens
#: 85 mm; the pick area is 240 x 300 mm) or the file has no unit.
MESHES = (
    Mesh("robosuite", "bread.stl", "m", 1.0, "bread"),
    Mesh("robosuite", "lemon.stl", "m", 1.0, "lemon"),
    Mesh("robosuite", "cereal.stl", "m", 1.0, "cereal"),
    Mesh("robosuite", "milk.stl", "m", 1.0, "milk"),
    Mesh("robosuite", "bottle.stl", "m", 1.0, "bottle"),
    Mesh("robosuite", "can.stl", "m", 1.0, "can"),
    Mesh("pybullet", "duck_vhacd.urdf", "m", 1.0, "duck"),
    Mesh("pybullet", "lego/lego.urdf", "m", 1.0, "lego"),
    Mesh("pybullet", "teddy_vhacd.urdf", "m", 1.0, "teddy"),
    Mesh("pybullet", "bunny.obj", "m", 0.05, "bunny", "no unit in the file; 0.05 makes it 99 mm tall"),
    Mesh("pybullet", "torus/torus_textured.obj", "m", 0.05, "torus", "1.5 m across as written; 0.05 makes it 75 mm"),
    Mesh("pybullet", "objects/mug.urdf", "m", 1.0, "mug"),
    Mesh("pybullet", "domino/domino.urdf", "m", 1.0, "domino"),
    Mesh("pybullet", "jenga/jenga.urdf", "m", 1.0, "jenga"),
    Mesh("pybullet", "cube_small.urdf", "m", 1.0, "cube_small"),
    Mesh("pybullet", "sphere_small.urdf", "m", 1.0, "sphere_small"),
    Mesh("pybullet", "block.urdf", "m", 1.0, "block"),
    Mesh("pybullet", "soccerball.urdf", "m", 0.06, "soccerball", "1 m ball as written; 0.06 makes it 60 mm"),
    Mesh("pybullet", "sphere_1cm.urdf", "m", 1.0, "sphere_1cm"),
    Mesh("pybullet", "random_urdfs/000/000.urdf", "m", 1.0, "random_000"),
    Mesh("pybullet", "random_urdfs/001/001.urdf", "m", 1.0, "random_001"),
    Mesh("pybullet", "random_urdfs/002/002.urdf", "m", 1.0, "random_002"),
)

#: The eight parts of the public-mesh benchmark set, in set order (names from ``MESHES``).
CHOSEN = ("bread", "lemon", "cereal", "milk", "bottle", "duck", "teddy", "bunny")
#: Scales of the set's parts other than ``MESHES``'s, with why: a full-size cereal box lies flat on its 100 x 150 mm
#: face, where no span across it fits the hand's 85 mm opening, and two of them fill half the pick area.
SET_SCALE = {"cereal": (0.5, "lying flat, a full-size box offers the top-down hand no span under 85 mm; 0.5 makes it "
                              "50 x 15 x 75 mm")}


def _root(m: Mesh, args: argparse.Namespace) -> Path:
    return Path(args.robosuite if m.package == "robosuite" else args.pybullet)


def _import(meshes: list[Mesh], args: argparse.Namespace, out: Path) -> tuple[str, float]:
    """Run ``posegrasp objects import`` on ``meshes`` into ``out``: (error line or "", wall seconds)."""
    err, s, _ = _cli(["objects", "import", *[str(_root(m, args) / m.path) for m in meshes], "--out", str(out),
                      "--unit", *[m.unit for m in meshes], "--scale", *[f"{m.scale:g}" for m in meshes],
                      "--name", *[m.name for m in meshes], "--no-progress"], args.timeout)
    return err, s


def _cli(argv: list[str], timeout: float) -> tuple[str, float, str]:
    """Run ``posegrasp ARGV``: (last error line or "", wall seconds, stderr)."""
    cmd = [sys.executable, "-m", "posegrasp.cli", *argv]
    t0 = time.perf_counter()
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"timed out after {timeout:g} s", time.perf_counter() - t0, ""
    s = time.perf_counter() - t0
    if r.returncode != 0:
        lines = (r.stderr.strip() or r.stdout.strip() or f"exit {r.returncode}").splitlines()
        return lines[-1], s, r.stderr
    return "", s, r.stderr


def _unstable(stderr: str) -> str:
    """" (unstable: N)" when MuJoCo warned of NaN/Inf accelerations N times, else ""."""
    n = stderr.count("The simulation is unstable")
    return f" (unstable: {n})" if n else ""


def _check(m: Mesh, args: argparse.Namespace) -> dict:
    """Drop ``OUT/parts/NAME`` into a scene, make a 3-scene dataset of it and check it, and run 10 oracle pick-place
    episodes, each through the real command line under ``OUT/checks/NAME``: a dict of the steps' results."""
    part, out = args.out / "parts" / m.name, args.out / "checks" / m.name
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    err, _, log = _cli(["scene", "--objects", str(part), "--blocks", "3", "--seed", "0", "--out", str(out / "scene")],
                       args.timeout)
    if not err:
        z = [b["T_world_obj"][2][3] for b in json.loads((out / "scene" / "scene.json").read_text())["blocks"]]
        if not all(-0.01 < v < 0.25 for v in z):
            err = "exploded: z " + ", ".join(f"{v * 1000:.0f}" for v in z) + " mm"
    row = {"scene": (err or "ok") + _unstable(log)}
    err, _, log = _cli(["datagen", "--objects", str(part), "--scenes", "3", "--views", "2", "--workers", "1",
                        "--out", str(out / "ds"), "--no-progress"], args.timeout)
    if not err:
        err, _, _ = _cli(["dataset", "check", str(out / "ds")], args.timeout)
    row["datagen"] = (err or "ok") + _unstable(log)
    err, _, log = _cli(["trials", "--task", "pick-place", "--objects", str(part), "--episodes", "10", "--seed", "1000",
                        "--workers", "1", "--perception", "oracle", "--out", str(out / "trials"), "--no-progress"],
                       args.timeout)
    if err:
        row["oracle"] = err + _unstable(log)
    else:
        s = json.loads((out / "trials" / "summary.json").read_text())
        row["oracle"] = f"{s['success']}/{s['n']} {s['failures'] or ''}".strip() + _unstable(log)
    return row


def _row(m: Mesh, error: str, seconds: float, entry: dict | None) -> dict:
    row = {"name": m.name, "file": f"{m.package}:{m.path}", "unit": m.unit, "scale": m.scale,
           "imported": not error, "seconds": round(seconds, 1)}
    if error:
        return {**row, "error": error}
    return {**row, "extents_mm": entry["_extents"], "mass_g": round(entry["mass_kg"] * 1000, 1),
            "pieces": len(entry["collision"]), "repairs": entry["repairs"],
            "warnings": entry["warnings"]}


def _entries(out: Path) -> dict[str, dict]:
    """The set's object entries by name, with the model's extents (mm) added as ``_extents``."""
    info = json.loads((out / "models" / "models_info.json").read_text())
    entries = {}
    for f in sorted((out / "objects").glob("obj_*.json")):
        e = json.loads(f.read_text())
        i = info[str(e["obj_id"])]
        e["_extents"] = [round(i["size_x"], 1), round(i["size_y"], 1), round(i["size_z"], 1)]
        entries[e["name"]] = e
    return entries


def _print(rows: list[dict]) -> None:
    print(f"{'name':<12} {'file':<38} {'unit':<4} {'scale':>5} {'s':>6}  result")
    for r in rows:
        head = f"{r['name']:<12} {r['file']:<38} {r['unit']:<4} {r['scale']:>5g} {r['seconds']:>6.1f}  "
        if not r["imported"]:
            print(head + "NOT IMPORTED: " + r["error"])
            continue
        x, y, z = r["extents_mm"]
        print(head + f"{x:.0f} x {y:.0f} x {z:.0f} mm, {r['mass_g']:.1f} g, {r['pieces']} pieces, "
                     f"{len(r['repairs'])} repairs, {len(r['warnings'])} warnings")
        for rep in r["repairs"]:
            print(f"{'':<14}repaired: {rep}")
        for w in r["warnings"]:
            print(f"{'':<14}warning: {w}")
        if "check" in r:
            c = r["check"]
            print(f"{'':<14}scene {c['scene']}; datagen+check {c['datagen']}; oracle pick-place {c['oracle']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robosuite", required=True, help="robosuite/models/assets/objects/meshes")
    ap.add_argument("--pybullet", required=True, help="pybullet_data")
    ap.add_argument("--out", required=True, type=Path, help="folder to write (the set, or parts/NAME with --all)")
    ap.add_argument("--all", action="store_true", help="import every mesh in MESHES on its own")
    ap.add_argument("--only", nargs="+", default=None, help="with --all: just these names")
    ap.add_argument("--check", action="store_true", help="with --all: also drop each part into a scene, make and "
                    "check a 3-scene dataset, and run 10 oracle pick-place episodes (OUT/checks/NAME)")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds allowed per import or check step")
    args = ap.parse_args()
    if args.check and not args.all:
        ap.error("--check goes with --all")
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    by_name = {m.name: m for m in MESHES}
    load0 = os.getloadavg()[0]
    rows = []
    if not args.all:
        chosen = [dataclasses.replace(by_name[n], scale=SET_SCALE[n][0], scaled=SET_SCALE[n][1]) if n in SET_SCALE
                  else by_name[n] for n in CHOSEN]
        err, s = _import(chosen, args, args.out)
        print(f"one set of {len(chosen)}: {'wrote ' + str(args.out) if not err else err} ({s:.1f} s wall)")
        if err:
            sys.exit(1)
        todo = chosen
    else:
        todo = [by_name[n] for n in args.only] if args.only else list(MESHES)
    for m in todo:
        out = args.out / "parts" / m.name
        if out.exists():
            shutil.rmtree(out)
        err, s = _import([m], args, out)
        rows.append(_row(m, err, s, None if err else _entries(out)[m.name]))
        if args.check and not err:
            rows[-1]["check"] = _check(m, args)
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    print(f"load average {load0:.1f} before, {os.getloadavg()[0]:.1f} after (2 cores)")
    _print(rows)
    for m in todo:
        if m.scaled:
            print(f"{m.name}: scale {m.scale:g}: {m.scaled}")


if __name__ == "__main__":
    main()
