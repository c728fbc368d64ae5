"""Object sets: any meshes (STL, PLY, OBJ, GLB/GLTF, STEP, URDF, a BOP ``models/`` folder) turned into a folder the
testbed can load.

``posegrasp objects import`` reads, repairs and measures the meshes, finds their symmetries, decomposes them into
convex collision pieces (CoACD) and writes an object set (``posegrasp.objset``, a core module: the simulator reads
sets through ``posegrasp.catalog``); ``posegrasp objects show`` draws one. The format is described in
``docs/objects.md``.
"""
