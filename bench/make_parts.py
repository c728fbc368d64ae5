"""Write the example parts (``posegrasp.objects.examples``) as mesh files in mixed formats and units, the way
CAD exports arrive, and print the ``posegrasp objects import`` command that makes them an object set.

Run: ``.venv/bin/python bench/make_parts.py /tmp/parts`` then the printed command (docs/objects.md).
"""

from __future__ import annotations

import sys
from pathlib import Path

from posegrasp.objects.examples import PARTS

#: (suffix, unit) per part, cycling: STL in mm, OBJ in m, PLY in mm.
_FORMATS = ((".stl", "mm"), (".obj", "m"), (".ply", "mm"))
_SCALE = {"m": 1.0, "mm": 1000.0}


def main(out: Path) -> None:
    """Write every example part under ``out`` and print the import command (object set ``out/set``)."""
    out.mkdir(parents=True, exist_ok=True)
    files, units = [], []
    for i, (name, make) in enumerate(PARTS.items()):
        suffix, unit = _FORMATS[i % len(_FORMATS)]
        path = out / f"{name}{suffix}"
        make().apply_scale(_SCALE[unit]).export(path)
        files.append(str(path))
        units.append(unit)
    print("posegrasp objects import " + " ".join(files) + " --unit " + " ".join(units) + f" --out {out / 'set'}")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/parts"))
