"""Seconds per object of ``posegrasp objects import``, and of its CoACD convex decomposition alone.

Imports the shipped blocks' BOP models (symmetries taken from their models_info.json) and three meshes made here
(a U-channel, a mug with a handle, a cylinder with a cap missing; symmetries searched) with the default
settings, and prints per object the wall and CPU seconds of the whole import and of CoACD alone, the piece count
and the pieces' volume over the mesh's, with the load average before and after (other processes on the machine
slow this down; say so when you quote the figures).
Run: ``.venv/bin/python bench/objects.py``.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import trimesh  # noqa: E402

from posegrasp import ASSETS
from posegrasp.objects import examples
from posegrasp.objects.config import ImportConfig
from posegrasp.objects.decompose import convex_pieces
from posegrasp.objects.importer import import_object, sources


def _made_meshes(d: Path) -> list[Path]:
    """A U-channel, a mug with a handle and a capless cylinder, as PLY in metres under ``d``."""
    u = examples.u_channel((0.06, 0.03, 0.01), -0.015, (0.01, 0.03, 0.04), 0.025)
    mug = examples.mug(0.03, 0.025, 0.08, 0.01, (0.012, 0.02, 0.01, 0.035))
    cyl = trimesh.creation.cylinder(0.015, 0.05, sections=32)
    capless = trimesh.Trimesh(cyl.vertices, cyl.faces[cyl.face_normals[:, 2] < 0.5])
    out = []
    for name, m in (("u_channel", u), ("mug", mug), ("capless_cylinder", capless)):
        out.append(d / f"{name}.ply")
        m.export(out[-1])
    return out


def main() -> None:
    cfg = ImportConfig()
    load0 = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        made = _made_meshes(Path(tmp))
        srcs = sources([ASSETS / "blocks" / "models"], ["mm"]) + sources(made, ["m"])
        for i, src in enumerate(srcs, start=1):
            w0, c0 = time.perf_counter(), time.process_time()
            obj = import_object(src, i, cfg)
            w1, c1 = time.perf_counter(), time.process_time()
            convex_pieces(trimesh.Trimesh(obj.vertices, obj.faces), cfg.max_pieces, cfg.coacd_threshold, cfg.seed)
            w2, c2 = time.perf_counter(), time.process_time()
            rows.append({"object": src.path.stem, "faces": len(obj.faces), "import_wall_s": round(w1 - w0, 2),
                         "import_cpu_s": round(c1 - c0, 2), "coacd_wall_s": round(w2 - w1, 2),
                         "coacd_cpu_s": round(c2 - c1, 2), "pieces": len(obj.collision),
                         "volume_ratio": round(obj.collision_volume_ratio, 3), "repairs": list(obj.repairs)})
    print(f"{'object':18s} {'faces':>6s} {'import s':>9s} {'cpu s':>7s} {'CoACD s':>8s} {'cpu s':>7s} "
          f"{'pieces':>6s} {'vol':>6s}")
    for r in rows:
        print(f"{r['object']:18s} {r['faces']:6d} {r['import_wall_s']:9.2f} {r['import_cpu_s']:7.2f} "
              f"{r['coacd_wall_s']:8.2f} {r['coacd_cpu_s']:7.2f} {r['pieces']:6d} {r['volume_ratio']:6.3f}")
    print(json.dumps({"rows": rows, "loadavg_before": load0, "loadavg_after": os.getloadavg()[0],
                      "cpus": os.cpu_count()}))


if __name__ == "__main__":
    main()
