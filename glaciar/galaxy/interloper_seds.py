"""Built-in spectra of low-redshift interlopers, and their magnitudes in many bands.

Two parametric families, generated here (no template files, no downloads):

``dusty``
    A star-forming continuum f_lambda ∝ lambda^beta behind a Calzetti et al. (2000)
    starburst attenuation law: f_lambda = (lambda / 1600 A)^beta 10^(-0.4 A_V k(lambda) / R_V),
    R_V = 4.05 (:func:`calzetti_k`).
``balmer``
    A quiescent / post-starburst continuum with a 4000 A (Balmer) break:
    f_lambda ∝ (lambda / 4000 A)^beta_red redward of ``BREAK_ANGSTROM`` and
    s (lambda / 4000 A)^beta_blue blueward, the step s set so that the break strength
    D4000 of Bruzual (1983) -- the mean f_nu over 4050-4250 A over the mean f_nu over
    3750-3950 A (:func:`d4000`) -- equals the requested value (optionally also attenuated
    by the Calzetti law).  A two-slope step, not a stellar-population model: it carries
    the break that makes such galaxies drop out, not their line indices.

Both are zero below the Lyman limit (912 A rest: galaxies are opaque to ionising
photons), and the IGM (:func:`glaciar.galaxy.igm.igm_transmission`) acts on the observed
spectrum as it does on the high-z sources.

Accuracy (tests/galaxy/test_interloper_seds.py): :func:`calzetti_k` is the published
formula (Calzetti et al. 2000, eq. 4) inside 0.12-2.2 micron, k(V) = 4.05 within 0.1 %,
k(B) - k(V) = 1 within 2 % (the definition of E(B-V)); beyond the formula's range it is
continued linearly in 1/lambda with the slope at the edge (a common choice; the UV end
matters for z > 5 interlopers in blue bands only).  The D4000 measured on the template
equals the configured value to < 1e-5 relative.  Band magnitudes: trapezoid rule on a
grid of step d ln lambda = 2e-3 over the filter, with nodes either side of every jump (IGM
edges, the Lyman limit, the break); against :func:`glaciar.galaxy.filters.ab_magnitude` on
a fine grid < 5e-4 mag (measured: 3e-4 at z = 1-5.5 in HST and NIRCam bands).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from glaciar.constants import FAINT_MAG_LIMIT, LYA_REST_ANGSTROM
from glaciar.galaxy.filters import Filter, get_filter
from glaciar.galaxy.igm import igm_discontinuities, igm_transmission

__all__ = ["CALZETTI_RV", "BREAK_ANGSTROM", "D4000_BLUE", "D4000_RED", "LYMAN_LIMIT_ANGSTROM",
           "FAMILIES", "calzetti_k", "d4000", "balmer_step", "rest_flambda",
           "InterloperParams", "interloper_band_magnitudes", "number_counts", "number_counts_integral"]

#: Total-to-selective attenuation of the Calzetti et al. (2000) law.
CALZETTI_RV = 4.05
#: Rest wavelength of the template's break [Angstrom] (between the two D4000 windows).
BREAK_ANGSTROM = 4000.0
#: Bruzual (1983) D4000 windows [Angstrom]: blue and red continuum bands.
D4000_BLUE = (3750.0, 3950.0)
D4000_RED = (4050.0, 4250.0)
#: No flux below this rest wavelength [Angstrom].
LYMAN_LIMIT_ANGSTROM = 911.75
#: The built-in families.
FAMILIES = ("dusty", "balmer")

# Calzetti et al. (2000) eq. 4 (lambda in micron).
_CAL_UV = (0.12, 0.63)
_CAL_IR = (0.63, 2.20)
_LN10_OVER_2P5 = np.log(10.0) / 2.5
# Quadrature step in ln(lambda): the spectra are smooth between the nodes added at every
# jump (IGM edges, the Lyman limit, the break), so 2e-3 is < 1e-3 mag (tested).
_DLNLAM = 2e-3


def _k_formula(lam_um):
    x = 1.0 / lam_um
    uv = 2.659 * (-2.156 + 1.509 * x - 0.198 * x ** 2 + 0.011 * x ** 3) + CALZETTI_RV
    ir = 2.659 * (-1.857 + 1.040 * x) + CALZETTI_RV
    return np.where(lam_um < _CAL_IR[0], uv, ir)


def _k_slope(lam_um):
    """dk / d(1/lambda) of the formula [micron]."""
    x = 1.0 / lam_um
    uv = 2.659 * (1.509 - 2 * 0.198 * x + 3 * 0.011 * x ** 2)
    ir = 2.659 * 1.040
    return np.where(lam_um < _CAL_IR[0], uv, ir)


def calzetti_k(wave_rest_angstrom) -> np.ndarray:
    """Calzetti et al. (2000) attenuation curve k(lambda) = A(lambda) / E(B-V)_star.

    Parameters
    ----------
    wave_rest_angstrom : array_like
        Rest-frame wavelengths [Angstrom] (> 0).

    Returns
    -------
    numpy.ndarray
        k(lambda) (dimensionless; A(lambda) = A_V k(lambda) / R_V).  The published
        formula inside 0.12-2.2 micron; beyond it continued linearly in 1/lambda with the
        edge's slope, and never below 0.
    """
    lam = np.asarray(wave_rest_angstrom, dtype=float) / 1e4
    inside = np.clip(lam, _CAL_UV[0], _CAL_IR[1])
    edge = np.where(lam < _CAL_UV[0], _CAL_UV[0], _CAL_IR[1])
    out = _k_formula(inside)
    beyond = (lam < _CAL_UV[0]) | (lam > _CAL_IR[1])
    ext = _k_formula(edge) + _k_slope(edge) * (1.0 / lam - 1.0 / edge)
    return np.maximum(np.where(beyond, ext, out), 0.0)


def _window_mean_fnu(wave, flam, window):
    """Mean f_nu (∝ lambda^2 f_lambda) over ``window`` [A], trapezoid on ``wave``."""
    lo, hi = window
    sel = (wave >= lo) & (wave <= hi)
    w = wave[sel]
    return np.trapezoid(flam[..., sel] * w ** 2, w, axis=-1) / (hi - lo)


# Gauss-Legendre nodes (24 per window) for the step: the windows' integrands are smooth
# (the break lies between them), so this is exact to ~1e-12.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(24)


def _gl(window):
    lo, hi = window
    return 0.5 * (hi - lo) * _GL_X + 0.5 * (hi + lo), 0.5 * (hi - lo) * _GL_W


def d4000(wave_rest_angstrom, flambda) -> np.ndarray:
    """Break strength D4000 (Bruzual 1983) of rest-frame spectra.

    The mean f_nu over 4050-4250 A divided by the mean f_nu over 3750-3950 A, the
    means taken over wavelength (trapezoid rule on the spectrum's own samples inside
    each window).

    Parameters
    ----------
    wave_rest_angstrom : array_like (M,)
        Rest wavelengths [Angstrom], increasing, sampling both windows.
    flambda : array_like (..., M)
        f_lambda (any units).
    """
    w = np.asarray(wave_rest_angstrom, float)
    f = np.asarray(flambda, float)
    return _window_mean_fnu(w, f, D4000_RED) / _window_mean_fnu(w, f, D4000_BLUE)


def _dust(wave_rest, a_v):
    a_v = np.asarray(a_v, float)
    return 10.0 ** (-0.4 * a_v[..., None] * calzetti_k(wave_rest) / CALZETTI_RV)


def balmer_step(d4000_value, beta_blue, beta_red, a_v=0.0) -> np.ndarray:
    """The step s of the ``balmer`` template that gives the break strength ``d4000_value``.

    D4000 is linear in 1/s, so s = D(s = 1) / D4000 (the window means of D(s = 1) by
    24-point Gauss-Legendre quadrature: the integrands are smooth inside each window).
    """
    d, bb, br, av = np.broadcast_arrays(*(np.asarray(v, float) for v in
                                          (d4000_value, beta_blue, beta_red, a_v)))
    means = []
    for window in (D4000_RED, D4000_BLUE):
        lam, w = _gl(window)
        flam = _two_slopes(lam, bb, br, np.ones_like(d)) * _dust(lam, av)
        means.append((flam * lam ** 2) @ w)
    return means[0] / means[1] / d


def _two_slopes(wave_rest, beta_blue, beta_red, step):
    x = np.log(np.asarray(wave_rest, float) / BREAK_ANGSTROM)
    bb = np.asarray(beta_blue, float)[..., None]
    br = np.asarray(beta_red, float)[..., None]
    s = np.asarray(step, float)[..., None]
    return np.where(x < 0, s * np.exp(bb * x), np.exp(br * x))


@dataclass(frozen=True)
class InterloperParams:
    """Spectral parameters of N interlopers (arrays of length N).

    Attributes
    ----------
    family : ndarray of str
        ``"dusty"`` or ``"balmer"`` per source.
    beta : ndarray
        UV slope (dusty) or the slope blueward of the break (balmer), f_lambda ∝ lambda^beta.
    beta_red : ndarray
        Slope redward of the break (balmer; ignored for dusty).
    a_v : ndarray
        V-band attenuation [mag] (Calzetti law).
    d4000 : ndarray
        Break strength (balmer; NaN for dusty).
    """

    family: np.ndarray
    beta: np.ndarray
    beta_red: np.ndarray
    a_v: np.ndarray
    d4000: np.ndarray


def rest_flambda(wave_rest_angstrom, params: InterloperParams) -> np.ndarray:
    """Rest-frame f_lambda (unnormalised) of each source, shape (N, M)."""
    w = np.asarray(wave_rest_angstrom, float)
    fam = np.asarray(params.family)
    beta = np.asarray(params.beta, float)
    dusty = fam == "dusty"
    out = np.empty((fam.size, w.size))
    if dusty.any():
        out[dusty] = np.exp(beta[dusty, None] * np.log(w / 1600.0)[None, :])
    bal = ~dusty
    if bal.any():
        s = balmer_step(params.d4000[bal], beta[bal], params.beta_red[bal], params.a_v[bal])
        out[bal] = _two_slopes(w, beta[bal], params.beta_red[bal], s)
    out *= _dust(w, params.a_v)
    out[:, w < LYMAN_LIMIT_ANGSTROM] = 0.0
    return out


@dataclass(frozen=True)
class _Quadrature:
    wave: np.ndarray      # observed wavelengths of the nodes [A]
    u: np.ndarray         # w_i T_i T_IGM,i lambda_i
    log_den: float        # ln ∫ T c / lambda dlambda (up to the constant the colours cancel)


@functools.lru_cache(maxsize=1024)
def _quadrature(z: float, filt: Filter, igm: str) -> _Quadrature:
    fw, ft = filt.wave_angstrom, filt.throughput
    nz = np.flatnonzero(ft > 0)
    lo, hi = fw[max(nz[0] - 1, 0)], fw[min(nz[-1] + 1, fw.size - 1)]
    # A grid uniform in ln(lambda) (the filters' own samples are ~10x finer than needed).
    n = max(2, int(np.ceil(np.log(hi / lo) / _DLNLAM)) + 1)
    grid = np.exp(np.linspace(np.log(lo), np.log(hi), n))
    edges = igm_discontinuities(z, igm)
    edges = np.concatenate([edges, [LYMAN_LIMIT_ANGSTROM * (1 + z), BREAK_ANGSTROM * (1 + z)]])
    edges = edges[(edges > grid[0]) & (edges < grid[-1])]
    grid = np.unique(np.concatenate([grid, edges * (1 - 1e-9), edges * (1 + 1e-9)]))
    thr = np.interp(grid, fw, ft)
    wts = np.zeros_like(grid)
    dl = np.diff(grid)
    wts[:-1] += 0.5 * dl
    wts[1:] += 0.5 * dl
    trans = np.ones_like(grid)
    blue = grid < LYA_REST_ANGSTROM * (1.0 + z)
    if blue.any():
        trans[blue] = igm_transmission(grid[blue], z, igm)
    u = wts * thr * trans * grid
    keep = u > 0
    den = float(np.sum(wts * thr / grid))
    return _Quadrature(grid[keep], u[keep], float(np.log(den)))


def interloper_band_magnitudes(z: float, params: InterloperParams, filters, mag,
                               detection_index: int, igm: str = "inoue14",
                               faint_limit: float = FAINT_MAG_LIMIT) -> np.ndarray:
    """AB magnitudes of interlopers at redshift ``z``, normalised in the detection band.

    Parameters
    ----------
    z : float
        Redshift (> 0).
    params : InterloperParams
        N sources.
    filters : sequence of Filter or str
    mag : array_like (N,)
        Apparent AB magnitudes in band ``detection_index``.
    detection_index : int
    igm : {"inoue14", "madau95", "sharp"}
    faint_limit : float
        Fainter magnitudes become ``+inf`` (no flux, no stamp), as for the high-z sources.

    Returns
    -------
    numpy.ndarray (N, n_bands)

    Raises
    ------
    ValueError
        The detection band receives no flux from some source at this z.
    """
    z = float(z)
    if not (np.isfinite(z) and z > 0):
        raise ValueError(f"interloper z must be finite and > 0, got {z}")
    filts = [get_filter(f) for f in filters]
    mag = np.broadcast_to(np.asarray(mag, float), np.asarray(params.beta).shape)
    logn = np.empty((mag.size, len(filts)))
    for j, f in enumerate(filts):
        q = _quadrature(z, f, igm)
        if q.wave.size == 0:
            logn[:, j] = -np.inf
            continue
        flux = rest_flambda(q.wave / (1.0 + z), params) @ q.u
        with np.errstate(divide="ignore"):
            logn[:, j] = np.log(flux) - q.log_den
    det = logn[:, detection_index]
    if not np.all(np.isfinite(det)):
        raise ValueError(f"detection band {filts[detection_index].name!r} receives no flux "
                         f"from an interloper at z = {z}")
    out = mag[:, None] - (logn - det[:, None]) / _LN10_OVER_2P5
    out[:, detection_index] = mag
    out[~(out <= faint_limit)] = np.inf
    return out


def number_counts(counts, m) -> np.ndarray:
    """Power-law number counts ``dN/dm = 10^(a + b (m - m0))`` [arcmin^-2 mag^-1] at ``m``;
    ``counts`` = (a, b, m0)."""
    a, b, m0 = counts
    return 10.0 ** (a + b * (np.asarray(m, float) - m0))


def number_counts_integral(counts, lo, hi) -> np.ndarray:
    """``∫ dN/dm dm`` over [lo, hi] [arcmin^-2] of :func:`number_counts` (closed form)."""
    a, b, m0 = counts
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    if b == 0:
        return 10.0 ** a * (hi - lo)
    k = b * np.log(10.0)
    return 10.0 ** a * (np.exp(k * (hi - m0)) - np.exp(k * (lo - m0))) / k
