"""A part's looks where one colour does not say them: a textured surface (triangles, texture coordinates, image).

Texture coordinates follow OpenGL and OBJ: ``(u, v)`` in [0, 1], ``v = 0`` at the image's bottom row. Colours given
per vertex or per face are baked into a small palette image, one square of texels per colour, so every look is one
textured surface; several are merged by stacking their images. In an object set the surface is stored beside the
object's file: ``objects/obj_NNNNNN_surface.ply`` (binary PLY, metres, object frame, ``texture_u``/``texture_v`` per
vertex) and ``objects/obj_NNNNNN_texture.png``.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

#: Texels per side of a baked colour's square (its centre keeps the colour under the renderer's mipmaps).
_BLOCK = 8


@dataclass(frozen=True, eq=False)
class TexturedSurface:
    """Triangles (m) with a texture: ``vertices`` (N, 3), ``faces`` (M, 3), ``uv`` (N, 2), ``image`` (H, W, 3)
    uint8 RGB, row 0 at the top."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    image: np.ndarray

    def moved(self, scale: float, offset: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
              T: np.ndarray | None = None) -> "TexturedSurface":
        """The surface with ``v' = R (scale v) + t + offset`` (``T`` = [R | t], identity when None)."""
        v = np.asarray(self.vertices, np.float64) * scale
        if T is not None:
            v = v @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]
        return TexturedSurface(v + np.asarray(offset, np.float64), self.faces, self.uv, self.image)

    def png(self) -> bytes:
        """The image as PNG bytes (the same image gives the same bytes)."""
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(self.image, "RGB").save(buf, format="PNG", optimize=False)
        return buf.getvalue()

    def ply(self) -> bytes:
        """Binary PLY (metres) with ``texture_u``/``texture_v`` per vertex."""
        v = np.zeros(len(self.vertices), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("texture_u", "<f4"),
                                          ("texture_v", "<f4")])
        for i, k in enumerate("xyz"):
            v[k] = self.vertices[:, i]
        v["texture_u"], v["texture_v"] = self.uv[:, 0], self.uv[:, 1]
        f = np.zeros(len(self.faces), [("n", "u1"), ("i", "<i4", (3,))])
        f["n"], f["i"] = 3, self.faces
        head = ("ply\nformat binary_little_endian 1.0\ncomment units metres; TextureFile in the object's json\n"
                f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
                "property float texture_u\nproperty float texture_v\n"
                f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
        return head.encode() + v.tobytes() + f.tobytes()


def read_surface(ply: bytes, png: bytes) -> TexturedSurface:
    """The surface ``TexturedSurface.ply`` and ``.png`` wrote (ValueError when the bytes are not that)."""
    from PIL import Image

    end = ply.find(b"end_header\n")
    head = ply[:end].decode("ascii", "replace").split("\n")
    counts = {ln.split()[1]: int(ln.split()[2]) for ln in head if ln.startswith("element ")}
    if end < 0 or set(counts) != {"vertex", "face"} or "property float texture_u" not in head:
        raise ValueError("not a textured surface PLY")
    body = ply[end + len(b"end_header\n"):]
    vt = np.dtype([("p", "<f4", (3,)), ("uv", "<f4", (2,))])
    ft = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    v = np.frombuffer(body, vt, counts["vertex"])
    f = np.frombuffer(body, ft, counts["face"], offset=vt.itemsize * counts["vertex"])
    if (f["n"] != 3).any() or (f["i"] < 0).any() or (f["i"] >= len(v)).any():
        raise ValueError("faces are not triangles of its vertices")
    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    return TexturedSurface(v["p"].astype(np.float64), f["i"].astype(np.int64), v["uv"].astype(np.float64), image)


def baked(vertices: np.ndarray, faces: np.ndarray, face_rgb: np.ndarray) -> TexturedSurface:
    """A surface showing one colour per face (``face_rgb`` (M, 3) uint8): the faces' corners get their own
    vertices, mapped to the centre of their colour's square in a palette image."""
    colours, index = np.unique(np.asarray(face_rgb, np.uint8).reshape(-1, 3), axis=0, return_inverse=True)
    side = int(np.ceil(np.sqrt(len(colours))))
    image = np.zeros((side * _BLOCK, side * _BLOCK, 3), np.uint8)
    for k, c in enumerate(colours):
        r, col = divmod(k, side)
        image[r * _BLOCK:(r + 1) * _BLOCK, col * _BLOCK:(col + 1) * _BLOCK] = c
    r, col = np.divmod(index.ravel(), side)
    uv_face = np.stack([(col + 0.5) / side, 1.0 - (r + 0.5) / side], axis=1)
    faces = np.asarray(faces, np.int64)
    return TexturedSurface(np.asarray(vertices, np.float64)[faces].reshape(-1, 3),
                           np.arange(3 * len(faces), dtype=np.int64).reshape(-1, 3), np.repeat(uv_face, 3, axis=0),
                           image)


def merged(surfaces: list[TexturedSurface]) -> TexturedSurface:
    """One surface holding all of ``surfaces``, their images stacked top to bottom (widths padded to the widest)."""
    if len(surfaces) == 1:
        return surfaces[0]
    width = max(s.image.shape[1] for s in surfaces)
    height = sum(s.image.shape[0] for s in surfaces)
    image = np.zeros((height, width, 3), np.uint8)
    verts, faces, uvs, row, n = [], [], [], 0, 0
    for s in surfaces:
        h, w = s.image.shape[:2]
        image[row:row + h, :w] = s.image
        u = np.mod(s.uv, 1.0)  # the stacked images do not repeat: wrap coordinates into one copy
        uvs.append(np.stack([u[:, 0] * w / width, 1.0 - (row + (1.0 - u[:, 1]) * h) / height], axis=1))
        verts.append(s.vertices)
        faces.append(s.faces + n)
        row, n = row + h, n + len(s.vertices)
    return TexturedSurface(np.vstack(verts), np.vstack(faces), np.vstack(uvs), image)
