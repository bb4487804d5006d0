"""Survey access: fields x bands of FITS images, read lazily and cached per process.

A :class:`Survey` knows where each field's science and noise (weight or RMS)
image is, converts weight maps to RMS, gives the footprint (where the
detection band has valid data) and the pixel scale (from the config or the
detection image's WCS).

Arrays are read on first use (by blocks of rows through astropy's ``section``,
straight into one native array) and kept in a module-level, byte-bounded LRU
cache, so each worker process reads each image once and a pickled ``Survey``
stays small. Validity maps and the footprint are made block by block from the
files without caching the images they read; ``science(..., cache=False)`` and
``rms(..., cache=False)`` give a caller new, writable arrays of its own (the
field set-up). FITS data are big-endian on disk; every array returned here is
native-endian (float32 for 32-bit or smaller data, float64 otherwise), as
``sep`` and numpy kernels require.

The cached arrays are shared by every caller in the process, so they are
returned **read-only**: an in-place injection would otherwise corrupt every
later task. ``sep`` refuses read-only buffers, so pass it a copy (an injected
window ``science[win] + stamps`` already is one; ``rms[win].copy()``).
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from .config import BandConfig, Config
from .engine.blocks import row_blocks

__all__ = ["Survey", "clear_cache", "set_cache_limit", "selection_bands"]

# ---------------------------------------------------------------------------
# Per-process array cache
# ---------------------------------------------------------------------------
_CACHE: "OrderedDict[tuple, np.ndarray]" = OrderedDict()
_CACHE_LOCK = threading.Lock()
_CACHE_LIMIT = [2 * 1024 ** 3]     # bytes; an entry larger than this is still kept alone


def set_cache_limit(nbytes: int) -> None:
    """Set the per-process image cache budget [bytes] (default 2 GiB)."""
    if nbytes < 0:
        raise ValueError(f"cache limit must be >= 0 bytes, got {nbytes}")
    _CACHE_LIMIT[0] = int(nbytes)
    _evict()


def clear_cache() -> None:
    """Drop every cached image array of this process."""
    with _CACHE_LOCK:
        _CACHE.clear()


def _evict() -> None:
    with _CACHE_LOCK:
        total = sum(a.nbytes for a in _CACHE.values())
        while len(_CACHE) > 1 and total > _CACHE_LIMIT[0]:
            _, old = _CACHE.popitem(last=False)
            total -= old.nbytes


def _file_key(path: Path) -> tuple:
    # Size and mtime in the key: a rewritten file is never served from a stale cache.
    st = path.stat()
    return (str(path), st.st_mtime_ns, st.st_size)


def _file_key_or_none(path: Path) -> tuple:
    try:
        return _file_key(path)
    except OSError:          # a missing file has nothing cached
        return (str(path), None, None)


def _cached(key: tuple, build):
    with _CACHE_LOCK:
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return _CACHE[key]
    arr = build()
    arr.flags.writeable = False   # shared by every caller: inject into copies
    with _CACHE_LOCK:
        _CACHE[key] = arr
    _evict()
    return arr


# ---------------------------------------------------------------------------
# FITS helpers
# ---------------------------------------------------------------------------
def _image_hdu_index(hdul, path: Path) -> tuple[int, tuple[int, int]]:
    """Index and (ny, nx) of the first HDU holding a 2-D image (extra axes of length 1 ok)."""
    for i, hdu in enumerate(hdul):
        if not getattr(hdu, "is_image", False):
            continue
        h = hdu.header
        naxis = int(h.get("NAXIS", 0))
        dims = [int(h.get(f"NAXIS{k}", 0)) for k in range(1, naxis + 1)]
        if naxis < 2 or any(d == 0 for d in dims):
            continue
        if any(d != 1 for d in dims[2:]):
            raise ValueError(f"{path}: HDU {i} is a {naxis}-D image of shape "
                             f"{tuple(reversed(dims))}; expected a 2-D image")
        return i, (dims[1], dims[0])
    raise ValueError(f"{path}: no 2-D image found in any HDU")


def _native_float_dtype(dtype: np.dtype) -> np.dtype:
    if (dtype.kind == "f" and dtype.itemsize <= 4) or (dtype.kind in "iub" and dtype.itemsize <= 2):
        return np.dtype(np.float32)
    return np.dtype(np.float64)


def read_array(path: Path) -> np.ndarray:
    """The image of a FITS file, native-endian float (float32 for 32-bit or smaller data,
    float64 otherwise), read by blocks of rows into one new array (no other whole-image copy)."""
    arr = None
    for y0, y1, block in _row_blocks(path):
        if arr is None:
            arr = np.empty((_read_header(path)[1][0], block.shape[1]), dtype=block.dtype)
        arr[y0:y1] = block
    return arr


#: Pixels per block of :func:`_row_blocks` (16 MB of float32).
ROW_BLOCK_PIXELS = 1 << 22


def _row_blocks(path: Path):
    """``(y0, y1, block)``: the image of a FITS file by blocks of rows, native-endian float
    (the dtype of :func:`read_array`).

    For whole-image quantities made pixel by pixel (validity maps, RMS from weights):
    only one block of the image is in memory at a time.  Read through astropy's
    ``section`` (plain reads of those rows), not a memory map, whose pages would stay
    resident in this process until the file is closed (the whole image by then).
    """
    from astropy.io import fits

    with fits.open(path, memmap=False, lazy_load_hdus=True) as hdul:
        idx, (ny, nx) = _image_hdu_index(hdul, path)
        hdu = hdul[idx]
        lead = (0,) * (len(hdu.shape) - 2)          # axes of length 1 before (y, x)
        # A compressed file (.fits.gz) is decompressed once, whole: a section of it would
        # decompress again from the start of the file for every block.
        compressed = getattr(getattr(hdul, "_file", None), "compression", None) or \
            Path(path).suffix.lower() in (".gz", ".bz2", ".zip")
        source = hdu.data if compressed else hdu.section
        for y0, y1, _, _ in row_blocks((ny, nx), ROW_BLOCK_PIXELS):
            block = np.asarray(source[lead + (slice(y0, y1), slice(None))])
            yield y0, y1, np.array(block.reshape(y1 - y0, nx),
                                   dtype=_native_float_dtype(block.dtype), order="C")


def _noise_to_rms(a: np.ndarray, noise_type: str) -> np.ndarray:
    """Per-pixel RMS from a block of a noise map (``a`` itself, changed, for an RMS map).

    Weights (inverse variance) give ``1/sqrt(weight)``; pixels without a valid noise
    (weight or RMS <= 0 or non-finite) get inf, i.e. zero weight.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        good = np.isfinite(a) & (a > 0)
        if noise_type == "weight":
            out = np.full(a.shape, np.inf, dtype=a.dtype)
            out[good] = 1.0 / np.sqrt(a[good])
            # A huge weight can underflow to RMS 0 in float32: keep it positive.
            out[good & (out <= 0)] = np.finfo(a.dtype).tiny
            return out
        a[~good] = np.inf
        return a


#: Most pixels :func:`strided_sample` returns: enough for a robust scatter to ~0.1 %.
SAMPLE_PIXELS = 1 << 20


def strided_sample(path: Path, max_pixels: int = SAMPLE_PIXELS) -> np.ndarray:
    """Every k-th row and column of a FITS image (k the smallest that keeps <= ``max_pixels``).

    Read by blocks of rows (:func:`_row_blocks`): memory is one block plus the
    sample, whatever the image's size. Images of one field share their shape, so
    samples of a science image and its noise map are the same pixels.

    Returns
    -------
    ndarray, 2-D
        The sampled pixels, native-endian float.
    """
    import math

    parts, step = [], None
    for y0, y1, block in _row_blocks(path):
        if step is None:
            ny = _read_header(path)[1][0]
            step = max(1, math.ceil(math.sqrt(ny * block.shape[1] / max(int(max_pixels), 1))))
        first = (-y0) % step                      # rows y0 + first, ... are multiples of step
        parts.append(np.array(block[first::step, ::step]))
    return np.concatenate(parts) if parts else np.zeros((0, 0))


def _read_header(path: Path):
    from astropy.io import fits

    with fits.open(path, memmap=True) as hdul:
        idx, shape = _image_hdu_index(hdul, path)
        return hdul[idx].header.copy(), shape


def _gz_alternative(path: Path) -> Path:
    """``path``, or the same name with ``.gz`` added or removed when only that exists."""
    if path.exists():
        return path
    alt = path.with_name(path.name[:-3]) if path.name.endswith(".gz") else \
        path.with_name(path.name + ".gz")
    return alt if alt.exists() else path


def selection_bands(cfg: Config) -> tuple[str, ...]:
    """Bands whose columns the configuration's selection reads, in config order."""
    from .config.user_selection import SelectionFunctionConfig
    from .engine.selection import compile_selection

    if not cfg.selection:
        return ()
    if isinstance(cfg.selection, SelectionFunctionConfig):      # given every band's columns
        return tuple(b.name for b in cfg.survey.bands)
    columns = compile_selection(cfg.selection).columns
    return tuple(b.name for b in cfg.survey.bands
                 if any(c.endswith("_" + b.name.lower()) for c in columns))


def _region_mask(path: Path, shape: tuple[int, int], header) -> np.ndarray:
    """Pixels (centres) inside any region of a DS9 file; sky regions through ``header``'s WCS."""
    import warnings

    from astropy.wcs import WCS, FITSFixedWarning
    from regions import PixelRegion, Regions

    try:
        regs = Regions.read(str(path), format="ds9")
    except Exception as exc:  # the regions parser raises several types
        raise ValueError(f"{path}: not a readable DS9 region file ({exc}) (survey.mask)") from None
    wcs = None
    out = np.zeros(shape, dtype=bool)
    for k, reg in enumerate(regs):
        if not isinstance(reg, PixelRegion):
            if wcs is None:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", FITSFixedWarning)
                    wcs = WCS(header, naxis=2)
                if not wcs.has_celestial:
                    raise ValueError(f"{path}: region {k + 1} is in sky coordinates but the "
                                     "detection image has no celestial WCS (survey.mask)")
            reg = reg.to_pixel(wcs)
        m = reg.to_mask(mode="center")
        img = m.to_image(shape)
        if img is not None:
            out |= img.astype(bool)
    return out


class Survey:
    """Fields and bands of a survey, with lazy, cached image access.

    Build with :meth:`from_config`. All methods take a field name and (where
    relevant) a band name from the config.

    Attributes
    ----------
    config : Config
    fields : tuple of str
    bands : tuple of str
        Band names in config order (the detection band included).
    detection_band : str
    """

    def __init__(self, config: Config):
        self.config = config
        s = config.survey
        self.fields = tuple(s.fields)
        self.bands = tuple(b.name for b in s.bands)
        self.detection_band = s.detection_band
        self._headers: dict[tuple[str, str, str], tuple] = {}
        self._shapes: dict[str, tuple[int, int]] = {}
        self._scales: dict[str, float] = {}

    @classmethod
    def from_config(cls, cfg: Config) -> "Survey":
        """The survey described by ``cfg.survey``."""
        return cls(cfg)

    def __getstate__(self):
        # Headers are re-read lazily in the receiving process.
        state = self.__dict__.copy()
        state["_headers"] = {}
        return state

    def __repr__(self) -> str:
        return (f"Survey(fields={list(self.fields)}, bands={list(self.bands)}, "
                f"detection_band={self.detection_band!r})")

    # --- paths and band settings ------------------------------------------
    def _check(self, field: str, band: str | None = None) -> None:
        if field not in self.fields:
            raise KeyError(f"unknown field {field!r}; fields are {list(self.fields)}")
        if band is not None and band not in self.bands:
            raise KeyError(f"unknown band {band!r}; bands are {list(self.bands)}")

    def band(self, band: str) -> BandConfig:
        """The :class:`~glaciar.config.BandConfig` of ``band`` (zeropoint, gain, PSF, filter)."""
        self._check(self.fields[0], band)
        return self.config.survey.band(band)

    def science_path(self, field: str, band: str) -> Path:
        """Absolute path of the science image of ``field`` in ``band``.

        When the templated file does not exist but the same name with ``.gz``
        added or removed does, that one (mixed ``.fits`` / ``.fits.gz`` layouts).
        """
        self._check(field, band)
        s = self.config.survey
        return _gz_alternative(s.image_dir / s.science.format(field=field, band=band))

    def noise_path(self, field: str, band: str) -> Path | None:
        """Absolute path of the weight or RMS map, or None if the config has none."""
        self._check(field, band)
        s = self.config.survey
        if s.noise is None:
            return None
        return _gz_alternative(s.image_dir / s.noise.format(field=field, band=band))

    def _existing(self, path: Path, key: str, field: str, band: str) -> Path:
        if not path.is_file():
            raise FileNotFoundError(f"{key} (field {field!r}, band {band!r}): file not found: "
                                    f"{path}")
        return path

    # --- headers and shapes ------------------------------------------------
    def _header_and_shape(self, field: str, band: str, kind: str):
        k = (field, band, kind)
        if k not in self._headers:
            if kind == "science":
                path = self._existing(self.science_path(field, band), "survey.science",
                                      field, band)
            else:
                path = self._existing(self.noise_path(field, band), "survey.noise", field, band)
            self._headers[k] = _read_header(path)
        return self._headers[k]

    def header(self, field: str, band: str):
        """FITS header (astropy ``Header``, a copy) of the science image."""
        self._check(field, band)
        return self._header_and_shape(field, band, "science")[0].copy()

    def shape(self, field: str) -> tuple[int, int]:
        """(ny, nx) shared by every science and noise image of ``field``.

        Raises
        ------
        ValueError
            If the images of the field differ in shape (the files are named).
        """
        self._check(field)
        if field not in self._shapes:
            shapes = {}
            for b in self.bands:
                shapes[self.science_path(field, b)] = self._header_and_shape(field, b,
                                                                             "science")[1]
                if self.config.survey.noise is not None:
                    shapes[self.noise_path(field, b)] = self._header_and_shape(field, b,
                                                                               "noise")[1]
            distinct = set(shapes.values())
            if len(distinct) > 1:
                listing = "; ".join(f"{p.name}: {s[0]}x{s[1]}" for p, s in shapes.items())
                raise ValueError(f"field {field!r}: images differ in shape (ny x nx): {listing}")
            self._shapes[field] = distinct.pop()
        return self._shapes[field]

    # --- pixel data -------------------------------------------------------
    def science(self, field: str, band: str, cache: bool = True) -> np.ndarray:
        """Science image [image units], native-endian float, read-only (cached).

        ``cache=False``: a new, writable array read from the file, not kept (nor
        taken from the cache): for a caller that makes its own array from it.

        Returns
        -------
        numpy.ndarray, shape (ny, nx)
            float32 for 32-bit or smaller FITS data, float64 otherwise.
        """
        self.shape(field)
        path = self.science_path(field, band)
        if not cache:
            return read_array(path)
        return _cached(("science",) + _file_key(path), lambda: read_array(path))

    def release_pixels(self, field: str, bands=None) -> None:
        """Drop this process's cached science and noise arrays of ``field`` (masks stay).

        For a caller that has made its own arrays from them (the field context
        holds background-subtracted copies): the cached ones would double the
        memory of every task that follows. A later call reads the file again.
        ``bands``: only these (default: every band).
        """
        keys = set()
        for b in (self.bands if bands is None else bands):
            keys.add(("science",) + _file_key_or_none(self.science_path(field, b)))
            noise = self.noise_path(field, b)
            if noise is not None:
                keys.add(("rms", self.config.survey.noise_type) + _file_key_or_none(noise))
        with _CACHE_LOCK:
            for k in keys:
                _CACHE.pop(k, None)

    def rms(self, field: str, band: str, cache: bool = True) -> np.ndarray | None:
        """Per-pixel noise RMS [image units], read-only (cached); None without a noise map.

        For ``noise_type: weight`` (inverse variance) the RMS is 1/sqrt(weight).
        Pixels with no valid noise (weight <= 0 or non-finite; RMS <= 0 or
        non-finite) get RMS = inf, i.e. zero weight. Made from the file by blocks of
        rows (no whole-image temporaries). ``cache=False``: a new, writable array,
        not kept (nor taken from the cache).
        """
        shape = self.shape(field)
        path = self.noise_path(field, band)
        if path is None:
            return None
        ntype = self.config.survey.noise_type

        def build():
            out = None
            for y0, y1, a in self._noise_blocks(field, band):
                r = _noise_to_rms(a, ntype)
                if out is None:
                    out = np.empty(shape, dtype=r.dtype)
                out[y0:y1] = r
            return out

        if not cache:
            return build()
        return _cached(("rms", ntype) + _file_key(path), build)

    def _noise_blocks(self, field: str, band: str):
        """The noise map of ``field`` in ``band`` by blocks of rows (:func:`_row_blocks`);
        with ``negative_weights: error``, raises after the last block if any weight is < 0."""
        path = self.noise_path(field, band)
        check = self.config.survey.noise_type == "weight" and \
            self.config.survey.negative_weights == "error"
        n_neg = 0
        for y0, y1, a in _row_blocks(path):
            if check:
                n_neg += int(np.count_nonzero(a < 0))
            yield y0, y1, a
        if n_neg:
            raise ValueError(f"{path}: {n_neg} negative weight pixel(s) (survey.noise, "
                             f"field {field!r}, band {band!r}); fix the map or set "
                             "survey.negative_weights: mask to mask them")

    def coverage_bands(self) -> tuple[str, ...]:
        """Bands whose data define the footprint (``survey.coverage``), detection band first.

        ``selection_bands``: the detection band and every band the selection
        reads; ``all_bands``: every band; ``detection_band``: that band only.
        """
        s = self.config.survey
        det = self.detection_band
        if s.coverage == "detection_band":
            return (det,)
        if s.coverage == "all_bands":
            return (det,) + tuple(b for b in self.bands if b != det)
        return (det,) + tuple(b for b in selection_bands(self.config) if b != det)

    def band_valid(self, field: str, band: str) -> np.ndarray:
        """Where ``band`` has data: finite, non-zero science and (with a noise map) finite RMS.

        Drizzled mosaics mark uncovered pixels with 0 science and 0 weight.
        """
        sci_path = self._existing(self.science_path(field, band), "survey.science", field, band)
        noise_path = self.noise_path(field, band)
        key = ("valid", self.config.survey.noise_type, self.config.survey.negative_weights) + \
            _file_key(sci_path)
        if noise_path is not None:
            key += _file_key(self._existing(noise_path, "survey.noise", field, band))

        def build():
            ok = np.empty(self.shape(field), dtype=bool)
            for y0, y1, v in self._valid_blocks(field, band):
                ok[y0:y1] = v
            return ok

        return _cached(key, build)

    def _valid_blocks(self, field: str, band: str):
        """:meth:`band_valid` by blocks of rows read from the files: ``(y0, y1, valid)``.

        The science image and the RMS are never whole in memory (nor cached): the
        footprint of a large mosaic costs its own bool map, not the bands' images.
        """
        self.shape(field)
        sci_path = self._existing(self.science_path(field, band), "survey.science", field, band)
        noise_path = self.noise_path(field, band)
        noise = None
        if noise_path is not None:
            self._existing(noise_path, "survey.noise", field, band)
            noise = self._noise_blocks(field, band)
        ntype = self.config.survey.noise_type
        for y0, y1, sci in _row_blocks(sci_path):
            ok = np.isfinite(sci) & (sci != 0)
            if noise is not None:
                ok &= np.isfinite(_noise_to_rms(next(noise)[2], ntype))
            yield y0, y1, ok
        if noise is not None:
            for _ in noise:         # the noise map's checks after its last block
                pass

    def mask_path(self, field: str) -> Path | None:
        """Path of the field's mask (FITS image or DS9 region file), or None."""
        self._check(field)
        s = self.config.survey
        return None if s.mask is None else s.image_dir / s.mask.format(field=field)

    def mask(self, field: str) -> np.ndarray | None:
        """Pixels masked by ``survey.mask`` (bool, read-only, cached); None without a mask.

        A FITS mask masks its non-zero (or non-finite) pixels; a DS9 region
        file masks the pixels whose centres lie inside any of its regions
        (sky regions through the detection image's WCS).
        """
        path = self.mask_path(field)
        if path is None:
            return None
        path = self._existing(path, "survey.mask", field, self.detection_band)
        shape = self.shape(field)

        def build():
            if path.suffix.lower() == ".reg":
                return _region_mask(path, shape, self.header(field, self.detection_band))
            arr = read_array(path)
            if arr.shape != shape:
                raise ValueError(f"{path}: mask is {arr.shape[0]}x{arr.shape[1]} but field "
                                 f"{field!r} images are {shape[0]}x{shape[1]} (survey.mask)")
            return ~np.isfinite(arr) | (arr != 0)

        return _cached(("mask",) + _file_key(path) + shape, build)

    def footprint(self, field: str) -> np.ndarray:
        """Where sources are placed and area is counted (bool, read-only, cached).

        Every band of :meth:`coverage_bands` has data (:meth:`band_valid`) and
        the pixel is not masked (:meth:`mask`).
        """
        bands = self.coverage_bands()
        key = ("footprint",) + tuple(bands) + tuple(
            _file_key(self._existing(self.science_path(field, b), "survey.science", field, b))
            for b in bands)
        mpath = self.mask_path(field)
        if mpath is not None:
            key += _file_key(self._existing(mpath, "survey.mask", field, self.detection_band))

        def build():
            # Block by block from the files: no band's image or validity map is kept.
            ok = np.empty(self.shape(field), dtype=bool)
            for y0, y1, v in self._valid_blocks(field, bands[0]):
                ok[y0:y1] = v
            for b in bands[1:]:
                for y0, y1, v in self._valid_blocks(field, b):
                    ok[y0:y1] &= v
            m = self.mask(field)
            if m is not None:
                ok &= ~m
            return ok

        return _cached(key + (self.config.survey.noise_type,
                              self.config.survey.negative_weights), build)

    def pixel_scale_arcsec(self, field: str) -> float:
        """Pixel scale [arcsec/pixel]: the config value, else the detection image's WCS.

        Raises
        ------
        ValueError
            No config value and no pixel scale in the header, or
            pixels that are not square to 1 %.
        """
        if self.config.survey.pixel_scale_arcsec is not None:
            return float(self.config.survey.pixel_scale_arcsec)
        self._check(field)
        if field not in self._scales:
            from .wcs import pixel_axis_scales_arcsec, pixel_scale_arcsec

            det = self.detection_band
            h = self.header(field, det)
            path = self.science_path(field, det)
            sides = pixel_axis_scales_arcsec(h)
            if sides is None:
                raise ValueError(f"{path}: no pixel scale (CD, CDELT or PIXSCALE) in the "
                                 f"header; set survey.pixel_scale_arcsec")
            sx, sy = sides
            if not (np.isfinite(sx) and np.isfinite(sy) and sx > 0 and sy > 0):
                raise ValueError(f"{path}: invalid WCS pixel scale ({sx}, {sy}) arcsec; set "
                                 f"survey.pixel_scale_arcsec")
            if abs(sx - sy) > 0.01 * max(sx, sy):
                raise ValueError(f"{path}: pixels are not square ({sx:.5g} x {sy:.5g} arcsec); "
                                 f"set survey.pixel_scale_arcsec explicitly")
            self._scales[field] = float(pixel_scale_arcsec(h))
        return self._scales[field]
