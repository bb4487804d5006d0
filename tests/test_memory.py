"""glaciar.memory: what a finished run lets go before its summaries (release_memory), and the
clean file pages a hand-over drops (drop_file_pages)."""
from __future__ import annotations

import ctypes
import gc
import mmap
import os
import sys

import numpy as np
import pytest

from glaciar.engine.shotnoise import noisy_pixels, wings_cache_info
from glaciar.fieldprep import shared_template_cache
from glaciar.galaxy.psf import gaussian_psf
from glaciar.memory import drop_file_pages, release_memory


def test_release_drops_the_shared_templates_and_their_splits():
    psfs = {"a": gaussian_psf(0.15, 0.08)}
    # Other tests in this process may have filled the shared cache: start without it.
    release_memory()
    gc.collect()
    n0, b0 = wings_cache_info()
    cache = shared_template_cache(psfs, 0.995)
    assert shared_template_cache(psfs, 0.995) is cache          # kept between fields
    rng = np.random.default_rng(3)
    for k in range(4):
        noisy_pixels(cache.stamp("a", 1.0, 0.7, 30.0, 1.2, 10.0 + k / 8, 5.0).data, 300.0, 2.0, rng)
    assert wings_cache_info()[0] == n0 + 4
    del cache
    release_memory()
    assert wings_cache_info() == (n0, b0)                         # the splits left with them
    fresh = shared_template_cache(psfs, 0.995)
    assert fresh.stats.entries == 0 and fresh.stats.convolutions == 0


# --------------------------------------------------------------------------
# drop_file_pages: clean read-only file pages go, values stay
# --------------------------------------------------------------------------
linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/smaps")


def _resident_kb(path) -> int:
    """Resident kB of this process's mappings of ``path`` (read from /proc/self/smaps here,
    independently of glaciar.memory)."""
    total, ours = 0, False
    with open("/proc/self/smaps") as fh:
        for line in fh:
            head = line.split()
            if "-" in head[0] and len(head) >= 5 and ":" not in head[0]:
                ours = len(head) >= 6 and head[5] == str(path)
            elif ours and head[0] == "Rss:":
                total += int(head[1])
    return total


def _file(tmp_path, pages=64):
    data = np.arange(pages * mmap.PAGESIZE // 8, dtype=np.int64).tobytes()
    path = tmp_path / "pages.bin"
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())       # page-cache pages not yet written count as dirty
    return path, data


@linux_only
def test_drop_file_pages_drops_a_clean_read_only_private_map_and_keeps_its_values(tmp_path):
    path, data = _file(tmp_path)
    with open(path, "rb") as fh:
        m = mmap.mmap(fh.fileno(), 0, flags=mmap.MAP_PRIVATE, prot=mmap.PROT_READ)
    assert m[:] == data                                   # every page touched
    assert _resident_kb(path) >= len(data) // 1024
    assert drop_file_pages() >= len(data)
    assert _resident_kb(path) == 0
    assert m[:] == data                                   # read again from the file
    m.close()


@linux_only
def test_drop_file_pages_keeps_copied_on_write_pages_of_a_read_only_map(tmp_path):
    # A relocated library segment (RELRO): private, written once, then made read-only.
    # Dropping its pages would bring the file's bytes back in place of the written ones.
    path, data = _file(tmp_path)
    with open(path, "rb") as fh:
        m = mmap.mmap(fh.fileno(), 0, flags=mmap.MAP_PRIVATE,
                      prot=mmap.PROT_READ | mmap.PROT_WRITE)
    m[:8] = b"written!"
    view = ctypes.c_char.from_buffer(m)
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    assert libc.mprotect(ctypes.addressof(view), len(m), mmap.PROT_READ) == 0
    del view
    drop_file_pages()
    assert m[:8] == b"written!" and m[8:] == data[8:]
