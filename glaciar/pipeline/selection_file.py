"""The selection-function file: one or more fitted :class:`SelectionFunction` as FITS.

The layout (format :data:`FILE_FORMAT`) is documented in
``docs/selection-function-file.md`` so that it can be read without glaciar:
a primary header (format, version, model, magnitude type, area, fields), a
``META`` table (JSON values), and per fit (EXTVER 1..NFITS) ``DRAWS``
(posterior draws; model and simulated box in the header), ``PARAMS``
(quantiles and chain diagnostics per parameter), the ``C_GRID``, ``SR_GRID``
and ``P_GRID`` cubes (posterior quantiles :data:`GRID_QUANTILES` on the z x m
grid, survey averages over depth), ``PPC`` and ``DEPTH`` (area by depth), and
for luminosity-function codes ``VEFF_MUV`` / ``VEFF_MUV_DRAWS`` (V_eff as a function
of M_UV) and ``TRANSFER`` / ``TR_COUNTS`` / ``TR_DRAWS`` / ``TR_BINS`` (the photometric
transfer function p(m_obs | m_in, z)); one ``DETFILT`` table holds the detection
filter and the injections' beta distribution and IGM (:class:`InjectionSED`).
:func:`add_lf_products` computes the last two for ``glaciar fit``.

This module is the only place the layout is written or read;
``SelectionFunction.read/read_all/write/to_bytes`` forward here.
"""
from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from ..inference.models import SurfaceModel
from ..inference.selection_function import (GRID_QUANTILES, EffectiveVolume, InjectionSED,
                                             SelectionFunction, VeffTable)
from ..tables import TransferMatrix

__all__ = ["FILE_FORMAT", "to_bytes", "write", "read_all", "read", "add_lf_products",
           "injection_sed"]

FILE_FORMAT = "glaciar-selection-function-2"

_DOMAIN_TAGS = (("z", "Z"), ("mag", "M"), ("depth", "D"))
_GRID_EXTS = (("C", "C_GRID"), ("S", "SR_GRID"), ("P", "P_GRID"))
#: V_eff(M_UV) in the file: M_UV step [mag], posterior draws, Simpson nodes in z and
#: Gauss-Hermite nodes in beta (within 6.5e-4 of 401 z and 9 beta nodes, every draw and M_UV
#: above 1e-3 of the peak, on a depth-aware demo fit).
VEFF_MUV_STEP = 0.1
VEFF_MUV_DRAWS = 200
VEFF_MUV_NZ = 101
VEFF_MUV_NBETA = 5
VEFF_MUV_INTERVAL = 0.68
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
    if sf.veff_muv is not None:
        hdus += _veff_hdus(sf.veff_muv, sf.field, extver)
    if sf.transfer_matrix is not None:
        hdus += _transfer_hdus(sf.transfer_matrix, sf.field, extver)
    if sf.depth_area:
        rows = [(f, lo, hi, a) for f, (e, aa) in sorted(sf.depth_area.items())
                for lo, hi, a in zip(e[:-1], e[1:], aa)]
        t = Table(rows=rows, names=("field", "depth_lo", "depth_hi", "area_arcmin2"))
        h = fits.table_to_hdu(t)
        h.name, h.ver = "DEPTH", extver
        h.header["FIELD"] = sf.field
        hdus.append(h)
    return hdus


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


def _transfer_hdus(tm: TransferMatrix, field: str, extver: int) -> list:
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
    sed = next((sf.sed for sf in fits_list if sf.sed is not None), None)
    if sed is not None:
        hdus.append(_sed_hdu(sed))
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
        sed = None
        if "DETFILT" in hdul:
            from ..galaxy.filters import Filter
            fh = hdul["DETFILT"]
            ft = _native(fh.data)
            sed = InjectionSED(Filter(str(fh.header["FILTNAME"]), np.asarray(ft["wave_angstrom"], float),
                                      np.asarray(ft["throughput"], float)),
                               float(fh.header["BETAMEAN"]), float(fh.header["BETASD"]),
                               str(fh.header["IGM"]), str(fh.header["COSMO"]))
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
                                           depth_area=depth_area, domain=domain, diagnostics=diag,
                                           sed=sed, veff_muv=_read_veff(hdul, v),
                                           transfer_matrix=_read_transfer(hdul, v))
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


def injection_sed(run_dir, manifest: dict) -> InjectionSED | None:
    """The injections' spectra of a run: detection filter, beta distribution, IGM, cosmology.

    From the manifest's ``store_settings`` (the resolved configuration); a detection
    filter given as a file is read from the run's ``config.yaml``.  None when the
    manifest does not record them (a run made before they were stored).
    """
    from .. import constants as C
    from ..galaxy.filters import get_filter

    st = manifest.get("store_settings") or {}
    src = st.get("source") or {}
    det = manifest.get("detection_band")
    band = ((st.get("survey") or {}).get("bands") or {}).get(det) or {}
    spec = band.get("filter")
    if not (src and det and spec) or any(k not in src for k in ("beta_mean", "beta_sd", "igm")):
        return None
    if spec == "<file>":
        import yaml

        cfg_path = Path(run_dir) / C.RUN_CONFIG_NAME
        try:
            spec = yaml.safe_load(cfg_path.read_text())["survey"]["bands"][det]["filter"]
        except (OSError, KeyError, TypeError) as exc:
            raise ValueError(f"{cfg_path}: cannot read the detection band's filter file "
                             f"({exc})") from exc
        p = Path(spec)
        spec = p if p.is_absolute() else Path(run_dir) / p
    return InjectionSED(get_filter(spec), float(src["beta_mean"]), float(src["beta_sd"]),
                        str(src["igm"]), str(src.get("cosmology", "Planck18")))


def add_lf_products(run_dir, manifest: dict, fits_list: list[SelectionFunction], *,
                    cosmology=None, seed=0) -> None:
    """Attach the injections' SED, V_eff(M_UV) and the transfer matrices to each fit.

    The transfer matrices come from the per-task histograms of the measured
    magnitude stored in the footers (:func:`glaciar.store.read_current_histograms`,
    no row read) when every task has them, else from the per-source rows
    (:func:`glaciar.pipeline.inputs.read_columns`: input and measured
    detection-band magnitudes and the flags); fits named by a field use that
    field's sources, the pooled fit ("all") every listed field's.  V_eff(M_UV)
    is left out (with the reason in ``fit_info["veffmuv"]``) when the fit has
    no area or no redshift range; the transfer matrices when the store has no
    measured magnitude.

    Parameters
    ----------
    run_dir : path-like
    manifest : dict
    fits_list : list of SelectionFunction
        Modified in place (``sed``, ``veff_muv``, ``transfer_matrix``).
    cosmology : astropy Cosmology, optional
        Default: the injections'.
    seed : int
        Seed of the transfer matrices' draws (fit i uses ``[seed, i]``).
    """
    import warnings

    from .. import constants as C
    from ..galaxy.population import get_cosmology

    sed = injection_sed(run_dir, manifest)
    det = manifest.get("detection_band")
    obs_col = C.band_column(C.OBS_MAG_QUANTITY, det) if det else None
    transfer = _transfer_source(run_dir, obs_col)
    listed = [str(f) for f in (manifest.get("fields") or [])]
    for i, sf in enumerate(fits_list):
        sf.sed = sed
        cosmo = get_cosmology(cosmology if cosmology is not None else
                              (sed.cosmology if sed is not None else None))
        if sed is not None or sf.magnitude_type == "absolute":
            try:
                grid = sf.muv_grid(VEFF_MUV_STEP, cosmology=cosmo)
                if not grid.size:
                    raise ValueError("no M_UV maps inside the simulated magnitude range at every z")
                few = SelectionFunction(sf.model, sf.draws[:VEFF_MUV_DRAWS], meta=sf.meta,
                                        field=sf.field, depth_area=sf.depth_area,
                                        domain=sf.domain, sed=sed)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")     # the fit already warns about z edges
                    vol = few.effective_volume_muv(grid, cosmology=cosmo,
                                                   n_z=VEFF_MUV_NZ, n_beta=VEFF_MUV_NBETA,
                                                   interval=VEFF_MUV_INTERVAL)
                sf.veff_muv = VeffTable(M_uv=grid, volume=vol, interval=VEFF_MUV_INTERVAL,
                                        area_arcmin2=float(few.area_arcmin2() or np.nan),
                                        cosmology=str(getattr(cosmo, "name", cosmo)))
            except ValueError as exc:
                sf.fit_info["veffmuv"] = f"none: {exc}"[:60]
        if transfer is not None:
            keep = ([sf.field] if sf.field != "all" else listed) or None
            tm = transfer(keep, [int(seed), i])
            if tm is not None:
                sf.transfer_matrix = tm


def _transfer_source(run_dir, obs_col):
    """``f(fields or None, seed) -> TransferMatrix or None`` over the store, or None.

    From the stored histograms when every current task has them for
    ``obs_col``; else from the rows (None when they lack the columns).
    """
    from .. import constants as C
    from ..store import (COUNT_K_REC, COUNT_K_SEL, COUNT_N, HIST_MIN_KEY, HIST_MOBS_BIN,
                         read_current_histograms)
    from ..tables import transfer_from_histograms, transfer_matrix
    from .inputs import read_columns

    if obs_col is None:
        return None
    got = read_current_histograms(run_dir)
    if got is not None and got[1] == obs_col:
        hist = got[0]

        def from_hist(keep, seed):
            h = hist
            if keep and C.COL_FIELD in h.columns:
                h = h[h[C.COL_FIELD].astype(str).isin(keep)]
            if not int(h[COUNT_N].sum()):
                return None
            return transfer_from_histograms(
                h[C.COL_Z].to_numpy(float), h[HIST_MIN_KEY].to_numpy(float),
                h[HIST_MOBS_BIN].to_numpy(), h[COUNT_N].to_numpy(), h[COUNT_K_REC].to_numpy(),
                h[COUNT_K_SEL].to_numpy(), seed=seed)
        return from_hist

    want = [C.COL_FIELD, C.COL_Z, C.COL_MAG_INPUT, C.COL_RECOVERED, C.COL_SELECTED, obs_col]
    df = read_columns(run_dir, want)
    if obs_col not in df.columns or C.COL_MAG_INPUT not in df.columns:
        return None

    def from_rows(keep, seed):
        rows = df
        if keep and C.COL_FIELD in df.columns:
            rows = df[df[C.COL_FIELD].astype(str).isin(keep)]
        if not len(rows):
            return None
        return transfer_matrix(
            rows[C.COL_Z].to_numpy(float), rows[C.COL_MAG_INPUT].to_numpy(float),
            rows[obs_col].to_numpy(float), rows[C.COL_RECOVERED].to_numpy(bool),
            rows[C.COL_SELECTED].to_numpy(bool), seed=seed)
    return from_rows


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
