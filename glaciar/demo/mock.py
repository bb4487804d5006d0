"""A mock universe with a known UV luminosity function, rendered into demo fields.

The end-to-end closure test (``benchmarks/closure.py``) needs a sky whose true
luminosity function is known: galaxies drawn from a Schechter phi(M_UV) over the
comoving volume of a redshift range, given the same spectra, shapes and sizes as
glaciar's injections, rendered with the same PSF-convolved templates and added,
with source shot noise, to the science images of several demo fields.  Running
the user's path (catalogue -> simulate -> fit -> lf) on those images must then
give back the input parameters.

The population (:func:`draw_mock_population`)
----------------------------------------------
* Number: Poisson with mean N = Omega int dz dV/dz/dOmega int dM phi(M) over
  ``z_range`` x ``M_range`` (phi does not evolve with z, so the two integrals
  separate), one draw per field (mean from the field's own solid angle).
* z from dV/dz (the injections' cosmology, ``source.cosmology``), M_UV from
  phi(M): exact inverse CDFs of fine tabulations (4097 nodes, piecewise
  linear; the tabulated integrals agree with ``scipy.integrate.quad`` to < 1e-6,
  tests/demo/test_mock.py).
* beta, Sersic index, axis ratio, position angle and r_eff from the config's
  :class:`~glaciar.galaxy.population.SourceModel`, drawn as
  :func:`glaciar.engine.task.draw_task_sources` draws them (same functions, same
  rounding of r_eff to the template lattice), except that beta is always drawn
  per source (a universe has no "iteration"; ``beta_per: iteration`` is a
  convention of the injections whose average over iterations is this
  distribution).
* Band magnitudes from :func:`glaciar.galaxy.sed.band_magnitudes` with the
  source's own z, beta and M_UV (the config's filters and IGM).

Rendering (:func:`render_sources`, :func:`render_mock_universe`)
----------------------------------------------------------------
Positions are uniform over the field's footprint (the pixels where the run
places injections and counts area: :meth:`glaciar.survey.Survey.footprint`),
uniform inside the pixel.  Each source gets, in each band where it has flux
(m < 50, the injections' rule), the unit-flux template of
:class:`glaciar.galaxy.templates.TemplateCache` built from the band's PSF as the
run builds it, scaled by its flux 10^(-0.4 (m - zeropoint)).  Source shot noise:
with gain g (electrons per image unit, the band's ``gain``), each stamp pixel
of mean c = g x model gets Poisson(c) / g instead of model; without a gain (None
or inf) the stamp is added noise-free.  Pixels without data (weight 0) get
nothing.  Weight maps are not changed.  The injections themselves add no
pixel shot noise (glaciar.engine.scene); at the selection limit the source
shot noise is < 2 % of the sky variance in the demo's bands, so this is not a
difference the closure test can see.

The science images are rewritten atomically, with the header keyword
``MOCKSEED`` so that a second rendering into the same files is refused.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

__all__ = ["Schechter", "comoving_volume_arcmin2", "expected_number", "draw_mock_population",
           "field_footprints", "place_sources", "render_sources", "render_mock_universe",
           "build_mock_survey", "MOCK_CONFIG_NAME", "MOCK_TRUTH_NAME"]

MOCK_CONFIG_NAME = "mock.yaml"
MOCK_TRUTH_NAME = "mock_truth.parquet"
_N_NODES = 4097
_ARCMIN2_SR = (math.pi / (180.0 * 60.0)) ** 2          # one arcmin^2 in steradians


@dataclass(frozen=True)
class Schechter:
    """phi(M) = 0.4 ln 10 phi* 10^(-0.4 (alpha + 1)(M - M*)) exp(-10^(-0.4 (M - M*))).

    Attributes
    ----------
    log_phi_star : float
        log10 phi* [Mpc^-3 mag^-1].
    M_star : float
        Characteristic absolute UV magnitude (AB, rest 1600 A).
    alpha : float
        Faint-end slope.
    """

    log_phi_star: float
    M_star: float
    alpha: float

    def __call__(self, M, z=None):
        """phi at absolute magnitude(s) ``M`` [Mpc^-3 mag^-1] (``z`` ignored: no evolution)."""
        x = 10.0 ** (-0.4 * (np.asarray(M, dtype=float) - self.M_star))
        out = 0.4 * math.log(10.0) * 10.0 ** self.log_phi_star * x ** (self.alpha + 1.0) * np.exp(-x)
        if z is not None:
            out = np.broadcast_to(out, np.broadcast_shapes(np.shape(out), np.shape(z))).copy()
        return out

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def _cosmology(cfg_or_name):
    from ..galaxy.population import get_cosmology

    name = cfg_or_name
    if hasattr(cfg_or_name, "source"):
        name = cfg_or_name.source.cosmology
    return get_cosmology(name)


def _cdf_table(x: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Cumulative trapezoid integral of ``f`` over ``x`` (starting at 0)."""
    return np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(x))])


def _tables(lf, z_range, M_range, cosmology):
    """(zz, cumulative dV/dz/dOmega [Mpc^3/sr]; MM, cumulative phi [Mpc^-3])."""
    import astropy.units as u

    z_lo, z_hi = (float(v) for v in z_range)
    M_lo, M_hi = (float(v) for v in M_range)
    if not (0 < z_lo < z_hi and M_lo < M_hi):
        raise ValueError(f"need 0 < z_lo < z_hi and M_bright < M_faint, got z {z_range}, M {M_range}")
    zz = np.linspace(z_lo, z_hi, _N_NODES)
    dv = cosmology.differential_comoving_volume(zz).to_value(u.Mpc ** 3 / u.sr)
    MM = np.linspace(M_lo, M_hi, _N_NODES)
    ph = np.asarray(lf(MM), dtype=float)
    if not (np.all(np.isfinite(ph)) and np.all(ph >= 0)):
        raise ValueError("the luminosity function must be finite and >= 0 over M_range")
    return zz, _cdf_table(zz, dv), MM, _cdf_table(MM, ph)


def comoving_volume_arcmin2(z_range, cosmology="Planck18") -> float:
    """Comoving volume per arcmin^2 between the redshifts of ``z_range`` [Mpc^3]."""
    cosmo = _cosmology(cosmology)
    zz, cv, _, _ = _tables(lambda M: np.ones_like(M), z_range, (0.0, 1.0), cosmo)
    return float(cv[-1] * _ARCMIN2_SR)


def expected_number(lf, z_range, M_range, area_arcmin2: float, cosmology="Planck18") -> float:
    """Mean number of sources, Omega int dV/dz/dOmega dz int phi dM, for a non-evolving phi."""
    cosmo = _cosmology(cosmology)
    _, cv, _, cp = _tables(lf, z_range, M_range, cosmo)
    return float(area_arcmin2) * _ARCMIN2_SR * cv[-1] * cp[-1]


def _inverse_cdf(rng, x, cum, n):
    u = rng.random(n) * cum[-1]
    return np.interp(u, cum, x)


def _band_setup(cfg):
    """(band names, resolved filters, zeropoints, gains, detection index)."""
    from ..fieldprep import resolve_filter

    bands = tuple(b.name for b in cfg.survey.bands)
    filters = [resolve_filter(b.filter, cfg.base_dir) for b in cfg.survey.bands]
    zps = {b.name: float(b.zeropoint) for b in cfg.survey.bands}
    gains = {b.name: (None if b.gain is None else float(b.gain)) for b in cfg.survey.bands}
    return bands, filters, zps, gains, bands.index(cfg.survey.detection_band)


def draw_mock_population(rng: np.random.Generator, lf, z_range, M_range, area_arcmin2, cfg,
                         *, pixel_scale_arcsec: float | None = None,
                         z_step: float | None = None) -> pd.DataFrame:
    """Galaxies of a luminosity function over the volume of a survey.

    Parameters
    ----------
    rng : numpy.random.Generator
    lf : callable
        phi(M) [Mpc^-3 mag^-1] (e.g. :class:`Schechter`); not evolving with z.
    z_range : (float, float)
        Redshift range.
    M_range : (float, float)
        (M_bright, M_faint), absolute UV magnitudes at rest 1600 A.
    area_arcmin2 : float or mapping of field name to float
        Solid angle [arcmin^2]; a mapping draws each field's sources (Poisson with the
        field's own mean), in the mapping's order.  A float gives field ``""``.
    cfg : glaciar.config.Config
        The survey's configuration: its bands (filters, detection band), source model
        (beta, shapes, sizes, IGM, cosmology).
    pixel_scale_arcsec : float, optional
        Image pixel scale; with it, ``r_eff_pix`` is on the injections' template lattice
        and ``r_eff_arcsec`` follows from it (as in the injections).
    z_step : float, optional
        Round each redshift to the nearest multiple of ``z_step`` (inside ``z_range``):
        the redshifts then take lattice values with probabilities equal to the comoving
        volume of each lattice cell (the midpoint rule of the continuous distribution).
        With 0.01 (``glaciar.galaxy.sed.Z_LATTICE_STEP``) the band magnitudes come from
        the exact, cached band tables of the lattice instead of one exact table per
        source where the IGM enters a band (~15 ms each): ~0.5 ms per source once
        the lattice is cached, against ~60 ms.  Effect on any count: the midpoint
        rule's error, (dz^2 / 24) P''/P ~ 1e-5 relative for a selection that turns on
        over dz ~ 0.3.

    Returns
    -------
    pandas.DataFrame
        One row per galaxy: ``field``, ``z``, ``M_uv``, ``beta``, ``sersic_n``,
        ``axis_ratio``, ``position_angle_deg``, ``r_eff_kpc``, ``r_eff_arcsec``,
        (``r_eff_pix``), ``mag_in_<band>`` per band (+inf: no flux).
        ``attrs``: ``n_expected`` {field: mean number}, ``lf``, ``z_range``,
        ``M_range``, ``area_arcmin2`` {field: area}.
    """
    from ..engine.context import FieldContext
    from ..galaxy import population, sed

    areas = dict(area_arcmin2) if hasattr(area_arcmin2, "items") else {"": float(area_arcmin2)}
    cosmo = _cosmology(cfg)
    model = population.SourceModel(**cfg.source.model_dump())
    model = dataclasses.replace(model, beta_per="source")
    bands, filters, _, _, _ = _band_setup(cfg)
    zz, cv, MM, cp = _tables(lf, z_range, M_range, cosmo)
    per_sr = cv[-1] * cp[-1]
    frames, n_exp = [], {}
    for field, area in areas.items():
        if not (math.isfinite(float(area)) and float(area) >= 0):
            raise ValueError(f"area of field {field!r} must be >= 0, got {area!r}")
        mu = float(area) * _ARCMIN2_SR * per_sr
        n_exp[field] = mu
        n = int(rng.poisson(mu))
        z = _inverse_cdf(rng, zz, cv, n)
        if z_step is not None:
            step = float(z_step)
            z = np.round(np.clip(np.round(z / step) * step, zz[0], zz[-1]), 10)
        M = _inverse_cdf(rng, MM, cp, n)
        beta = population.draw_beta(rng, n, model)
        shapes = population.draw_shapes(rng, n, model)
        r_kpc = population.r_eff_kpc(z, model, M_uv=M, rng=rng) * np.ones(n)
        r_arcsec = population.kpc_to_arcsec(r_kpc, z, cosmo) if n else np.zeros(0)
        cols = {"field": np.full(n, field, dtype=object), "z": z, "M_uv": M, "beta": beta,
                "sersic_n": shapes["sersic_n"], "axis_ratio": shapes["axis_ratio"],
                "position_angle_deg": shapes["position_angle_deg"], "r_eff_kpc": r_kpc}
        if pixel_scale_arcsec is not None:
            r_pix = FieldContext.quantise_r_eff(r_arcsec / float(pixel_scale_arcsec))
            cols["r_eff_pix"] = r_pix
            r_arcsec = r_pix * float(pixel_scale_arcsec)
        cols["r_eff_arcsec"] = np.asarray(r_arcsec, dtype=float)
        mags = np.empty((n, len(bands)))
        for i in range(n):
            mags[i] = sed.band_magnitudes(float(z[i]), beta[i:i + 1], filters, M_uv=M[i:i + 1],
                                          cosmology=cosmo, igm=model.igm)[0]
        for j, b in enumerate(bands):
            cols[f"mag_in_{b}"] = mags[:, j]
        frames.append(pd.DataFrame(cols))
    out = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    out.attrs.update(n_expected=n_exp, area_arcmin2=areas, z_range=tuple(map(float, z_range)),
                     M_range=tuple(map(float, M_range)),
                     lf=(lf.as_dict() if hasattr(lf, "as_dict") else repr(lf)))
    return out


def field_footprints(cfg) -> dict:
    """{field: (footprint bool array, pixel scale [arcsec])}: where the run places sources."""
    from ..survey import Survey

    survey = Survey.from_config(cfg)
    return {f: (np.asarray(survey.footprint(f)), float(survey.pixel_scale_arcsec(f)))
            for f in survey.fields}


def place_sources(rng: np.random.Generator, footprint: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) [pixels] uniform over the footprint's pixels, uniform inside each pixel."""
    iy, ix = np.nonzero(footprint)
    if n and not iy.size:
        raise ValueError("place_sources: the footprint is empty")
    k = rng.integers(0, iy.size, size=int(n))
    u = rng.random((2, int(n))) - 0.5
    return ix[k] + u[0], iy[k] + u[1]


def render_sources(science: np.ndarray, cache, band: str, sources: pd.DataFrame, zeropoint: float,
                   gain: float | None, rng: np.random.Generator,
                   valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Add sources to one band's image (numpy in and out).

    Parameters
    ----------
    science : ndarray (ny, nx)
        The band's image [image units]; not modified.
    cache : glaciar.galaxy.templates.TemplateCache
        Holds the band's PSF.
    band : str
    sources : DataFrame
        Columns ``x``, ``y``, ``sersic_n``, ``axis_ratio``, ``position_angle_deg``,
        ``r_eff_pix`` and ``mag_in_<band>``.
    zeropoint : float
        AB magnitude of one image unit.
    gain : float or None
        Electrons per image unit: each stamp pixel's model m becomes Poisson(g m) / g
        (model clipped at 0 for the draw).  None or inf: no shot noise.
    rng : numpy.random.Generator
        Draws the shot noise (one Poisson array per stamp, in the sources' order).
    valid : bool ndarray (ny, nx), optional
        Pixels that may receive light (default: all).

    Returns
    -------
    image : ndarray float64
        ``science`` plus the sources.
    added : ndarray (n,)
        Noise-free flux each source put into the image (stamp sum inside the image and
        ``valid``) [image units].
    """
    from ..galaxy import sed

    img = np.array(science, dtype=np.float64, copy=True)
    ny, nx = img.shape
    mags = np.asarray(sources[f"mag_in_{band}"], dtype=float)
    flux = sed.mag_to_flux(mags, zeropoint) * np.ones(len(mags))
    skip = sed.bands_to_skip(mags) if len(mags) else np.zeros(0, bool)
    noisy = gain is not None and math.isfinite(float(gain))
    added = np.zeros(len(mags))
    cols = [np.asarray(sources[c], dtype=float) for c in
            ("sersic_n", "axis_ratio", "position_angle_deg", "r_eff_pix", "x", "y")]
    for i in np.flatnonzero(~np.asarray(skip, bool)):
        ps = cache.stamp(band, *(float(c[i]) for c in cols))
        h, w = ps.data.shape
        ya, xa = max(ps.y0, 0), max(ps.x0, 0)
        yb, xb = min(ps.y0 + h, ny), min(ps.x0 + w, nx)
        if ya >= yb or xa >= xb:
            continue
        model = flux[i] * ps.data[ya - ps.y0:yb - ps.y0, xa - ps.x0:xb - ps.x0]
        if valid is not None:
            model = np.where(valid[ya:yb, xa:xb], model, 0.0)
        added[i] = float(model.sum())
        if noisy:
            g = float(gain)
            lam = np.clip(model, 0.0, None) * g
            model = model + (rng.poisson(lam) - lam) / g
        img[ya:yb, xa:xb] += model
    return img, added


def _read_fits(path: Path):
    from astropy.io import fits

    with fits.open(path, memmap=False) as hdul:
        for hdu in hdul:
            if hdu.data is not None and hdu.data.ndim == 2:
                return np.array(hdu.data), hdul[0].header.copy(), hdu.header.copy()
    raise ValueError(f"{path}: no 2-d image")


def render_mock_universe(cfg_path, truth: pd.DataFrame, seed: int, *,
                         truth_path=None) -> Path:
    """Place ``truth``'s galaxies in their fields and add them to the science images.

    Parameters
    ----------
    cfg_path : path-like
        The survey's config (images, bands, PSFs, gains).
    truth : DataFrame
        From :func:`draw_mock_population` (with ``pixel_scale_arcsec``, i.e. ``r_eff_pix``);
        its ``field`` values must be fields of the config.  Positions are drawn here
        (uniform over each field's footprint) unless ``x`` and ``y`` are given.
    seed : int
        Seeds the positions and the shot noise (one stream per field, keyed by its name).
    truth_path : path-like, optional
        Where to write the truth table (default ``<config dir>/mock_truth.parquet``).

    Returns
    -------
    pathlib.Path
        The truth table (Parquet): the input columns plus ``x``, ``y`` [pixels, 0-based],
        ``flux_in_<band>`` (total) and ``flux_added_<band>`` (inside the image and the
        data, noise-free) [image units]; metadata ``glaciar_mock`` (JSON: seed, LF,
        ranges, areas, expected numbers).

    Raises
    ------
    ValueError
        A field of ``truth`` not in the config, or an image already holding a mock
        universe (header ``MOCKSEED``).
    """
    import json

    from astropy.io import fits

    from ..config import load_config
    from ..engine.task import field_key
    from ..galaxy import sed
    from ..galaxy.templates import TemplateCache
    from ..galaxy.population import SourceModel
    from ..fieldprep import band_psf
    from ..rundir import atomic_write_bytes
    from ..survey import Survey

    cfg_path = Path(cfg_path)
    cfg = load_config(cfg_path)
    survey = Survey.from_config(cfg)
    bands, _, zps, gains, _ = _band_setup(cfg)
    unknown = sorted(set(truth["field"]) - set(survey.fields)) if len(truth) else []
    if unknown:
        raise ValueError(f"render_mock_universe: fields {unknown} are not in {cfg_path}")
    model = SourceModel(**cfg.source.model_dump())
    truth = truth.copy()
    attrs = dict(truth.attrs)
    have_xy = {"x", "y"} <= set(truth.columns)
    if not have_xy:
        truth["x"] = np.nan
        truth["y"] = np.nan
    for b in bands:
        truth[f"flux_in_{b}"] = sed.mag_to_flux(truth[f"mag_in_{b}"].to_numpy(float), zps[b]) \
            if len(truth) else np.zeros(0)
        truth[f"flux_added_{b}"] = 0.0
    for field in survey.fields:
        rows = np.flatnonzero(truth["field"].to_numpy() == field) if len(truth) else np.zeros(0, int)
        streams = np.random.SeedSequence(int(seed), spawn_key=(field_key(field),)).spawn(1 + len(bands))
        pixscale = survey.pixel_scale_arcsec(field)
        if not have_xy:
            x, y = place_sources(np.random.default_rng(streams[0]), survey.footprint(field), rows.size)
            truth.loc[truth.index[rows], "x"] = x
            truth.loc[truth.index[rows], "y"] = y
        if "r_eff_pix" not in truth.columns:
            raise ValueError("render_mock_universe: truth needs r_eff_pix (draw it with pixel_scale_arcsec)")
        cache = TemplateCache({b.name: band_psf(cfg, b, pixscale) for b in cfg.survey.bands},
                              enclosed_fraction=model.stamp_flux_fraction)
        sub = truth.iloc[rows]
        for k, b in enumerate(bands):
            path = survey.science_path(field, b)
            data, phead, head = _read_fits(path)
            if "MOCKSEED" in head or "MOCKSEED" in phead:
                raise ValueError(f"{path} already holds a mock universe (MOCKSEED = "
                                 f"{head.get('MOCKSEED', phead.get('MOCKSEED'))}); rebuild the survey")
            npath = survey.noise_path(field, b)
            valid = (_read_fits(npath)[0] > 0) if npath is not None else np.isfinite(data)
            valid &= np.isfinite(data)
            img, added = render_sources(data, cache, b, sub, zps[b], gains[b],
                                        np.random.default_rng(streams[1 + k]), valid=valid)
            truth.loc[truth.index[rows], f"flux_added_{b}"] = added
            head["MOCKSEED"] = (int(seed), "glaciar.demo.mock: mock galaxies added")
            head["MOCKN"] = (int(rows.size), "number of mock galaxies in this field")
            out = np.where(valid, img, data).astype(data.dtype if data.dtype.kind == "f" else np.float32)
            buf = _fits_bytes(out, head)
            atomic_write_bytes(path, buf)
    truth_path = Path(truth_path) if truth_path is not None else cfg_path.parent / MOCK_TRUTH_NAME
    meta = {"seed": int(seed), "config": str(cfg_path)}
    meta.update({k: (v if not isinstance(v, tuple) else list(v)) for k, v in attrs.items()})
    _write_table(truth, truth_path, meta)
    return truth_path


def _fits_bytes(data: np.ndarray, header) -> bytes:
    import io

    from astropy.io import fits

    buf = io.BytesIO()
    fits.PrimaryHDU(data=data, header=header).writeto(buf)
    return buf.getvalue()


def _write_table(df: pd.DataFrame, path: Path, meta: dict) -> None:
    """Parquet with ``meta`` (JSON) in the schema metadata, written atomically."""
    import io
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    from ..rundir import atomic_write_bytes

    df = df.copy()
    df.attrs = {}
    table = pa.Table.from_pandas(df, preserve_index=False)
    md = dict(table.schema.metadata or {})
    md[b"glaciar_mock"] = json.dumps(meta, default=str).encode()
    table = table.replace_schema_metadata(md)
    buf = io.BytesIO()
    pq.write_table(table, buf)
    atomic_write_bytes(path, buf.getvalue())


def read_truth(path) -> pd.DataFrame:
    """The truth table written by :func:`render_mock_universe` (``attrs``: its metadata)."""
    import json

    import pyarrow.parquet as pq

    table = pq.read_table(path)
    df = table.to_pandas()
    raw = (table.schema.metadata or {}).get(b"glaciar_mock")
    df.attrs.update(json.loads(raw) if raw else {})
    return df


def build_mock_survey(out_dir, *, n_fields: int = 4, shape=(1000, 1000), seed: int = 2018,
                      prefix: str = "mock", config_updates: dict | None = None,
                      **demo_kw) -> Path:
    """Write ``n_fields`` demo fields into ``out_dir`` and one config listing them all.

    Field k (0-based) is named ``f"{prefix}{k + 1:02d}"`` and built by
    :func:`glaciar.demo.build_demo_survey` with image seed ``seed + k`` (different
    background sources and noise per field).  The config is the demo's, with
    ``survey.fields`` listing every field, written as ``out_dir/mock.yaml``;
    ``config_updates`` ({section: {key: value}}) replaces keys of sections (e.g.
    ``{"grid": {...}, "simulation": {"n_iterations": 4}}``; a value ``None`` removes the key).

    Returns
    -------
    pathlib.Path
        The config path.
    """
    import yaml

    from ..rundir import atomic_write_text
    from .survey import config_dumper, build_demo_survey

    out_dir = Path(out_dir)
    if int(n_fields) < 1:
        raise ValueError(f"n_fields must be >= 1, got {n_fields}")
    fields = [f"{prefix}{k + 1:02d}" for k in range(int(n_fields))]
    last = None
    for k, f in enumerate(fields):
        last = build_demo_survey(out_dir, shape=tuple(shape), seed=int(seed) + k, field=f, **demo_kw)
    cfg = yaml.safe_load(Path(last).read_text())
    cfg["survey"]["fields"] = fields
    for section, upd in (config_updates or {}).items():
        sec = cfg.setdefault(section, {})
        for key, value in upd.items():
            if value is None:
                sec.pop(key, None)
            else:
                sec[key] = value
    path = out_dir / MOCK_CONFIG_NAME
    head = (f"# glaciar mock universe survey: {len(fields)} demo fields ({', '.join(fields)}), "
            f"{shape[1]} x {shape[0]} px, image seeds {seed}..{int(seed) + len(fields) - 1}.\n"
            "# Written by glaciar.demo.mock.build_mock_survey; paths relative to this file.\n")
    atomic_write_text(path, head + yaml.dump(cfg, Dumper=config_dumper(), sort_keys=False,
                                             default_flow_style=False, width=100))
    try:
        Path(last).unlink()            # demo.yaml describes only the last field
    except FileNotFoundError:
        pass
    return path
