"""Filter throughput curves: built-in HST/JWST bands and user files; AB magnitudes.

Built-in curves are read, by name, from the throughput files shipped inside
the ``astro-sedpy`` package (module ``sedpy``, folder ``sedpy/data/filters``):
no download happens at run time.  Canonical names are
``<instrument>_<band>``, e.g. ``wfc3_ir_f160w``, ``wfc3_uvis_f606w``,
``acs_wfc_f814w``, ``nircam_f444w``; a short band name (``f160w``,
``F160W``) resolves when only one instrument has that band.

User curves (``read_filter_file``) may be two-column text (GLACiAR's
``.tab`` files, ``.dat``, sedpy ``.par``, CSV) or FITS tables.  Wavelengths
are in Angstrom throughout.
"""
from __future__ import annotations

import functools
import importlib.util
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from glaciar.constants import AB_ZEROPOINT_FNU, C_ANGSTROM_PER_S

__all__ = ["Filter", "BUILTIN_FILTERS", "builtin_filter_names", "get_filter",
           "read_filter_file", "ab_magnitude"]

# canonical name -> file name inside sedpy/data/filters (None: not shipped)
BUILTIN_FILTERS: dict[str, str | None] = {
    "wfc3_ir_f098m": "wfc3_ir_f098m.par",
    "wfc3_ir_f105w": "wfc3_ir_f105w.par",
    "wfc3_ir_f125w": "wfc3_ir_f125w.par",
    "wfc3_ir_f140w": "wfc3_ir_f140w.par",
    "wfc3_ir_f160w": "wfc3_ir_f160w.par",
    # No maintained PyPI package ships the WFC3/UVIS F600LP *system*
    # throughput (sedpy has none; pyphot's HST_WFC3_F600LP is the bare filter
    # transmission, peaking at 0.99, without detector QE and telescope).
    "wfc3_uvis_f600lp": None,
    "wfc3_uvis_f606w": "wfc3_uvis_f606w.par",
    "wfc3_uvis_f814w": "wfc3_uvis_f814w.par",
    "acs_wfc_f435w": "acs_wfc_f435w.par",
    "acs_wfc_f606w": "acs_wfc_f606w.par",
    "acs_wfc_f775w": "acs_wfc_f775w.par",
    "acs_wfc_f814w": "acs_wfc_f814w.par",
    "acs_wfc_f850lp": "acs_wfc_f850lp.par",
    # NIRCam curves: module-averaged filter + DBS + QE + OTE (sedpy's jwst_*.par)
    "nircam_f090w": "jwst_f090w.par",
    "nircam_f115w": "jwst_f115w.par",
    "nircam_f150w": "jwst_f150w.par",
    "nircam_f200w": "jwst_f200w.par",
    "nircam_f277w": "jwst_f277w.par",
    "nircam_f356w": "jwst_f356w.par",
    "nircam_f410m": "jwst_f410m.par",
    "nircam_f444w": "jwst_f444w.par",
}

#: Suffixes that mark a filter name as a throughput-curve file (text or FITS table).
FILE_SUFFIXES = (".tab", ".dat", ".txt", ".par", ".csv", ".ecsv", ".fits", ".fit", ".fts",
                 ".fits.gz")


@dataclass(frozen=True, eq=False)
class Filter:
    """A filter's total system throughput (photon-counting response).

    Parameters
    ----------
    name : str
        Band name (canonical built-in name, or the file stem of a user curve).
    wave_angstrom : numpy.ndarray
        Strictly increasing wavelengths [Angstrom], at least 2.
    throughput : numpy.ndarray
        Dimensionless throughput (>= 0, not all zero) at ``wave_angstrom``;
        linear between samples and zero outside.
    """

    name: str
    wave_angstrom: np.ndarray
    throughput: np.ndarray

    def __post_init__(self):
        wave = np.array(self.wave_angstrom, dtype=float)
        thr = np.array(self.throughput, dtype=float)
        where = f"filter {self.name!r}"
        if wave.ndim != 1 or thr.shape != wave.shape:
            raise ValueError(f"{where}: wavelength and throughput must be 1-D arrays of equal "
                             f"length, got shapes {wave.shape} and {thr.shape}")
        if wave.size < 2:
            raise ValueError(f"{where}: needs at least 2 samples, got {wave.size}")
        if not (np.all(np.isfinite(wave)) and np.all(np.isfinite(thr))):
            raise ValueError(f"{where}: wavelength and throughput must be finite")
        if wave[0] <= 0:
            raise ValueError(f"{where}: wavelengths must be positive (Angstrom), got {wave[0]}")
        bad = np.flatnonzero(np.diff(wave) <= 0)
        if bad.size:
            i = bad[0]
            raise ValueError(f"{where}: wavelengths must be strictly increasing; "
                             f"row {i + 1} ({wave[i]}) is followed by {wave[i + 1]}")
        if np.any(thr < 0):
            i = int(np.flatnonzero(thr < 0)[0])
            raise ValueError(f"{where}: throughput must be >= 0; got {thr[i]} at {wave[i]} A")
        if not np.any(thr > 0):
            raise ValueError(f"{where}: throughput is zero everywhere")
        wave.setflags(write=False)
        thr.setflags(write=False)
        object.__setattr__(self, "wave_angstrom", wave)
        object.__setattr__(self, "throughput", thr)

    @property
    def pivot_wavelength_angstrom(self) -> float:
        """Pivot wavelength sqrt(int T lambda dlambda / int T / lambda dlambda) [Angstrom]."""
        w, t = self.wave_angstrom, self.throughput
        return float(np.sqrt(np.trapezoid(t * w, w) / np.trapezoid(t / w, w)))

    def __repr__(self) -> str:
        return (f"Filter({self.name!r}, {self.wave_angstrom[0]:.0f}-{self.wave_angstrom[-1]:.0f} A, "
                f"pivot {self.pivot_wavelength_angstrom:.1f} A)")


def builtin_filter_names() -> tuple[str, ...]:
    """Canonical names of the built-in filters."""
    return tuple(BUILTIN_FILTERS)


def _sedpy_filter_dir() -> Path:
    # find_spec locates the package without importing it (sedpy's __init__
    # pulls in its whole photometry stack, which we do not need).
    spec = importlib.util.find_spec("sedpy")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(
            "built-in filters need the astro-sedpy package (pip install astro-sedpy); "
            "alternatively give the path of a throughput file")
    for loc in spec.submodule_search_locations:
        d = Path(loc) / "data" / "filters"
        if d.is_dir():
            return d
    raise FileNotFoundError(
        "the installed 'sedpy' module has no data/filters folder: another package named "
        "'sedpy' may shadow astro-sedpy; reinstall astro-sedpy or give a throughput file path")


def _resolve_builtin(name: str) -> str | None:
    """Canonical built-in name for ``name``, or None if it is not a built-in name."""
    key = name.strip().lower()
    if key in BUILTIN_FILTERS:
        return key
    matches = [c for c in BUILTIN_FILTERS if c.rsplit("_", 1)[-1] == key]
    if len(matches) == 1:
        return matches[0]
    if len(matches) > 1:
        raise ValueError(f"filter name {name!r} is ambiguous; use one of: {', '.join(matches)}")
    return None


@functools.lru_cache(maxsize=None)
def _load_builtin(canonical: str) -> Filter:
    fname = BUILTIN_FILTERS[canonical]
    if fname is None:
        raise ValueError(
            f"built-in filter {canonical!r} is not available: no maintained package ships its "
            f"system throughput; give the path of a throughput file instead (two columns, "
            f"Angstrom and throughput, e.g. STScI's or GLACiAR's f600lp.tab)")
    path = _sedpy_filter_dir() / fname
    filt = _read_filter_file(str(path), *_stat_key(path))
    return Filter(canonical, filt.wave_angstrom, filt.throughput)


def _stat_key(path: Path) -> tuple[int, int]:
    st = path.stat()
    return st.st_mtime_ns, st.st_size


def looks_like_path(value: str, suffixes=FILE_SUFFIXES) -> bool:
    """True for a string that names a file rather than a built-in (a separator or a suffix)."""
    return os.sep in value or "/" in value or "\\" in value or value.lower().endswith(tuple(suffixes))


def get_filter(name_or_path) -> Filter:
    """A filter by built-in name, or read from a throughput file.

    Parameters
    ----------
    name_or_path : str, os.PathLike or Filter
        A canonical built-in name (``wfc3_ir_f160w``), a unique short band
        name (``f160w``, case-insensitive), or the path of a curve file (see
        `read_filter_file`).  A `Filter` is returned unchanged.

    Returns
    -------
    Filter
        Cached: the same object is returned for the same name or unchanged file.

    Raises
    ------
    ValueError
        Unknown or ambiguous name (the message lists the choices), or a
        built-in band whose curve is not shipped.
    FileNotFoundError
        A path that does not exist.
    """
    if isinstance(name_or_path, Filter):
        return name_or_path
    if isinstance(name_or_path, os.PathLike):
        return read_filter_file(name_or_path)
    if not isinstance(name_or_path, str):
        raise TypeError(f"filter must be a name, a path or a Filter, got {type(name_or_path).__name__}")
    if not looks_like_path(name_or_path):
        canonical = _resolve_builtin(name_or_path)
        if canonical is not None:
            return _load_builtin(canonical)
    if os.path.isfile(name_or_path) or looks_like_path(name_or_path):
        return read_filter_file(name_or_path)
    raise ValueError(f"unknown filter {name_or_path!r}: not a built-in name ("
                     f"{', '.join(BUILTIN_FILTERS)}) nor an existing file")


def read_filter_file(path) -> Filter:
    """Read a throughput curve from a file.

    Parameters
    ----------
    path : str or os.PathLike
        Either a FITS table (``.fits``, ``.fit``, ``.fts``, ``.fits.gz``): the
        first table HDU, columns ``WAVELENGTH`` and ``THROUGHPUT`` (or
        ``TRANSMISSION``) if present, else the first two columns; the
        wavelength unit is read from ``TUNITn`` (any length unit), Angstrom
        when absent.  Or a text file: whitespace- or comma-separated columns,
        ``#`` starts a comment, leading non-numeric header lines are skipped;
        wavelength [Angstrom] and throughput are the first two columns, or
        columns 2-3 when the first is a row counter 1, 2, ... (as in
        GLACiAR's ``f140w.IR.tab``).  sedpy ``.par`` files are of this kind.

    Returns
    -------
    Filter
        Named after the file name without its suffix.  Cached per file
        (path, modification time, size).

    Raises
    ------
    FileNotFoundError, ValueError
        Missing file, unreadable content, too few columns, non-increasing
        wavelengths, negative throughput; the message names the file.
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise FileNotFoundError(f"filter curve file not found: {p}")
    p = p.resolve()
    return _read_filter_file(str(p), *_stat_key(p))


@functools.lru_cache(maxsize=64)
def _read_filter_file(path: str, _mtime_ns: int, _size: int) -> Filter:
    lower = path.lower()
    name = Path(path).name
    for suffix in sorted(FILE_SUFFIXES, key=len, reverse=True):
        if lower.endswith(suffix):
            name = name[: -len(suffix)]
            break
    if lower.endswith((".fits", ".fit", ".fts", ".fits.gz")):
        wave, thr = _read_fits_curve(path)
    else:
        wave, thr = _read_text_curve(path)
    try:
        return Filter(name, wave, thr)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


def _read_text_curve(path: str) -> tuple[np.ndarray, np.ndarray]:
    rows: list[list[float]] = []
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            text = line.split("#", 1)[0].strip()
            if not text:
                continue
            fields = text.replace(",", " ").split()
            try:
                values = [float(f) for f in fields]
            except ValueError:
                if not rows:        # a header line such as "WAVELENGTH,THROUGHPUT"
                    continue
                raise ValueError(f"{path}, line {lineno}: not a number in {text!r}") from None
            if len(values) < 2:
                raise ValueError(f"{path}, line {lineno}: expected at least 2 columns "
                                 f"(wavelength [Angstrom], throughput), got {len(values)}")
            if rows and len(values) != len(rows[0]):
                raise ValueError(f"{path}, line {lineno}: {len(values)} columns where the "
                                 f"previous lines have {len(rows[0])}")
            rows.append(values)
    if len(rows) < 2:
        raise ValueError(f"{path}: no throughput table found (need >= 2 numeric rows of "
                         f"wavelength [Angstrom] and throughput)")
    table = np.array(rows)
    first = table[:, 0]
    counter = (table.shape[1] >= 3 and
               (np.array_equal(first, np.arange(1, len(first) + 1))
                or np.array_equal(first, np.arange(len(first)))))
    wave, thr = (table[:, 1], table[:, 2]) if counter else (table[:, 0], table[:, 1])
    _check_angstrom(path, wave)
    return wave, thr


def _read_fits_curve(path: str) -> tuple[np.ndarray, np.ndarray]:
    from astropy import units as u
    from astropy.io import fits

    try:
        hdul = fits.open(path, memmap=False)
    except OSError as err:
        raise ValueError(f"{path}: cannot read as FITS ({err})") from None
    with hdul:
        hdu = next((h for h in hdul if isinstance(h, (fits.BinTableHDU, fits.TableHDU))), None)
        if hdu is None:
            raise ValueError(f"{path}: no table extension with wavelength and throughput columns")
        cols = hdu.columns
        names = [c.name.upper() for c in cols]
        if len(names) < 2:
            raise ValueError(f"{path}: table has {len(names)} column(s); need wavelength and throughput")
        iw = next((names.index(n) for n in ("WAVELENGTH", "WAVE", "LAMBDA") if n in names), 0)
        it = next((names.index(n) for n in ("THROUGHPUT", "TRANSMISSION", "RESPONSE") if n in names),
                  1 if iw != 1 else 0)
        wave = np.asarray(hdu.data.field(iw), dtype=float).ravel()
        thr = np.asarray(hdu.data.field(it), dtype=float).ravel()
        unit = cols[iw].unit
    if unit and unit.strip():
        try:
            wave = (wave * u.Unit(unit.strip())).to_value(u.AA)
        except (ValueError, u.UnitConversionError):
            raise ValueError(f"{path}: wavelength unit {unit!r} (TUNIT{iw + 1}) is not a "
                             f"length unit") from None
    else:
        _check_angstrom(path, wave)
    return wave, thr


def _check_angstrom(path: str, wave: np.ndarray) -> None:
    # A filter curve whose reddest sample is below 100 A is almost surely in
    # micron or nm-less units; catch it instead of silently mis-scaling.
    if wave.size and np.nanmax(wave) < 100.0:
        raise ValueError(f"{path}: wavelengths must be in Angstrom; the largest is "
                         f"{np.nanmax(wave):g}, which looks like micron")


def ab_magnitude(wave_angstrom, flambda, filt) -> float:
    """Photon-counting AB magnitude of a spectrum through a filter.

    m = -2.5 log10[ int f_lambda T lambda dlambda / int T c / lambda dlambda ] - 48.60,
    evaluated with the trapezoid rule on the union of the spectrum's and the
    filter's wavelength samples (both linear between samples; the spectrum
    is zero outside its range, the throughput outside the filter's).

    Parameters
    ----------
    wave_angstrom : array_like
        Spectrum wavelengths [Angstrom], strictly increasing.
    flambda : array_like
        f_lambda [erg s^-1 cm^-2 Angstrom^-1] at ``wave_angstrom``.
    filt : Filter or str or path
        The band (anything `get_filter` accepts).

    Returns
    -------
    float
        AB magnitude; ``+inf`` when the in-band flux is zero, ``nan`` when it
        is negative.  No warnings are emitted.
    """
    filt = get_filter(filt)
    w = np.asarray(wave_angstrom, dtype=float)
    f = np.asarray(flambda, dtype=float)
    if w.ndim != 1 or f.shape != w.shape:
        raise ValueError(f"wave_angstrom and flambda must be 1-D of equal length, "
                         f"got shapes {w.shape} and {f.shape}")
    if w.size >= 2 and np.any(np.diff(w) <= 0):
        raise ValueError("wave_angstrom must be strictly increasing")
    fw, ft = filt.wave_angstrom, filt.throughput
    inside = (w > fw[0]) & (w < fw[-1])
    grid = np.union1d(fw, w[inside])
    thr = np.interp(grid, fw, ft)
    flux = np.interp(grid, w, f, left=0.0, right=0.0) if w.size else np.zeros_like(grid)
    num = np.trapezoid(flux * thr * grid, grid)
    den = np.trapezoid(thr * C_ANGSTROM_PER_S / grid, grid)
    if num == 0:
        return float("inf")
    if not num > 0:
        return float("nan")
    return float(-2.5 * np.log10(num / den) + AB_ZEROPOINT_FNU)
