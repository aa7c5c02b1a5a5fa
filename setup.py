"""Builds the C++ CPU rasterizer (csrc/) as ``promptgs_engine._C``.

Needs a C++17 compiler with OpenMP (GCC >= 9 or Clang with libomp) and torch installed
beforehand; install with ``pip install --no-build-isolation -e .``.
"""

import sys

from setuptools import setup
from torch.utils.cpp_extension import BuildExtension, CppExtension

extra_compile_args = ["-O3", "-std=c++17", "-fopenmp", "-ffp-contract=fast"]
extra_link_args = ["-fopenmp"]
if sys.platform == "darwin":
    extra_compile_args = ["-O3", "-std=c++17", "-Xpreprocessor", "-fopenmp"]
    extra_link_args = ["-lomp"]

setup(
    ext_modules=[
        CppExtension(
            name="promptgs_engine._C",
            sources=[
                "csrc/bindings.cpp",
                "csrc/carve.cpp",
                "csrc/rasterize_forward.cpp",
                "csrc/rasterize_backward.cpp",
                "csrc/kernels.cpp",
                "csrc/project.cpp",
                "csrc/ssim.cpp",
            ],
            extra_compile_args=extra_compile_args,
            extra_link_args=extra_link_args,
        )
    ],
    cmdclass={"build_ext": BuildExtension},
)
