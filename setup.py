"""The compiled part of posegrasp, the depth fit's kernels (``perception/depth_fit/_*.c``, loaded with ctypes by
``perception.depth_fit.kernels``); everything else is declared in pyproject.toml."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("posegrasp.perception.depth_fit._kernels",
                             ["perception/depth_fit/_icp.c", "perception/depth_fit/_score.c"],
                             depends=["perception/depth_fit/_kernels.h", "perception/depth_fit/_parallel.h"],
                             extra_compile_args=["-O3", "-fno-trapping-math", "-fopenmp"], extra_link_args=["-fopenmp"],
                             libraries=["m"])])
