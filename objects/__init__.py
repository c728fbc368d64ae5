"""Object sets: any meshes (STL, OBJ, PLY, a BOP ``models/`` folder) turned into a folder the testbed can load.

``posegrasp objects import`` reads, repairs and measures the meshes, finds their symmetries, decomposes them into
convex collision pieces (CoACD) and writes an object set (``objset``); ``posegrasp objects show`` draws one. The
format is described in ``docs/objects.md``.
"""
