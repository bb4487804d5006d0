"""Source detection with ``sep``, configured in SExtractor's vocabulary.

Thresholds are relative to a per-pixel RMS map, as SExtractor with
``WEIGHT_TYPE MAP_RMS``: a (filtered) pixel is detected when it exceeds
``DETECT_THRESH x rms`` of that pixel.  Pixels without data (masked, NaN, or
with a non-finite or non-positive RMS) are never detected; sep treats them as
zero data with infinite noise.

Known difference from SExtractor (and from a naive windowed sep): sep's
deblender assigns the faint pixels of a split region to its children at
random, from one random stream per ``sep.extract`` call, so a deblended
footprint depends on every region processed before it.  :mod:`glaciar.engine.measure`
therefore re-extracts deblended regions on their own (see its docstring).
"""
from __future__ import annotations

import dataclasses
import math
import mmap
import os
from dataclasses import dataclass, field
from importlib import resources


import numpy as np
import sep

from glaciar.engine.blocks import row_blocks

__all__ = [
    "DetectionError", "DetectionParams", "builtin_filter", "builtin_filter_names",
    "read_conv_file", "measure_background", "background_model", "extract", "sep_extract", "sanitize",
    "detection_rms",
    "CLEAN_STYLES", "THRESHOLD_RMS", "BACKENDS",
]

#: CLEAN styles (``DetectionParams.clean_style``; config ``detection.CLEAN_STYLE``), default first
CLEAN_STYLES = ("region", "sextractor", "sep", "sep-merge")
#: what DETECT_THRESH multiplies (``DetectionParams.threshold_rms``), default first
THRESHOLD_RMS = ("pixel", "filtered")
#: who segments the detection image (``DetectionParams.backend``), default first
BACKENDS = ("sep", "source-extractor")

#: sep's object flag for "deblended from a larger region" (SExtractor flag 2 is
#: BLENDED; sep's SEP_OBJ_MERGED is bit 1).
SEP_OBJ_MERGED = 1
#: noise value sep gives masked pixels (its BIG); any pixel with this RMS is never detected
_BIG = 1e30


class DetectionError(RuntimeError):
    """sep failed (e.g. deblending sub-object overflow, pixel-stack overflow)."""


# --------------------------------------------------------------------------
# Built-in filters
# --------------------------------------------------------------------------
def _filter_table() -> dict[str, tuple[str, int, float]]:
    text = resources.files("glaciar").joinpath("data/sextractor/filters.txt").read_text()
    table = {}
    for line in text.splitlines():
        line = line.split("#", 1)[0].split()
        if len(line) == 4:
            table[line[0]] = (line[1], int(line[2]), float(line[3]))
    return table


def builtin_filter_names() -> tuple[str, ...]:
    """Names accepted by :func:`builtin_filter` (SExtractor's filter names)."""
    return tuple(_filter_table())


def builtin_filter(name: str) -> np.ndarray:
    """Detection kernel from its analytic definition.

    Parameters
    ----------
    name : str
        SExtractor-style name, e.g. ``"gauss_2.0_5x5"``, ``"tophat_3.0_3x3"``,
        ``"default"``; a trailing ``.conv`` is ignored.

    Returns
    -------
    ndarray
        Kernel normalised to unit sum.  ``gauss_F_NxN``: circular Gaussian of
        FWHM F pixels integrated over each pixel (exact, via erf).
        ``tophat_D_NxN``: area fraction of each pixel inside a disk of diameter
        D pixels (101x101 sub-sampling: error < 1e-3 per pixel).  ``default``:
        the 3x3 pyramid (1 2 1) outer (1 2 1).  The normalisation is irrelevant
        to detection (sep normalises by the sum of absolute values).
    """
    key = os.path.basename(str(name))
    if key.endswith(".conv"):
        key = key[:-5]
    table = _filter_table()
    if key not in table:
        raise ValueError(f"unknown built-in filter {name!r}; expected one of "
                         f"{', '.join(table)} or a path to a .conv file")
    kind, size, par = table[key]
    c = np.arange(size) - (size - 1) / 2.0
    if kind == "pyramid":
        v = np.array([1.0, 2.0, 1.0])
        k = np.outer(v, v)
    elif kind == "gauss":
        from scipy.special import erf
        sigma = par / (2.0 * math.sqrt(2.0 * math.log(2.0)))
        edges = np.append(c - 0.5, c[-1] + 0.5) / (sigma * math.sqrt(2.0))
        p = np.diff(0.5 * erf(edges))
        k = np.outer(p, p)
    elif kind == "tophat":
        nsub = 101
        s = (np.arange(nsub) + 0.5) / nsub - 0.5
        fine = (c[:, None] + s[None, :]).ravel()
        inside = (fine[:, None] ** 2 + fine[None, :] ** 2) <= (par / 2.0) ** 2
        k = inside.reshape(size, nsub, size, nsub).mean(axis=(1, 3))
    else:  # pragma: no cover - table is ours
        raise ValueError(f"bad filter kind {kind!r} in filters.txt")
    return k / k.sum()


def read_conv_file(path) -> np.ndarray:
    """Read a SExtractor ``.conv`` filter file.

    Format: a header line ``CONV NORM`` or ``CONV NONORM``, ``#`` comments,
    then rows of numbers (all rows the same length).

    Returns
    -------
    ndarray
        The kernel as written (float64); normalisation is left to sep.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"filter file {path!r} not found")
    rows = []
    header = None
    with open(path) as fh:
        for lineno, raw in enumerate(fh, 1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            if header is None:
                words = line.upper().split()
                if words[0] != "CONV" or len(words) < 2 or words[1] not in ("NORM", "NONORM"):
                    raise ValueError(f"{path}:{lineno}: expected header 'CONV NORM' or 'CONV NONORM', got {line!r}")
                header = words[1]
                continue
            try:
                rows.append([float(v) for v in line.split()])
            except ValueError:
                raise ValueError(f"{path}:{lineno}: expected a row of numbers, got {line!r}") from None
    if header is None or not rows:
        raise ValueError(f"{path}: no 'CONV NORM/NONORM' header or no kernel rows")
    if len({len(r) for r in rows}) != 1:
        raise ValueError(f"{path}: kernel rows have different lengths {[len(r) for r in rows]}")
    k = np.array(rows, dtype=np.float64)
    if not np.all(np.isfinite(k)) or not np.any(k != 0):
        raise ValueError(f"{path}: kernel must be finite and not all zero")
    return k


# --------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------
def _default_kernel():
    return builtin_filter("gauss_2.0_5x5")


@dataclass(frozen=True)
class DetectionParams:
    """Detection and photometry settings (SExtractor names in brackets).

    Attributes
    ----------
    detect_thresh : float
        Threshold in units of the per-pixel RMS [DETECT_THRESH].
    threshold_rms : {"pixel", "filtered"}
        Which RMS DETECT_THRESH multiplies (no SExtractor key).  ``"pixel"``
        (default): each pixel's RMS (sep).  ``"filtered"``: the square root of
        the variance map filtered with the detection kernel, pixels without
        data counting as infinite variance -- what SExtractor does with a
        filter and a weight map (so it detects nothing within the filter
        half-width of a pixel without data, and smooths the threshold across
        depth steps).  The two differ only where the RMS varies; with
        ``"filtered"`` and ``clean_style="sextractor"`` glaciar's segmentation
        is SExtractor's (``tests/test_sextractor_backend.py``).
    detect_minarea : int
        Minimum number of pixels above threshold [DETECT_MINAREA].
    filter_kernel : ndarray or None
        Detection filter [FILTER_NAME]; None = no filtering [FILTER N].
        Stored as a read-only float64 array; compared by value.
    filter_type : {"conv", "matched"}
        ``conv`` is SExtractor's convolution; ``matched`` is sep's noise-aware
        matched filter.
    deblend_nthresh : int
        [DEBLEND_NTHRESH]
    deblend_mincont : float
        [DEBLEND_MINCONT]
    clean, clean_param : bool, float
        [CLEAN], [CLEAN_PARAM]
    clean_style : {"region", "sextractor", "sep", "sep-merge"}
        Which CLEAN (no SExtractor key: each program has its own).
        ``"region"`` (default): sep's CLEAN run inside each re-extracted split
        region only, so CLEAN acts between the deblended children of one
        region, never between separate regions (fast: no task-wide object
        list; not what a full-frame program does -- see
        ``benchmarks/sextractor_agreement.py`` for the measured difference).
        The three others run CLEAN on the injected image's whole pre-CLEAN
        object list (:mod:`glaciar.engine.localclean`), as a full-frame run does.
        ``"sextractor"``: SExtractor 2.x's -- objects are cleaned as they are
        extracted, an absorbed object's pixels, filtered flux and area go to
        the object that absorbs it (whose FLUX_ISO then includes them), and
        later tests use the merged flux and area (see
        :func:`glaciar.engine.clean.sextractor_clean`).  ``"sep"``: sep's --
        every pair compared after extraction, removed objects' pixels left
        unlabelled.  ``"sep-merge"``: sep's decisions with SExtractor's
        hand-over of the removed pixels.
    back_size, back_filtersize : int
        Background mesh size and median-filter size [pixels / meshes]
        [BACK_SIZE], [BACK_FILTERSIZE].
    phot_apertures : tuple of float
        Aperture *diameters* [pixels] [PHOT_APERTURES].
    phot_autoparams : (float, float)
        Kron factor k and minimum radius R_min in units of (a, b) [PHOT_AUTOPARAMS].
    initial_window : int
        Side of the first detection window around an injected source [pixels]
        (speed only: windows grow until exact).
    max_window : int
        Largest window side before giving up (FLAG_WINDOW_AT_LIMIT) [pixels].
    sub_object_limit : int
        sep's deblending sub-object limit (``sep.set_sub_object_limit``).
    backend : {"sep", "source-extractor"}
        Who segments the detection images: glaciar with sep (windowed or
        full frame, exact) or the SExtractor binary on the full injected
        image in dual-image mode (:mod:`glaciar.engine.sextractor_backend`;
        a reference, ~3x slower than the full frame); classification and
        photometry are glaciar's in both.
    filter_name : str
        Provenance of the kernel (built-in name or path).
    backphoto_type : {"global", "local"}
        [BACKPHOTO_TYPE]: ``local`` subtracts from every flux a background
        re-estimated around each object (``photometry.local_background``).
    backphoto_thick : int
        [BACKPHOTO_THICK] thickness of the local-background annulus [pixels].
    mask_type : {None, "none", "blank", "correct"}
        [MASK_TYPE] neighbours in aperture and AUTO photometry, as SExtractor
        (``photometry.masked_cutout``); None = sep's masking (apertures: no
        neighbour mask; AUTO: neighbours excluded, sum scaled by the
        total/unmasked area; pixels without data likewise).
    satur_level : float
        [SATUR_LEVEL] pixel value (background included) from which a
        detection is flagged saturated [image units, ADU for SExtractor].
    """

    detect_thresh: float = 0.7
    threshold_rms: str = "pixel"
    detect_minarea: int = 9
    filter_kernel: np.ndarray | None = field(default_factory=_default_kernel)
    filter_type: str = "conv"
    deblend_nthresh: int = 32
    deblend_mincont: float = 0.005
    clean: bool = True
    clean_param: float = 1.0
    clean_style: str = "region"
    back_size: int = 64
    back_filtersize: int = 3
    phot_apertures: tuple = (4.0, 8.0)
    phot_autoparams: tuple = (2.5, 3.5)
    initial_window: int = 41
    max_window: int = 1025
    sub_object_limit: int = 1024
    backend: str = "sep"
    filter_name: str = "gauss_2.0_5x5"
    backphoto_type: str = "global"
    backphoto_thick: int = 24
    mask_type: str | None = None
    satur_level: float = 50000.0

    def __post_init__(self):
        def bad(name, expected, value):
            raise ValueError(f"detection parameter {name}: expected {expected}, got {value!r}")

        num = (int, float, np.integer, np.floating)
        if not isinstance(self.detect_thresh, num) or isinstance(self.detect_thresh, bool) \
                or not (math.isfinite(self.detect_thresh) and self.detect_thresh > 0):
            bad("detect_thresh", "a positive number", self.detect_thresh)
        for name, lo in (("detect_minarea", 1), ("deblend_nthresh", 1), ("back_size", 1),
                         ("back_filtersize", 1), ("initial_window", 3), ("max_window", 3),
                         ("sub_object_limit", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                bad(name, f"an integer >= {lo}", v)
        if self.max_window < self.initial_window:
            bad("max_window", f">= initial_window ({self.initial_window})", self.max_window)
        if not isinstance(self.deblend_mincont, num) or not (0.0 <= self.deblend_mincont <= 1.0):
            bad("deblend_mincont", "a number in [0, 1]", self.deblend_mincont)
        if not isinstance(self.clean, (bool, np.bool_)):
            bad("clean", "true or false", self.clean)
        if self.clean_style not in CLEAN_STYLES:
            bad("clean_style", "one of " + ", ".join(repr(v) for v in CLEAN_STYLES), self.clean_style)
        if not isinstance(self.clean_param, num) or not self.clean_param > 0:
            bad("clean_param", "a positive number", self.clean_param)
        if self.backphoto_type not in ("global", "local"):
            bad("backphoto_type", "'global' or 'local'", self.backphoto_type)
        if isinstance(self.backphoto_thick, bool) or not isinstance(self.backphoto_thick, (int, np.integer)) \
                or self.backphoto_thick < 1:
            bad("backphoto_thick", "an integer >= 1", self.backphoto_thick)
        if self.mask_type not in (None, "none", "blank", "correct"):
            bad("mask_type", "None, 'none', 'blank' or 'correct'", self.mask_type)
        if not isinstance(self.satur_level, num) or isinstance(self.satur_level, bool) \
                or not self.satur_level > 0:
            bad("satur_level", "a positive number", self.satur_level)
        if self.backend not in BACKENDS:
            bad("backend", "one of " + ", ".join(repr(v) for v in BACKENDS), self.backend)
        if self.threshold_rms not in THRESHOLD_RMS:
            bad("threshold_rms", "one of " + ", ".join(repr(v) for v in THRESHOLD_RMS), self.threshold_rms)
        if self.filter_type not in ("conv", "matched"):
            bad("filter_type", "'conv' or 'matched'", self.filter_type)
        if self.filter_kernel is not None:
            k = np.array(self.filter_kernel, dtype=np.float64)
            if k.ndim != 2 or k.size == 0 or not np.all(np.isfinite(k)) or not np.any(k != 0):
                bad("filter_kernel", "a finite, non-zero 2-d array", self.filter_kernel)
            k.setflags(write=False)
            object.__setattr__(self, "filter_kernel", k)
        try:
            ap = tuple(float(a) for a in np.atleast_1d(self.phot_apertures))
        except (TypeError, ValueError):
            bad("phot_apertures", "a list of positive diameters [pixels]", self.phot_apertures)
        if not ap or not all(math.isfinite(a) and a > 0 for a in ap):
            bad("phot_apertures", "a non-empty list of positive diameters [pixels]", self.phot_apertures)
        object.__setattr__(self, "phot_apertures", ap)
        try:
            au = tuple(float(a) for a in self.phot_autoparams)
        except (TypeError, ValueError):
            bad("phot_autoparams", "two positive numbers (k, R_min)", self.phot_autoparams)
        if len(au) != 2 or not all(math.isfinite(a) and a > 0 for a in au):
            bad("phot_autoparams", "two positive numbers (k, R_min)", self.phot_autoparams)
        object.__setattr__(self, "phot_autoparams", au)

    def __eq__(self, other):
        if not isinstance(other, DetectionParams):
            return NotImplemented
        for f in dataclasses.fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if f.name == "filter_kernel":
                if (a is None) != (b is None) or (a is not None and not np.array_equal(a, b)):
                    return False
            elif a != b:
                return False
        return True

    def __hash__(self):
        k = None if self.filter_kernel is None else (self.filter_kernel.shape, self.filter_kernel.tobytes())
        return hash((k,) + tuple(getattr(self, f.name) for f in dataclasses.fields(self)
                                 if f.name != "filter_kernel"))

    @property
    def filter_halfwidth(self) -> int:
        """Largest half-size of the filter kernel [pixels] (0 without filtering)."""
        if self.filter_kernel is None:
            return 0
        return int(max(self.filter_kernel.shape) // 2)


# --------------------------------------------------------------------------
# Background and extraction
# --------------------------------------------------------------------------
#: Pixels per block of :func:`sanitize`'s work on a large image.
SANITIZE_BLOCK_PIXELS = 1 << 22


def _whole_map(a):
    """The ``mmap`` under ``a`` when ``a`` is a whole memory-mapped image (a field's spilled
    array during its set-up), else None (an in-memory array, or a window of a map: a
    task's, whose map's pages are the worker's field cache)."""
    src, m = a, None
    while src is not None and m is None:
        m = getattr(src, "_mmap", None)
        src = getattr(src, "base", None)
    if m is None:
        return None
    try:
        return m if np.asarray(a).nbytes >= len(m) // 2 else None
    except (TypeError, ValueError):         # a closed map
        return None


def release_mapped(*arrays) -> None:
    """Drop this process's resident pages of whole memory-mapped images (they stay in the
    page cache): for a step that reads through a spilled image once, so that its pages
    do not pile up in the process as it goes. Anything else is left alone."""
    advice = getattr(mmap, "MADV_DONTNEED", None)
    for a in arrays:
        m = _whole_map(a)
        if m is not None and advice is not None:
            try:
                m.madvise(advice)
            except (OSError, ValueError):     # a closed map: nothing resident
                pass


def _float32_copy(a, blocks) -> np.ndarray:
    """``np.array(a, dtype=np.float32, order="C")``; when ``a`` is a whole memory-mapped
    image, block by block with its resident pages dropped as they are copied, so the
    copy does not hold the mapped image in this process as well."""
    src = np.asarray(a)
    if _whole_map(a) is None:
        return np.array(src, dtype=np.float32, order="C")
    out = np.empty(src.shape, dtype=np.float32)
    for rows in blocks:
        out[rows] = src[rows]
        release_mapped(a)
    return out


def _blocks(shape):
    """Slices of the first axis covering about :data:`SANITIZE_BLOCK_PIXELS` pixels each."""
    if len(shape) < 2:
        return [slice(None)]
    return [slice(y0, y1) for y0, y1, _, _ in row_blocks(shape, SANITIZE_BLOCK_PIXELS)]


def sanitize(image, err=None, mask=None):
    """Native float32 copies for sep and the combined no-data mask.

    Returns ``(data, err, nodata)``: NaN/inf data -> 0; pixels without data
    (``mask`` True, data non-finite, err non-finite or <= 0) are flagged in
    ``nodata``; their err is set to 1 (they are passed to sep as masked).
    Made by blocks of rows: no full-frame temporaries beyond the three results.
    """
    blocks = _blocks(np.shape(image))
    data = _float32_copy(image, blocks)
    m = None
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != data.shape:
            raise ValueError(f"mask shape {m.shape} differs from image shape {data.shape}")
    e = None
    if err is not None:
        e = _float32_copy(err, blocks)
        if e.shape != data.shape:
            raise ValueError(f"RMS map shape {e.shape} differs from image shape {data.shape}")
    nodata = np.empty(data.shape, dtype=bool)
    for rows in blocks:
        nd = ~np.isfinite(data[rows])
        if m is not None:
            nd |= np.asarray(m[rows], dtype=bool)
        if e is not None:
            with np.errstate(invalid="ignore"):
                nd |= ~(np.isfinite(e[rows]) & (e[rows] > 0))
            e[rows][nd] = 1.0
        data[rows][nd] = 0.0
        nodata[rows] = nd
        if m is not None:
            release_mapped(mask)        # a spilled mask's pages, read once
    return data, e, nodata


def detection_rms(err, nodata, params: DetectionParams, outside=None):
    """The RMS map the detection threshold multiplies (``params.threshold_rms``).

    Parameters
    ----------
    err : ndarray of float32
        Per-pixel RMS as passed to sep [image units].
    nodata : ndarray of bool
        Pixels without data.
    params : DetectionParams
    outside : ndarray of bool, optional
        Pixels that are not part of the image at all (the blank gaps between
        the windows of a canvas): they count as zero variance, like pixels
        beyond the image edge, not as missing data.

    Returns
    -------
    ndarray of float32
        ``err`` itself for ``"pixel"`` (or without a filter); for
        ``"filtered"``, ``sqrt(filter(err^2))`` with the detection kernel
        (normalised by the sum of its absolute values, as the image), pixels
        without data entering with a variance of 1e30.
    """
    if params.threshold_rms == "pixel" or params.filter_kernel is None:
        return err
    from glaciar.engine.sepscan import sep_filter

    var = np.square(np.asarray(err, dtype=np.float32)).astype(np.float32)
    var[np.asarray(nodata, dtype=bool)] = np.float32(1e30)
    if outside is not None:
        var[np.asarray(outside, dtype=bool)] = 0.0
    out = np.sqrt(np.maximum(sep_filter(var, params.filter_kernel), 0.0)).astype(np.float32)
    out[~(out > 0)] = np.float32(1.0)       # only where every neighbour is outside the image
    return out


def measure_background(image, mask, params: DetectionParams):
    """Background and RMS maps of an original band image (once per field and band).

    Parameters
    ----------
    image : ndarray
        Science image [image units]; any dtype or byte order.
    mask : ndarray of bool or None
        True where there are no data; non-finite pixels are masked too.
    params : DetectionParams
        Uses ``back_size`` and ``back_filtersize``.

    Returns
    -------
    background, rms : ndarray (float32)
        Per-pixel background level and RMS [image units] (sep.Background, i.e.
        SExtractor's mesh-mode / sigma-clipped background).
    """
    data, _, nodata = sanitize(image, None, mask)
    bkg = background_model(data, nodata, params)
    try:
        return bkg.back(dtype=np.float32), bkg.rms(dtype=np.float32)
    except Exception as exc:  # sep raises plain Exception subclasses
        raise DetectionError(f"sep background estimation failed: {exc}") from exc


def background_model(data, nodata, params: DetectionParams):
    """sep's background model (``sep.Background``) of a sanitized image.

    For a caller that needs only some of :func:`measure_background`'s full-frame maps:
    the model holds the meshes only; ``.back()`` / ``.rms()`` make the maps and
    ``.subfrom(data)`` subtracts the background in place (the same float32
    differences as ``data - .back()``, without that map).

    Parameters
    ----------
    data : ndarray of float32
        Native, C-contiguous image, 0 where ``nodata`` (:func:`sanitize`'s ``data``).
    nodata : ndarray of bool
        Pixels without data.
    params : DetectionParams
        Uses ``back_size`` and ``back_filtersize``.
    """
    # A mesh larger than the image is one mesh of the whole image, which sep computes the
    # same when the mesh is cut to the image; uncut, sep allocates a buffer of BACK_SIZE^2
    # pixels first (BACK_SIZE: 1e9 -> MemoryError with no message).
    bh, bw = (min(int(params.back_size), int(n)) for n in data.shape)
    try:
        return sep.Background(data, mask=nodata, bw=bw, bh=bh,
                              fw=params.back_filtersize, fh=params.back_filtersize)
    except Exception as exc:  # sep raises plain Exception subclasses
        raise DetectionError(f"sep background estimation failed: {exc}") from exc


#: First size of sep's pixel stack [pixels] (see :func:`sep_extract`): images up to
#: ~2000^2 get their whole area at once, as before; larger ones a stack this big first.
PIXSTACK_START = 1 << 22


def sep_extract(data, err, nodata, params: DetectionParams, clean: bool):
    """sep.extract on sanitized float32 arrays, with limits raised and errors wrapped.

    The one place the engine calls ``sep.extract`` (every backend path, full frame or
    windowed, goes through it so that sep's buffer limits are set the same way).

    Parameters
    ----------
    data : ndarray of float32
        Sanitized image (:func:`sanitize`; no-data pixels 0) [image units].
    err : ndarray of float32
        RMS the threshold scales (:func:`detection_rms`) [image units].
    nodata : ndarray of bool
        Pixels sep masks.
    params : DetectionParams
    clean : bool
        Run sep's CLEAN (``params.clean`` is not read here: callers emulate it).

    Returns
    -------
    catalog : structured ndarray
        sep's objects; row i has segment id i + 1.
    segmap : ndarray of int32

    Raises
    ------
    DetectionError
        When sep fails (after one retry with the whole image as pixel stack).
    """
    # The pixel stack must hold every pixel of the open objects; it cannot exceed
    # the image area.  sep initialises the whole stack on every call, so a stack
    # much larger than the image costs time, and on a large mosaic memory (~26 bytes
    # per stack pixel): it starts at PIXSTACK_START pixels and only a full stack
    # (sep's error, nothing returned) retries with the image area.  The stack is a
    # buffer: the result does not depend on its size.
    full = int(max(data.size + 1024, 4096))
    for stack in dict.fromkeys((min(full, PIXSTACK_START), full)):
        sep.set_extract_pixstack(stack)
        sep.set_sub_object_limit(int(params.sub_object_limit))
        try:
            cat, seg = sep.extract(
                data, float(params.detect_thresh), err=err, mask=nodata,
                minarea=int(params.detect_minarea),
                filter_kernel=params.filter_kernel, filter_type=params.filter_type,
                deblend_nthresh=int(params.deblend_nthresh), deblend_cont=float(params.deblend_mincont),
                clean=bool(clean), clean_param=float(params.clean_param), segmentation_map=True)
        except Exception as exc:
            if stack < full and "pixel buffer full" in str(exc):
                continue
            raise DetectionError(f"sep extraction failed: {exc}") from exc
        return cat, seg.astype(np.int32, copy=False)


def extract(image_sub, err, params: DetectionParams, mask=None):
    """Full-frame detection (single-image mode).

    Parameters
    ----------
    image_sub : ndarray
        Background-subtracted detection image [image units].
    err : ndarray
        Per-pixel RMS [image units]; threshold = ``detect_thresh * err``.
    params : DetectionParams
    mask : ndarray of bool, optional
        True where there are no data.  Such pixels, and pixels with
        non-finite data or non-finite/non-positive err, are never detected.

    Returns
    -------
    catalog : structured ndarray
        sep's object catalogue (x, y 0-based; a, b, theta; cflux, flux;
        npix; xmin..ymax; flag; ...).  Row i has segment id i + 1.
    segmap : ndarray of int32
        Segmentation map (0 = no object).

    Raises
    ------
    DetectionError
        When sep fails (e.g. deblending overflow).
    """
    data, e, nodata = sanitize(image_sub, err, mask)
    return sep_extract(data, detection_rms(e, nodata, params), nodata, params, params.clean)
