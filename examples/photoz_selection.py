"""Example selection function for glaciar: a small template-fitting photo-z cut.

This is an EXAMPLE of ``selection: {function: ...}`` (docs/configuration.md), written to
show the interface and to test it -- it is NOT a photometric-redshift code.  Its
templates are a handful of analytic shapes, not stellar-population models; use EAZY-py,
LePhare, BAGPIPES, ... for science (docs/configuration.md shows how to wrap one).

What it does, per source:

* templates (rest-frame f_lambda, all behind the mean IGM of
  :func:`glaciar.galaxy.igm.igm_transmission` at the trial z):
  - star-forming UV power laws f_lambda ~ lambda^beta, beta = -2.6 ... -1.4 (the
    spectra glaciar injects, :func:`glaciar.galaxy.sed.uv_flambda`: the high-z solutions),
  - dusty power laws, beta = -0.5, 0.5, 1.5 (red low-z interlopers),
  - Balmer/4000 A-break continua: f_lambda ~ lambda^beta_red above 4000 A, a step down
    by a factor D (2 or 3.5) across 3650-4000 A, and lambda^+1.5 below (old, quiescent
    low-z interlopers; the break is a crude stand-in for real stellar populations);
* chi^2(z, t) = sum_b (F_b - a F_b^model(z, t))^2 / sigma_b^2 with the best amplitude
  a >= 0 (analytic), errors with a fractional floor added in quadrature;
* P(z) ~ sum_t exp(-chi^2(z, t) / 2) on a uniform z grid (flat priors);
* selected when P(z > z_cut) > p_min (and, optionally, S/N >= min_sn in one band).

The survey's bands are given in the configuration (the table holds only measured
columns): ``filters`` maps each band to a filter name or file glaciar reads, and
``zeropoints`` to its AB zeropoint (the same as in ``survey.bands``).

Use it (examples/photoz_selection.yaml)::

    selection:
      function: photoz_selection:select
      kwargs: {filters: {f160w: wfc3_ir_f160w, ...}, zeropoints: {f160w: 25.946, ...},
               z_cut: 7.0, p_min: 0.7}

with this directory on ``PYTHONPATH`` (``PYTHONPATH=examples glaciar simulate ...``).
"""
from __future__ import annotations

import functools

import numpy as np

from glaciar.constants import LYA_REST_ANGSTROM, UV_REST_ANGSTROM
from glaciar.galaxy.filters import get_filter
from glaciar.galaxy.igm import igm_transmission

#: Declared version: glaciar puts it in the run's identity.  Change it whenever the
#: selection's result may change (templates, defaults), so an old run is not resumed.
glaciar_selection_version = "1"

#: UV slopes of the star-forming templates, and of the dusty ones.
BETAS_STAR_FORMING = (-2.6, -2.2, -1.8, -1.4)
BETAS_DUSTY = (-0.5, 0.5, 1.5)
#: (break factor D, slope redward of 4000 A) of the Balmer-break templates.
BALMER_BREAKS = ((2.0, -1.0), (3.5, 0.0))
BALMER_EDGES_ANGSTROM = (3650.0, 4000.0)
BALMER_BLUE_SLOPE = 1.5
#: Samples per filter curve in the band integrals.
N_FILTER_SAMPLES = 400
#: Rows fitted at once (memory: rows x templates x z values x 8 bytes x ~4).
CHUNK_ROWS = 2000


def _balmer_flambda(wave_rest: np.ndarray, break_factor: float, red_slope: float) -> np.ndarray:
    """Rest-frame f_lambda of a break template (1 at 4000 A), log-linear across the break."""
    lo, hi = BALMER_EDGES_ANGSTROM
    red = (wave_rest / hi) ** red_slope
    blue = (wave_rest / lo) ** BALMER_BLUE_SLOPE / break_factor
    t = np.clip(np.log(wave_rest / lo) / np.log(hi / lo), 0.0, 1.0)
    ramp = np.exp((1 - t) * np.log(1.0 / break_factor) + t * np.log((wave_rest / hi) ** red_slope))
    return np.where(wave_rest >= hi, red, np.where(wave_rest <= lo, blue, ramp))


def template_names() -> tuple[str, ...]:
    """Names of the templates, in the order of :func:`template_fluxes`' second axis."""
    return (tuple(f"uv_beta{b:+.1f}" for b in BETAS_STAR_FORMING)
            + tuple(f"dusty_beta{b:+.1f}" for b in BETAS_DUSTY)
            + tuple(f"balmer_D{d:g}_beta{s:+.1f}" for d, s in BALMER_BREAKS))


@functools.lru_cache(maxsize=8)
def template_fluxes(filters: tuple[str, ...], z_grid: tuple[float, ...],
                    igm: str = "inoue14") -> np.ndarray:
    """Band-mean f_nu of every template at every trial redshift (arbitrary units).

    Parameters
    ----------
    filters : tuple of str
        Filter names or files (:func:`glaciar.galaxy.filters.get_filter`), one per band.
    z_grid : tuple of float
        Trial redshifts.
    igm : str
        IGM model of :func:`glaciar.galaxy.igm.igm_transmission`.

    Returns
    -------
    numpy.ndarray
        Shape (n_z, n_templates, n_bands): <f_nu> = int f_lambda T lambda dlambda /
        int T c / lambda dlambda, with c and the normalisation dropped (the fit scales
        each template freely).
    """
    z = np.asarray(z_grid, dtype=float)
    out = np.empty((z.size, len(template_names()), len(filters)))
    for j, name in enumerate(filters):
        filt = get_filter(name)
        wave = np.linspace(filt.wave_angstrom[0], filt.wave_angstrom[-1], N_FILTER_SAMPLES)
        thr = np.interp(wave, filt.wave_angstrom, filt.throughput)
        norm = np.trapezoid(thr / wave, wave)
        rest = wave[None, :] / (1.0 + z[:, None])                          # (n_z, n_wave)
        # The IGM is exactly 1 redward of rest Lyman alpha: evaluated only blueward.
        igm_t = np.ones(rest.shape)
        blue = rest < LYA_REST_ANGSTROM
        zz = np.broadcast_to(z[:, None], rest.shape)
        igm_t[blue] = igm_transmission(np.broadcast_to(wave, rest.shape)[blue], zz[blue], igm)
        # uv_flambda's power law x IGM (glaciar.galaxy.sed), all z at once.
        shapes = [igm_t * (rest / UV_REST_ANGSTROM) ** b for b in BETAS_STAR_FORMING]
        shapes += [igm_t * (rest / UV_REST_ANGSTROM) ** b for b in BETAS_DUSTY]
        shapes += [igm_t * _balmer_flambda(rest, d, s) for d, s in BALMER_BREAKS]
        for t, f_lambda in enumerate(shapes):
            out[:, t, j] = np.trapezoid(f_lambda * thr * wave, wave, axis=-1) / norm
    return out


def photoz(table, *, filters, zeropoints, z_min=0.1, z_max=15.0, z_step=0.1,
           flux="flux_iso", error_floor=0.05, igm="inoue14"):
    """P(z) of every row of a glaciar selection table.

    Parameters
    ----------
    table : mapping of str -> ndarray
        ``<flux>_<band>`` and ``<flux>err_<band>`` columns, e.g. ``flux_iso_f160w`` and
        ``fluxerr_iso_f160w`` [image units].
    filters : mapping band -> str
        Filter name or file of every band used.
    zeropoints : mapping band -> float
        AB zeropoints [mag] of the bands (image units -> f_nu).
    z_min, z_max, z_step : float
        The uniform trial grid.
    flux : str
        Which photometry: ``flux_iso`` (default), ``flux_auto``, ``flux_aper0``, ...
    error_floor : float
        Fractional error added in quadrature (template mismatch).
    igm : str

    Returns
    -------
    z_grid : ndarray, shape (n_z,)
    pz : ndarray, shape (n_rows, n_z)
        Normalised P(z) (rows without any usable band: uniform).
    """
    bands = list(filters)
    z_grid = np.round(np.arange(z_min, z_max + 0.5 * z_step, z_step), 6)
    model = template_fluxes(tuple(str(filters[b]) for b in bands), tuple(z_grid), igm)
    n_z, n_t, n_b = model.shape
    model = model.reshape(n_z * n_t, n_b)
    err_name = flux.replace("flux_", "fluxerr_", 1)
    scale = np.array([10.0 ** (-0.4 * float(zeropoints[b])) for b in bands])   # -> f_nu units
    f = np.column_stack([np.asarray(table[f"{flux}_{b.lower()}"], float) for b in bands]) * scale
    e = np.column_stack([np.asarray(table[f"{err_name}_{b.lower()}"], float) for b in bands]) * scale
    good = np.isfinite(f) & np.isfinite(e) & (e > 0)
    f = np.where(good, f, 0.0)
    var = np.where(good, e ** 2 + (error_floor * np.abs(f)) ** 2, np.inf)
    w = 1.0 / var                                                           # 0 where unusable
    pz = np.empty((f.shape[0], n_z))
    for lo in range(0, f.shape[0], CHUNK_ROWS):
        fw, ww = f[lo:lo + CHUNK_ROWS] * w[lo:lo + CHUNK_ROWS], w[lo:lo + CHUNK_ROWS]
        num = fw @ model.T                                                  # sum F s / var
        den = ww @ (model ** 2).T                                           # sum s^2 / var
        with np.errstate(invalid="ignore", divide="ignore"):
            gain = np.where((num > 0) & (den > 0), num ** 2 / den, 0.0)   # amplitude a >= 0
        chi2 = (fw * f[lo:lo + CHUNK_ROWS]).sum(axis=1)[:, None] - gain
        chi2 = chi2.reshape(-1, n_z, n_t)
        like = np.exp(-0.5 * (chi2 - chi2.min(axis=(1, 2), keepdims=True)))
        pz[lo:lo + CHUNK_ROWS] = like.sum(axis=2)
    pz /= pz.sum(axis=1, keepdims=True)
    return z_grid, pz


def select(table, *, filters, zeropoints, z_cut=7.0, p_min=0.7, sn_band=None, min_sn=0.0,
           **fit):
    """glaciar selection function: P(z > z_cut) > p_min (and S/N >= min_sn in sn_band).

    Parameters
    ----------
    table : mapping of str -> ndarray
        The table glaciar passes (docs/configuration.md).
    filters, zeropoints : mapping band -> str / float
        See :func:`photoz`.
    z_cut : float
        Redshift threshold.
    p_min : float
        Least integrated probability above ``z_cut``.
    sn_band : str, optional
        Band whose ``sn_<band>`` must reach ``min_sn``.
    **fit
        Further arguments of :func:`photoz`.

    Returns
    -------
    ndarray of bool
    """
    z_grid, pz = photoz(table, filters=filters, zeropoints=zeropoints, **fit)
    chosen = pz[:, z_grid > z_cut].sum(axis=1) > p_min
    if sn_band is not None:
        with np.errstate(invalid="ignore"):
            chosen &= np.asarray(table[f"sn_{sn_band.lower()}"], float) >= min_sn
    return chosen
