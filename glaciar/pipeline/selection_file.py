"""The selection-function file: one or more fitted :class:`SelectionFunction` as FITS.

The layout (format :data:`FILE_FORMAT`) is documented in
``docs/selection-function-file.md`` so that it can be read without glaciar:
a primary header (format, version, model, magnitude type, area, fields), a
``META`` table (JSON values), and per fit (EXTVER 1..NFITS) ``DRAWS``
(posterior draws; model and simulated box in the header), ``PARAMS``
(quantiles and chain diagnostics per parameter), the ``C_GRID``, ``SR_GRID``
and ``P_GRID`` cubes (posterior quantiles :data:`GRID_QUANTILES` on the z x m
grid, survey averages over depth), ``PPC`` and ``DEPTH`` (area by depth).

This module is the only place the layout is written or read;
``SelectionFunction.read/read_all/write/to_bytes`` forward here.
"""
from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from ..inference.models import SurfaceModel
from ..inference.selection_function import GRID_QUANTILES, SelectionFunction

__all__ = ["FILE_FORMAT", "to_bytes", "write", "read_all", "read"]

FILE_FORMAT = "glaciar-selection-function-2"

_DOMAIN_TAGS = (("z", "Z"), ("mag", "M"), ("depth", "D"))
_GRID_EXTS = (("C", "C_GRID"), ("S", "SR_GRID"), ("P", "P_GRID"))
_GRID_QUANTITY = {"C": "completeness C(m,z), area-weighted over depth",
                  "S": "selected given recovered = P/C",
                  "P": "selection probability P(rec and sel|z,m)"}


def _hdus(sf: SelectionFunction, extver: int) -> list:
    """The extensions of one fit (EXTVER ``extver``)."""
    from astropy.io import fits
    from astropy.table import Table

    mdl = sf.model
    hdus = []
    h = fits.table_to_hdu(Table(sf.draws, names=mdl.param_names))
    h.name, h.ver = "DRAWS", extver
    h.header["FIELD"] = (sf.field, "field of this fit; all = pooled")
    h.header["MODEL"] = (mdl.shape, "completeness step shape")
    for k, v in mdl.to_header_dict().items():
        h.header[k] = v if not (isinstance(v, float) and np.isnan(v)) else "NONE"
    tags = dict(_DOMAIN_TAGS)
    for key, (lo, hi) in sf.domain.items():
        h.header[f"{tags[key]}MIN"] = (lo, f"simulated {key} range, lower end")
        h.header[f"{tags[key]}MAX"] = (hi, f"simulated {key} range, upper end")
    for k, v in sf.fit_info.items():
        if np.isscalar(v) and k.upper()[:8] not in h.header:
            h.header[k.upper()[:8]] = v
    hdus.append(h)
    q = np.quantile(sf.draws, GRID_QUANTILES, axis=0)
    cols = {"name": mdl.param_names, "prior_mean": mdl.prior_mean, "prior_sd": mdl.prior_sd,
            "median": q[0], "q16": q[1], "q84": q[2], "q025": q[3], "q975": q[4]}
    for k in ("tau", "ess", "rhat"):
        if k in sf.diagnostics:
            cols[k] = np.asarray(sf.diagnostics[k], float)
    h = fits.table_to_hdu(Table(cols))
    h.name, h.ver = "PARAMS", extver
    h.header["FIELD"] = sf.field
    hdus.append(h)
    if sf.z_grid is not None and sf.m_grid is not None:
        zg, mg = sf.z_grid, sf.m_grid
        gd = sf.grid_draws()
        for which, ext in _GRID_EXTS:
            img = fits.ImageHDU(np.quantile(gd[which], GRID_QUANTILES, axis=0).astype(np.float32),
                                name=ext, ver=extver)
            hh = img.header
            hh["FIELD"] = sf.field
            hh["CTYPE1"], hh["CRPIX1"], hh["CRVAL1"] = "MAG", 1.0, float(mg[0])
            hh["CDELT1"] = float(mg[1] - mg[0]) if len(mg) > 1 else 1.0
            hh["CUNIT1"] = "mag"
            hh["CTYPE2"], hh["CRPIX2"], hh["CRVAL2"] = "REDSHIFT", 1.0, float(zg[0])
            hh["CDELT2"] = float(zg[1] - zg[0]) if len(zg) > 1 else 1.0
            hh["CTYPE3"] = "QUANTILE"
            for k, qv in enumerate(GRID_QUANTILES):
                hh[f"QUANT{k + 1}"] = (qv, f"posterior quantile of plane {k + 1}")
            hh["QUANTITY"] = _GRID_QUANTITY[which]
            hdus.append(img)
    if sf.ppc is not None and len(sf.ppc):
        h = fits.table_to_hdu(Table(sf.ppc))
        h.name, h.ver = "PPC", extver
        h.header["FIELD"] = sf.field
        hdus.append(h)
    if sf.depth_area:
        rows = [(f, lo, hi, a) for f, (e, aa) in sorted(sf.depth_area.items())
                for lo, hi, a in zip(e[:-1], e[1:], aa)]
        t = Table(rows=rows, names=("field", "depth_lo", "depth_hi", "area_arcmin2"))
        h = fits.table_to_hdu(t)
        h.name, h.ver = "DEPTH", extver
        h.header["FIELD"] = sf.field
        hdus.append(h)
    return hdus


def to_bytes(fits_list: list[SelectionFunction], meta: dict | None = None) -> bytes:
    """One or more fits (e.g. one per field) as the bytes of one FITS file.

    Parameters
    ----------
    fits_list : list of SelectionFunction
        EXTVER 1, 2, ... in this order; all share one model shape.
    meta : dict, optional
        Run metadata for the primary header and ``META`` (default: the first fit's).
    """
    from astropy.io import fits
    from astropy.table import Table

    from .. import __version__

    if not fits_list:
        raise ValueError("to_bytes: nothing to write")
    meta = dict(meta if meta is not None else fits_list[0].meta)
    ph = fits.PrimaryHDU()
    ph.header["FORMAT"] = (FILE_FORMAT, "see docs/selection-function-file.md")
    ph.header["GLACVER"] = (__version__, "glaciar version that wrote the file")
    ph.header["MODEL"] = (fits_list[0].model.shape, "completeness step shape")
    ph.header["MAGTYPE"] = (str(meta.get("magnitude_type", "apparent")),
                            "m: apparent (AB) or absolute (M_UV)")
    ph.header["DEPTHAW"] = (bool(fits_list[0].model.depth_aware), "depth-aware model")
    ph.header["NFITS"] = (len(fits_list), "number of fits (EXTVER 1..NFITS)")
    for i, sf in enumerate(fits_list):
        ph.header[f"FIELD{i + 1}"] = sf.field
    total = SelectionFunction(fits_list[0].model, fits_list[0].draws[:1], meta=meta).area_arcmin2()
    if total is None:
        areas = [sf.area_arcmin2() for sf in fits_list]
        if all(a is not None for a in areas):
            total = areas[0] if fits_list[0].field == "all" else sum(areas)
    if total is not None:
        ph.header["AREA"] = (total, "survey area, all fields [arcmin2]")
    if meta.get("detection_band"):
        ph.header["DETBAND"] = str(meta["detection_band"])
    if meta.get("config_hash"):
        ph.header["CONFHASH"] = str(meta["config_hash"])
    keys = sorted(meta)
    mt = Table({"key": keys, "value": [json.dumps(meta[k], default=str) for k in keys]})
    mh = fits.table_to_hdu(mt)
    mh.name = "META"
    hdus = [ph, mh]
    for i, sf in enumerate(fits_list):
        hdus += _hdus(sf, i + 1)
    buf = io.BytesIO()
    fits.HDUList(hdus).writeto(buf)
    return buf.getvalue()


def write(fits_list: list[SelectionFunction], path, meta: dict | None = None) -> Path:
    """Write :func:`to_bytes` of ``fits_list`` to ``path`` atomically; returns the path."""
    from ..store import atomic_write_bytes

    path = Path(path)
    atomic_write_bytes(path, to_bytes(fits_list, meta))
    return path


def read_all(path) -> dict[str, SelectionFunction]:
    """All fits in the file at ``path``, keyed by field name.

    Raises
    ------
    ValueError
        The file is not a selection-function file of format :data:`FILE_FORMAT`.
    """
    from astropy.io import fits

    out = {}
    with fits.open(path, memmap=False) as hdul:
        if hdul[0].header.get("FORMAT") != FILE_FORMAT:
            raise ValueError(f"{path}: not a glaciar selection-function file of this version "
                             f"(FORMAT={hdul[0].header.get('FORMAT')!r}, expected {FILE_FORMAT!r})")
        meta = {}
        if "META" in hdul:
            t = _native(hdul["META"].data)
            for k, v in zip(t["key"], t["value"]):
                meta[str(k)] = json.loads(str(v))
        nfits = int(hdul[0].header["NFITS"])
        for v in range(1, nfits + 1):
            dh = hdul["DRAWS", v]
            hdr = dict(dh.header)
            if hdr.get("DEPTHREF") == "NONE":
                hdr["DEPTHREF"] = float("nan")
            model = SurfaceModel.from_header_dict(hdr)
            t = _native(dh.data)
            draws = np.column_stack([np.asarray(t[n], float) for n in model.param_names])
            domain = {}
            for key, tag in _DOMAIN_TAGS:
                if f"{tag}MIN" in hdr:
                    domain[key] = (float(hdr[f"{tag}MIN"]), float(hdr[f"{tag}MAX"]))
            zg = mg = None
            if ("C_GRID", v) in hdul:
                gh = hdul["C_GRID", v].header
                n_m, n_z = gh["NAXIS1"], gh["NAXIS2"]
                mg = gh["CRVAL1"] + (np.arange(n_m) + 1 - gh["CRPIX1"]) * gh["CDELT1"]
                zg = gh["CRVAL2"] + (np.arange(n_z) + 1 - gh["CRPIX2"]) * gh["CDELT2"]
            ppc = _native(hdul["PPC", v].data) if ("PPC", v) in hdul else None
            depth_area = {}
            if ("DEPTH", v) in hdul:
                d = _native(hdul["DEPTH", v].data)
                for f in np.unique(d["field"]):
                    r = d[d["field"] == f]
                    depth_area[str(f)] = (np.append(r["depth_lo"], r["depth_hi"][-1]),
                                          np.asarray(r["area_arcmin2"], float))
            diag = {}
            p = _native(hdul["PARAMS", v].data)
            for k in ("tau", "ess", "rhat"):
                if k in p.dtype.names:
                    diag[k] = np.asarray(p[k], float)
            field = str(hdr.get("FIELD", "all"))
            out[field] = SelectionFunction(model, draws, zg, mg, meta, field, ppc,
                                           depth_area=depth_area, domain=domain, diagnostics=diag)
    return out


def read(path, field: str | None = None) -> SelectionFunction:
    """One fit of the selection-function file at ``path``.

    Parameters
    ----------
    path : str or path-like
    field : str, optional
        Which fit to return when the file holds one per field.

    Raises
    ------
    FileNotFoundError
        No file at ``path``.
    ValueError
        Not a selection-function file, several fits and no ``field``, or no
        fit for ``field``.
    """
    if not Path(path).exists():
        raise FileNotFoundError(f"{path}: no such selection-function file")
    fits_ = read_all(path)
    if field is None:
        if len(fits_) == 1:
            return next(iter(fits_.values()))
        raise ValueError(f"{path} holds fits for fields {sorted(fits_)}; pass field=")
    if field not in fits_:
        raise ValueError(f"{path}: no fit for field {field!r} (have {sorted(fits_)})")
    return fits_[field]


def _native(data) -> np.ndarray:
    """A FITS table as a structured array in native byte order (strings as str, logicals as bool)."""
    from astropy.table import Table
    arr = Table(data).as_array()

    def native(dt):
        if dt.kind in "SU":
            return np.dtype(f"U{max(dt.itemsize // (4 if dt.kind == 'U' else 1), 1)}")
        return dt.newbyteorder("=") if dt.kind in "iufb" else dt

    dt = [(n, native(arr.dtype[n])) for n in arr.dtype.names]
    out = np.empty(len(arr), dtype=dt)
    for n in arr.dtype.names:
        col = arr[n]
        out[n] = np.char.strip(np.char.decode(col) if col.dtype.kind == "S" else col) \
            if col.dtype.kind in "SU" else col
    return out
