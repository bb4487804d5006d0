"""glaciar: injection-recovery completeness and selection functions for galaxy surveys.

The two objects most users need are imported lazily so that ``import glaciar``
stays cheap:

- :func:`glaciar.sersic_stamp` renders a pixel-integrated Sersic stamp;
- :class:`glaciar.SelectionFunction` reads an exported selection-function file.
"""
from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["sersic_stamp", "SelectionFunction", "__version__"]


def __getattr__(name):
    if name == "sersic_stamp":
        from .galaxy.sersic import sersic_stamp
        return sersic_stamp
    if name == "SelectionFunction":
        from .inference.selection_function import SelectionFunction
        return SelectionFunction
    raise AttributeError(f"module 'glaciar' has no attribute {name!r}")
