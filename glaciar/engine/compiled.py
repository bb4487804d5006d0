"""The engine's optional compiled kernels: :mod:`glaciar.engine.kernels` where it was built
(pip install compiles it where a C compiler exists, see setup.py), else None.

Each module that uses a kernel keeps its numpy code, which gives the same numbers, and
takes the kernel from here as its own ``KERNEL`` (None runs the numpy code; the tests run
both).
"""
from __future__ import annotations

__all__ = ["KERNELS"]

try:
    from glaciar.engine import kernels as KERNELS
except ImportError:
    KERNELS = None
