"""Build of glaciar's optional compiled kernels (glaciar/engine/kernels.pyx).

Everything else about the package is in pyproject.toml.  The extension is optional: where it
cannot be built (no C compiler), glaciar installs without it and runs the numpy code that
gives the same numbers (glaciar.engine.shotnoise.KERNEL is None then).
"""
import os
import sys

import numpy as np
from Cython.Build import cythonize
from setuptools import Extension, setup

# The shot-noise kernel calls numpy's C distributions (Poisson, uniform), which numpy ships as
# a static library for extensions like this one (numpy/random/lib/libnpyrandom.a).
_NPYRANDOM = os.path.join(os.path.dirname(np.__file__), "random", "lib")
# No fused multiply-adds: a kernel must round as the numpy code it replaces does, on every
# machine (arm64 compilers contract a * b + c into one rounding by default).
_NO_FMA = [] if sys.platform == "win32" else ["-ffp-contract=off"]

_EXTENSIONS = cythonize(
    [Extension("glaciar.engine.kernels", ["glaciar/engine/kernels.pyx"],
               include_dirs=[np.get_include()], library_dirs=[_NPYRANDOM], libraries=["npyrandom"],
               define_macros=[("NPY_NO_DEPRECATED_API", "NPY_1_7_API_VERSION")],
               extra_compile_args=_NO_FMA)],
    language_level=3)
# Optional: a failed compilation is a warning, and glaciar installs without its kernels (set
# here, after cythonize, which builds new Extension objects without the flag).
for _ext in _EXTENSIONS:
    _ext.optional = True

setup(ext_modules=_EXTENSIONS)
