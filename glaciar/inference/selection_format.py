"""The selection-function file's layout: fitted selection functions <-> the bytes of a FITS file.

The layout (format :data:`FILE_FORMAT`) is documented in
``docs/selection-function-file.md`` so that it can be read without glaciar:
a primary header (format, version, model, magnitude type, area, fields), a
``META`` table (JSON values), and per fit (EXTVER 1..NFITS) ``DRAWS``
(posterior draws; model and simulated box in the header), ``PARAMS``
(quantiles and chain diagnostics per parameter), the ``C_GRID``, ``SR_GRID``
and ``P_GRID`` cubes (posterior quantiles :data:`GRID_QUANTILES` on the z x m
grid, survey averages over depth), ``PPC`` and ``DEPTH`` (area by depth), ``LENS`` (lensed
fields: area nodes by depth and lens model, :mod:`glaciar.inference.lensed`), and
for luminosity-function codes ``VEFF_MUV`` / ``VEFF_MUV_DRAWS`` (V_eff as a function
of M_UV) and ``TRANSFER`` / ``TR_COUNTS`` / ``TR_DRAWS`` / ``TR_BINS`` (the photometric
transfer function p(m_obs | m_in, z)); one ``CONTAM`` table when the run injected
interlopers (:mod:`glaciar.inference.contamination`); one ``DETFILT`` table holds the detection
filter and the injections' beta distribution and IGM (:class:`InjectionSED`).

This module is the only place the layout is written or read.  It is a codec on bytes
(astropy.io.fits on an in-memory buffer): it touches no file, so it sits in the
inference layer beside the class whose product it encodes.
:class:`glaciar.SelectionFunction` (``to_bytes``, ``from_bytes``, ``read``, ``write``)
imports it; it does not import the class (:func:`decode` returns the class's keyword
arguments), so there is no cycle.
"""
from __future__ import annotations

import io
import json

import numpy as np

from ..galaxy.filters import Filter
from ..version import __version__
from ..galaxy.lensing import NODE_KEYS
from .contamination import contamination_hdu, read_contamination
from .covariates import covariate_hdus, read_covariates
from .lensed import LensNodes
from .models import SurfaceModel
from .products import GRID_QUANTILES, EffectiveVolume, InjectionSED, VeffTable

__all__ = ["FILE_FORMAT", "encode", "decode"]

FILE_FORMAT = "glaciar-selection-function-2"

_DOMAIN_TAGS = (("z", "Z"), ("mag", "M"), ("depth", "D"))
_GRID_EXTS = (("C", "C_GRID"), ("S", "SR_GRID"), ("P", "P_GRID"))
_GRID_QUANTITY = {"C": "completeness C(m,z), area-weighted over depth",
                  "S": "selected given recovered = P/C",
                  "P": "selection probability P(rec and sel|z,m)"}


def _hdus(sf, extver: int) -> list:
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
    if sf.veff_muv is not None:
        hdus += _veff_hdus(sf.veff_muv, sf.field, extver)
    if sf.transfer_matrix is not None:
        hdus += _transfer_hdus(sf.transfer_matrix, sf.field, extver)
    if sf.lens_nodes:
        hdus.append(_lens_hdu(sf.lens_nodes, sf.field, extver))
    hdus += covariate_hdus(sf, extver)          # size/beta covariates (CV_*), when fitted
    if sf.depth_area:
        rows = [(f, lo, hi, a) for f, (e, aa) in sorted(sf.depth_area.items())
                for lo, hi, a in zip(e[:-1], e[1:], aa)]
        t = Table(rows=rows, names=("field", "depth_lo", "depth_hi", "area_arcmin2"))
        h = fits.table_to_hdu(t)
        h.name, h.ver = "DEPTH", extver
        h.header["FIELD"] = sf.field
        hdus.append(h)
    return hdus


def _lens_hdu(lens_nodes: dict, field: str, extver: int):
    """``LENS``: every lensed field's area nodes per lens model (one row per node)."""
    from astropy.io import fits
    from astropy.table import Table

    rows = {k: [] for k in ("field", "model", "z_lens") + NODE_KEYS}
    for f, per in sorted(lens_nodes.items()):
        for name, nodes in per.items():
            n = len(nodes.area_arcmin2)
            rows["field"] += [f] * n
            rows["model"] += [name] * n
            rows["z_lens"] += [nodes.z_lens] * n
            for k in NODE_KEYS:
                rows[k] += list(np.asarray(getattr(nodes, k), float))
    h = fits.table_to_hdu(Table(rows))
    h.name, h.ver = "LENS", extver
    h.header["FIELD"] = field
    h.header["COMMENT"] = ("lens area nodes: image-plane area by local depth and lens (kappa, "
                           "gamma normalised to D_ls/D_s = 1); see docs/selection-function-file.md")
    return h


def _read_lens(hdul, v):
    if ("LENS", v) not in hdul:
        return None
    t = _native(hdul["LENS", v].data)
    out = {}
    for f, name in dict.fromkeys(zip(t["field"], t["model"])):
        r = t[(t["field"] == f) & (t["model"] == name)]
        out.setdefault(str(f), {})[str(name)] = LensNodes.from_dict(
            str(f), str(name), float(r["z_lens"][0]), {k: r[k] for k in NODE_KEYS})
    return out


def _veff_hdus(vt: VeffTable, field: str, extver: int) -> list:
    from astropy.io import fits
    from astropy.table import Table

    v = vt.volume
    t = Table({"M_uv": np.asarray(vt.M_uv, float), "median": v.median.value,
               "lower": v.lower.value, "upper": v.upper.value})
    for c in ("median", "lower", "upper"):
        t[c].unit = "Mpc3"
    t["M_uv"].unit = "mag"
    h = fits.table_to_hdu(t)
    h.name, h.ver = "VEFF_MUV", extver
    h.header["FIELD"] = field
    h.header["INTERVAL"] = (float(vt.interval), "central credible interval of lower/upper")
    h.header["AREA"] = (float(vt.area_arcmin2), "area integrated over [arcmin2]")
    h.header["COSMO"] = (str(vt.cosmology), "cosmology of dV/dz and M_UV -> m")
    d = fits.ImageHDU(np.asarray(v.draws.value, float), name="VEFF_MUV_DRAWS", ver=extver)
    d.header["FIELD"] = field
    d.header["BUNIT"] = "Mpc3"
    d.header["COMMENT"] = "V_eff per posterior draw (axis 2) and M_UV of VEFF_MUV (axis 1)"
    return [h, d]


def _transfer_hdus(tm, field: str, extver: int) -> list:
    """The extensions of a :class:`glaciar.tables.TransferMatrix`."""
    from astropy.io import fits
    from astropy.table import Table

    out = []
    for name, data in (("TRANSFER", tm.matrix), ("TR_COUNTS", tm.counts.astype(np.int64)),
                       ("TR_DRAWS", tm.draws.astype(np.float32))):
        h = fits.ImageHDU(data, name=name, ver=extver)
        h.header["FIELD"] = field
        for k, kind in enumerate(tm.kinds):
            h.header[f"KIND{k + 1}"] = (kind, f"plane {k + 1} of the kind axis")
        h.header["ALPHA"] = (float(tm.alpha), "Dirichlet prior per entry of a row")
        h.header["COMMENT"] = ("entry 0 of the last axis: not recovered/selected; 1+b: m_obs bin b "
                               "(TR_BINS); rows over the last axis sum to 1")
        out.append(h)
    rows = []
    for axis, e, val in (("z", tm.z_edges, tm.z_mean),
                         ("m_in", tm.m_in_edges, 0.5 * (tm.m_in_edges[1:] + tm.m_in_edges[:-1])),
                         ("m_obs", tm.m_obs_edges, None)):
        for i in range(len(e) - 1):
            rows.append((axis, i, float(e[i]), float(e[i + 1]),
                         float(val[i]) if val is not None else np.nan))
    t = Table(rows=rows, names=("axis", "index", "lo", "hi", "value"))
    h = fits.table_to_hdu(t)
    h.name, h.ver = "TR_BINS", extver
    h.header["FIELD"] = field
    out.append(h)
    return out


def _sed_hdu(sed: InjectionSED):
    from astropy.io import fits
    from astropy.table import Table

    f = sed.detection_filter
    h = fits.table_to_hdu(Table({"wave_angstrom": np.asarray(f.wave_angstrom, float),
                                 "throughput": np.asarray(f.throughput, float)}))
    h.name = "DETFILT"
    h.header["FILTNAME"] = (str(f.name), "detection band filter")
    h.header["BETAMEAN"] = (float(sed.beta_mean), "injected beta ~ N(BETAMEAN, BETASD)")
    h.header["BETASD"] = (float(sed.beta_sd), "scatter of the injected beta")
    h.header["IGM"] = (str(sed.igm), "IGM attenuation of the injections")
    h.header["COSMO"] = (str(sed.cosmology), "cosmology of the injections")
    return h


def encode(fits_list: list, meta: dict | None = None) -> bytes:
    """One or more fits (e.g. one per field) as the bytes of one FITS file.

    Parameters
    ----------
    fits_list : list of glaciar.SelectionFunction
        EXTVER 1, 2, ... in this order; all share one model shape.
    meta : dict, optional
        Run metadata for the primary header and ``META`` (default: the first fit's).
    """
    from astropy.io import fits
    from astropy.table import Table

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
    # the run's total area, as the class computes it from meta (one draw is enough)
    total = type(fits_list[0])(fits_list[0].model, fits_list[0].draws[:1], meta=meta).area_arcmin2()
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
    sed = next((sf.sed for sf in fits_list if sf.sed is not None), None)
    if sed is not None:
        hdus.append(_sed_hdu(sed))
    for i, sf in enumerate(fits_list):
        hdus += _hdus(sf, i + 1)
    # The interlopers' passing fraction (one per file: pooled over fields), when fitted.
    contam = next((sf.interlopers for sf in fits_list
                   if getattr(sf, "interlopers", None) is not None), None)
    if contam is not None:
        hdus.append(contamination_hdu(contam))
    buf = io.BytesIO()
    fits.HDUList(hdus).writeto(buf)
    return buf.getvalue()


def decode(data: bytes, source: str = "<bytes>") -> dict[str, dict]:
    """The fits in the bytes of a file: per field name, the keyword arguments of
    :class:`glaciar.SelectionFunction` (which builds itself from them: this module does
    not import the class).

    Parameters
    ----------
    data : bytes
        The whole file.
    source : str
        What to call it in messages (the file's path).

    Raises
    ------
    ValueError
        Not a selection-function file of format :data:`FILE_FORMAT`.
    """
    from astropy.io import fits

    out = {}
    with fits.open(io.BytesIO(data), memmap=False) as hdul:
        if hdul[0].header.get("FORMAT") != FILE_FORMAT:
            raise ValueError(f"{source}: not a glaciar selection-function file of this version "
                             f"(FORMAT={hdul[0].header.get('FORMAT')!r}, expected {FILE_FORMAT!r})")
        meta = {}
        if "META" in hdul:
            t = _native(hdul["META"].data)
            for k, v in zip(t["key"], t["value"]):
                meta[str(k)] = json.loads(str(v))
        sed = None
        if "DETFILT" in hdul:
            fh = hdul["DETFILT"]
            ft = _native(fh.data)
            sed = InjectionSED(Filter(str(fh.header["FILTNAME"]), np.asarray(ft["wave_angstrom"], float),
                                      np.asarray(ft["throughput"], float)),
                               float(fh.header["BETAMEAN"]), float(fh.header["BETASD"]),
                               str(fh.header["IGM"]), str(fh.header["COSMO"]))
        contam = read_contamination(hdul)       # None in files without CONTAM
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
            out[field] = dict(model=model, draws=draws, z_grid=zg, m_grid=mg, meta=meta,
                              field=field, ppc=ppc, depth_area=depth_area, domain=domain,
                              diagnostics=diag, sed=sed, veff_muv=_read_veff(hdul, v),
                              transfer_matrix=_read_transfer(hdul, v), interlopers=contam,
                              lens_nodes=_read_lens(hdul, v),
                              covariates=read_covariates(hdul, v))
    return out


def _read_veff(hdul, v):
    import astropy.units as u

    if ("VEFF_MUV", v) not in hdul:
        return None
    h = hdul["VEFF_MUV", v]
    t = _native(h.data)
    unit = u.Mpc ** 3
    draws = np.asarray(hdul["VEFF_MUV_DRAWS", v].data, float)
    vol = EffectiveVolume(median=np.asarray(t["median"], float) * unit,
                          lower=np.asarray(t["lower"], float) * unit,
                          upper=np.asarray(t["upper"], float) * unit, draws=draws * unit)
    return VeffTable(M_uv=np.asarray(t["M_uv"], float), volume=vol,
                     interval=float(h.header["INTERVAL"]), area_arcmin2=float(h.header["AREA"]),
                     cosmology=str(h.header["COSMO"]))


def _read_transfer(hdul, v):
    # glaciar.tables imports astropy.table: only when a file with transfer matrices is read
    from ..tables import TransferMatrix

    if ("TRANSFER", v) not in hdul:
        return None
    h = hdul["TRANSFER", v].header
    kinds = []
    while f"KIND{len(kinds) + 1}" in h:
        kinds.append(str(h[f"KIND{len(kinds) + 1}"]))
    b = _native(hdul["TR_BINS", v].data)

    def axis(name):
        r = b[b["axis"] == name]
        r = r[np.argsort(r["index"])]
        return np.append(np.asarray(r["lo"], float), float(r["hi"][-1])), np.asarray(r["value"], float)

    ze, zm = axis("z")
    me, _ = axis("m_in")
    oe, _ = axis("m_obs")
    return TransferMatrix(kinds=tuple(kinds), z_edges=ze, z_mean=zm, m_in_edges=me, m_obs_edges=oe,
                          counts=np.asarray(hdul["TR_COUNTS", v].data, np.int64),
                          matrix=np.asarray(hdul["TRANSFER", v].data, float),
                          draws=np.asarray(hdul["TR_DRAWS", v].data, float),
                          alpha=float(h["ALPHA"]))


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
