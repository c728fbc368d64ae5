"""The compiled parts of posegrasp, loaded with ctypes (``posegrasp.native``): the depth fit's kernels
(``perception/depth_fit/_*.c``, ``perception.depth_fit.kernels``) and the depth camera model's per-pixel steps
(``datagen/_sensor.c``, ``datagen.sensor``); everything else is declared in pyproject.toml."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("posegrasp.perception.depth_fit._kernels",
                             ["perception/depth_fit/_icp.c", "perception/depth_fit/_score.c"],
                             depends=["perception/depth_fit/_kernels.h", "perception/depth_fit/_parallel.h"],
                             extra_compile_args=["-O3", "-fno-trapping-math", "-fopenmp"], extra_link_args=["-fopenmp"],
                             libraries=["m"]),
                   # numpy's float operations, each rounded on its own: no fused multiply-adds
                   Extension("posegrasp.datagen._sensor", ["datagen/_sensor.c"],
                             extra_compile_args=["-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math"],
                             libraries=["m"])])
