"""The optional C extension of kpifs (everything else is in pyproject.toml).

``kpifs.detect._kernels`` holds the binary tests' fused elementwise loops
(``kpifs/detect/_elementwise.py`` says why). It is optional: where it cannot be
built, the same numbers come from numpy, more slowly. On GCC and Clang,
``-ffp-contract=off`` keeps numpy's roundings (no fused multiply-adds) and
``-fno-trapping-math`` lets the compiler vectorise the clipping.
"""
from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

GNU_FLAGS = ["-O3", "-ffp-contract=off", "-fno-trapping-math"]


class BuildExt(build_ext):
    def build_extensions(self):
        if self.compiler.compiler_type != "msvc":
            for ext in self.extensions:
                ext.extra_compile_args = GNU_FLAGS
        super().build_extensions()


setup(ext_modules=[Extension("kpifs.detect._kernels", ["kpifs/detect/_kernels.c"],
                             optional=True)],
      cmdclass={"build_ext": BuildExt})
