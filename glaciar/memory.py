"""Hand memory a run no longer reads back to the system before its next step.

``glaciar simulate`` writes its summaries (report tables, PNG maps: matplotlib) after the
tasks.  By then the field context (its memory-mapped cache pages), the template cache and
the shot-noise splits that follow it are no longer read, and the allocator keeps the
pages the tasks freed: the summaries' own memory then comes on top of the tasks' peak.
:func:`release_memory` drops them first, so the summaries fit below that peak.

With one worker the field set-up runs in the process that then runs every task
(:func:`glaciar.execute.simulate`), and the pages of library code that only the imports,
the configuration and the set-up ran (the loaders' and initialisers' code of pandas,
pyarrow, scipy, astropy: ~75 MB on GLACiAR's 1200^2 4-band job) stay resident: code pages
are file-backed and count in the resident set (and in ``ru_maxrss``) like any other.
:func:`drop_file_pages` drops them at the hand-over, and once more after the first task
(its own first-time code: lazy imports, the parquet writer's set-up).  The pages the
tasks do run are read again from the page cache at their next touch (minor faults, ~36 MB
once on that job).  Peak RSS of the 50 400-source job: 465 -> 409 MB, 4 200 sources: 450 ->
396 MB, for ~60 ms of CPU (docs/accuracy-and-speed.md).  The heap pages the set-up freed
(~105 MB there) are not trimmed then: the tasks reuse them (the peak is the same with a
trim), and a trim makes them fault in again (~30 000 minor faults).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import gc
import mmap
import re

__all__ = ["release_memory", "trim_allocator", "drop_file_pages"]

#: Where this process's mappings and their resident pages are listed (Linux).
SMAPS = "/proc/self/smaps"
_MAPPING = re.compile(r"^([0-9a-f]+)-([0-9a-f]+) (\S+) \S+ \S+ \S+\s*(.*)$")


def trim_allocator() -> bool:
    """Return the C allocator's free pages to the system (glibc ``malloc_trim(0)``).

    Freed numpy arrays below the allocator's (adaptive) mmap threshold stay in this
    process's heap, counted in its resident set, until reused; this gives the whole
    free pages among them back.  Values are untouched.  True if it ran (glibc only;
    elsewhere a no-op).
    """
    trim = getattr(_libc(), "malloc_trim", None)
    if trim is None:                        # not glibc (musl, macOS): nothing to call
        return False
    trim.argtypes = [ctypes.c_size_t]
    trim(0)
    return True


def _libc():
    """The C library (ctypes), or None where it cannot be found or loaded."""
    name = ctypes.util.find_library("c")
    if not name:
        return None
    try:
        return ctypes.CDLL(name, use_errno=True)
    except OSError:
        return None


def _clean_file_mappings(smaps_text: str) -> list[tuple[int, int, int]]:
    """``(start, end, resident bytes)`` of the mappings whose resident pages can be dropped
    with no value lost: private, not writable, backed by a file (a path), with resident
    pages, none of them dirty or anonymous (a relocated read-only segment (RELRO) holds
    copied-on-write pages: it is left alone, dropping them would undo the relocation)."""
    out, cur = [], None
    for line in smaps_text.splitlines():
        m = _MAPPING.match(line)
        if m is not None:
            start, end, perms, path = int(m.group(1), 16), int(m.group(2), 16), m.group(3), m.group(4)
            ok = perms[1] == "-" and perms[3] == "p" and path.startswith("/")
            cur = {"span": (start, end), "ok": ok, "Rss": 0, "dirty": 0}
            out.append(cur)
            continue
        if cur is None:
            continue
        key, _, value = line.partition(":")
        if key == "Rss":
            cur["Rss"] = int(value.split()[0]) * 1024
        elif key in ("Anonymous", "Private_Dirty", "Shared_Dirty", "AnonHugePages", "Swap"):
            cur["dirty"] += int(value.split()[0])
    return [(c["span"][0], c["span"][1], c["Rss"]) for c in out
            if c["ok"] and c["Rss"] and not c["dirty"]]


def drop_file_pages() -> int:
    """Drop the resident pages of this process's clean read-only file mappings; bytes dropped.

    The code and read-only data of the shared libraries (and any file mapped privately
    and read-only): their pages stay in the page cache, and a later touch maps them again
    (a minor fault).  Values are untouched (a mapping with copied-on-write or dirty pages
    is skipped).  Writable and shared mappings (a field cache's ``.npy`` maps:
    :func:`glaciar.engine.fieldcache.release`) are left alone.  0 where ``/proc/self/smaps``
    or ``madvise`` is missing (not Linux).
    """
    try:
        with open(SMAPS) as fh:
            text = fh.read()
    except OSError:
        return 0
    advice = getattr(mmap, "MADV_DONTNEED", None)
    madvise = getattr(_libc(), "madvise", None)
    if madvise is None or advice is None:
        return 0
    madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    dropped = 0
    for start, end, rss in _clean_file_mappings(text):
        if madvise(start, end - start, advice) == 0:
            dropped += rss
    return dropped


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
