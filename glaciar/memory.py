"""Hand the memory of a finished simulation back to the system before the next step.

``glaciar simulate`` writes its summaries (report tables, PNG maps: matplotlib) after the
tasks.  By then the field context (its memory-mapped cache pages), the template cache and
the shot-noise splits that follow it are no longer read, and the allocator keeps the
pages the tasks freed: the summaries' own memory then comes on top of the tasks' peak.
:func:`release_memory` drops them first, so the summaries fit below that peak.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import gc

__all__ = ["release_memory", "trim_allocator"]


def trim_allocator() -> bool:
    """Return the C allocator's free pages to the system (glibc ``malloc_trim(0)``).

    Freed numpy arrays below the allocator's (adaptive) mmap threshold stay in this
    process's heap, counted in its resident set, until reused; this gives the whole
    free pages among them back.  Values are untouched.  True if it ran (glibc only;
    elsewhere a no-op).
    """
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):       # not glibc (musl, macOS): nothing to call
        return False
    trim.argtypes = [ctypes.c_size_t]
    trim(0)
    return True


def release_memory() -> None:
    """Drop this process's field contexts and template cache, collect, and trim the heap.

    For the end of a run (before its summaries): later tasks in this process would map
    the field cache and render their stamps again (same values, more CPU).
    """
    from .contexts import clear_contexts
    from .fieldprep import release_template_cache

    clear_contexts()
    release_template_cache()
    gc.collect()
    trim_allocator()
