"""STEP (ISO 10303-21) parts: the B-rep tessellated by OpenCASCADE through ``cascadio`` (STEP -> GLB).

The tessellation keeps every face within ``linear`` metres of the true surface and turns the normal by at most
``angular`` radians between neighbouring triangles. The file's declared length unit is applied (glTF is in metres),
so ``--unit`` is not; ``--scale`` is. Solid colours of the file are not read.
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

from posegrasp.errors import UserError
from posegrasp.inputs import library_output
import posegrasp.objects.formats.meshfile as meshfile
from posegrasp.objects.formats.part import Part


def read(path: Path, linear: float, angular: float) -> Part:
    """The tessellated part in ``path`` (m), its bodies in one mesh."""
    import cascadio

    head = path.open("rb").read(64).lstrip()
    if not head.startswith(b"ISO-10303-21"):
        raise UserError(f"{path}: not a STEP file (it does not start with ISO-10303-21)")
    with tempfile.TemporaryDirectory(prefix="posegrasp-step-") as tmp:
        glb = Path(tmp) / "part.glb"
        with library_output((1, 2)) as said:  # OpenCASCADE's own messages: the first error goes into ours
            # OpenCASCADE reads STEP in millimetres: the linear deflection is given in mm
            rc = cascadio.step_to_glb(str(path), str(glb), tol_linear=linear * 1000.0, tol_angular=angular,
                                      tol_relative=False, use_parallel=False)
        if rc != 0 or not glb.is_file() or glb.stat().st_size == 0:
            why = next((re.sub(r"\x1b\[[0-9;]*m|\*+", "", ln).strip() for ln in said if "ERR" in ln), "")
            raise UserError(f"{path}: OpenCASCADE could not read a solid from it (corrupt or empty STEP"
                            f"{'; ' + why[:160] if why else ''})")
        try:
            part = meshfile.read(glb)
        except UserError:
            raise UserError(f"{path}: the STEP file holds no faces to tessellate (corrupt or empty STEP)") from None
    return Part(part.mesh)
