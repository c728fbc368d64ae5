"""Depth images of object models at given poses, rendered with pyrender (for VSD, as bop_toolkit renders them).

Camera frame OpenCV (x right, y down, z forward), K in pixels with pixel centres at integer coordinates (as the
dataset's images); depth in metres along the optical axis, 0 where the model is not. One pyrender scene holds
every model once; a render shows one of them at its pose. The renderer is the process's (``posegrasp.gl``).
"""

from __future__ import annotations

import numpy as np

from posegrasp.errors import UserError
from posegrasp.gl import pyrender_renderer

#: pyrender's principal point is in pixel-edge coordinates (+0.5 px), and its depth is read from a 4x multisampled
#: buffer, i.e. at sample 0, which Mesa places at (-1/8, +3/8) px from the pixel centre: K shifted by this samples
#: the pixel centres of an OpenCV K.
PYRENDER_PP_SHIFT = (0.5 - 0.125, 0.5 + 0.375)
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes -> OpenGL camera axes


class DepthRenderer:
    """Renders the depth (m) of one model alone at a pose ``T_cam_obj`` (4x4, m).

    ``models``: {obj_id: trimesh mesh in metres}. ``znear`` / ``zfar`` (m) clip as bop_toolkit's renderer does
    (10 mm, 10 m).
    """

    def __init__(self, models: dict, znear: float = 0.01, zfar: float = 10.0):
        try:
            import pyrender
        except ImportError:
            raise UserError("the VSD metric renders depth with pyrender: pip install 'posegrasp[render]'") from None

        self._flags = pyrender.RenderFlags.DEPTH_ONLY
        self._scene = pyrender.Scene()
        self._camera = pyrender.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=znear, zfar=zfar)
        self._scene.add(self._camera, pose=CV_TO_GL)
        self._nodes = {int(o): self._scene.add(pyrender.Mesh.from_trimesh(m, smooth=False)) for o, m in models.items()}

    def __call__(self, obj_id: int, T_cam_obj: np.ndarray, K: np.ndarray, height: int, width: int) -> np.ndarray:
        """(height, width) float32 depth (m) of model ``obj_id`` alone at ``T_cam_obj`` seen through ``K``."""
        c = self._camera
        c.fx, c.fy = float(K[0, 0]), float(K[1, 1])
        c.cx, c.cy = float(K[0, 2]) + PYRENDER_PP_SHIFT[0], float(K[1, 2]) + PYRENDER_PP_SHIFT[1]
        for o, node in self._nodes.items():
            node.mesh.is_visible = o == obj_id
        self._scene.set_pose(self._nodes[obj_id], np.asarray(T_cam_obj, dtype=np.float64))
        depth = pyrender_renderer(width, height).render(self._scene, flags=self._flags)
        return np.asarray(depth, dtype=np.float32)
