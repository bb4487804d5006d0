"""Mean transmission of the intergalactic medium (IGM) blueward of Lyman alpha.

Three models, selected by name:

``"inoue14"`` (default)
    Inoue, Shimizu, Iwata & Tanaka (2014, MNRAS 442, 1805): analytic fit to a
    Monte-Carlo IGM with the Lyman-alpha forest (LAF) and damped Lyman-alpha
    systems (DLA) as separate absorber populations; Lyman series up to
    j = 40 (eqs. 21-22, Table 2) plus the Lyman continuum (eqs. 25-29).
``"madau95"``
    Madau (1995, ApJ 441, 18): Lyman-series blanketing by Ly alpha - Ly delta
    (eq. 12 and the coefficients that follow it) plus the photoelectric
    (Lyman-continuum) term of Madau's footnote 3.
``"sharp"``
    Zero flux blueward of rest-frame Lyman alpha, one redward: the rule of
    the original GLACiAR.

All functions take observed-frame wavelengths in Angstrom.
"""
from __future__ import annotations

import functools
from importlib import resources

import numpy as np

from glaciar.constants import LYA_REST_ANGSTROM, LYLIMIT_REST_ANGSTROM

__all__ = ["IGM_MODELS", "igm_transmission", "igm_optical_depth", "igm_discontinuities"]

IGM_MODELS = ("inoue14", "madau95", "sharp")

# Inoue+14 define their continuum fits with lambda_L = 911.8 A (their eq. 25);
# using that value keeps the fitting formulas exactly as published.
_INOUE_LYMAN_LIMIT = 911.8
# Branch points of eqs. 21-22 in ln(lambda_obs / lambda_j): absorber redshifts 1.2, 4.7, 2.0.
_LN2P2, _LN5P7, _LN3 = np.log(2.2), np.log(5.7), np.log(3.0)

# Madau (1995) eq. 12 coefficients for Ly alpha, beta, gamma, delta.
_MADAU_LINES = np.array([1215.67, 1025.72, 972.537, 949.743])
_MADAU_COEFFS = np.array([3.6e-3, 1.7e-3, 1.2e-3, 9.3e-4])


@functools.lru_cache(maxsize=1)
def _inoue14_table() -> tuple[np.ndarray, ...]:
    """Table 2 of Inoue+14: (lambda_j, A_LAF1, A_LAF2, A_LAF3, A_DLA1, A_DLA2)."""
    path = resources.files("glaciar").joinpath("data/igm/inoue14_table2.txt")
    with resources.as_file(path) as p:
        table = np.loadtxt(p, comments="#")
    if table.ndim != 2 or table.shape[1] != 7:
        raise ValueError(f"{path}: expected 7 columns (j, lambda, 3 LAF, 2 DLA coefficients)")
    return tuple(table[:, k].copy() for k in range(1, 7))


def _check_model(model: str) -> str:
    if model not in IGM_MODELS:
        raise ValueError(f"unknown IGM model {model!r}; expected one of {', '.join(IGM_MODELS)}")
    return model


def _prepare(wave_obs_angstrom, z) -> tuple[np.ndarray, np.ndarray]:
    wave = np.asarray(wave_obs_angstrom, dtype=float)
    zz = np.asarray(z, dtype=float)
    if np.any(~np.isfinite(zz)) or np.any(zz < 0):
        raise ValueError(f"redshift must be finite and >= 0, got {z!r}")
    if np.any(~(wave > 0)):
        raise ValueError("observed wavelengths must be positive (Angstrom)")
    return np.broadcast_arrays(wave, zz)


def _tau_inoue14(lobs: np.ndarray, zs: np.ndarray) -> np.ndarray:
    lam, laf1, laf2, laf3, dla1, dla2 = _inoue14_table()
    shape = lobs.shape
    lobs, zs = lobs.ravel(), zs.ravel()
    tau = np.zeros(lobs.shape)
    one_z = 1.0 + zs
    log_lobs, log_one_z = np.log(lobs), np.log(one_z)

    # Lyman series (eqs. 21, 22): line j absorbs at lambda_j < lobs < lambda_j (1+z_S);
    # the power of the LAF (DLA) term changes at absorber redshifts 1.2 and 4.7 (2.0).
    # One line at a time, on the absorbed samples only, in log space so that
    # each term costs one exp.
    for j in range(lam.size):
        lx = log_lobs - np.log(lam[j])
        active = np.flatnonzero((lx > 0.0) & (lx < log_one_z))
        if active.size == 0:
            continue
        lx = lx[active]
        laf_p = np.where(lx < _LN2P2, 1.2, np.where(lx < _LN5P7, 3.7, 5.5))
        laf_a = np.where(lx < _LN2P2, laf1[j], np.where(lx < _LN5P7, laf2[j], laf3[j]))
        dla_p = np.where(lx < _LN3, 2.0, 3.0)
        dla_a = np.where(lx < _LN3, dla1[j], dla2[j])
        tau[active] += laf_a * np.exp(laf_p * lx) + dla_a * np.exp(dla_p * lx)

    # Lyman continuum (eqs. 25-29), for lobs < lambda_L (1+z_S).  The published
    # fits are used as printed for lambda_L <= lobs (the model's domain: absorbers
    # at 0 <= z <= z_S).  Below lobs = lambda_L they are held at their value at
    # lambda_L: the fits' polynomials in x = lobs / lambda_L are not valid for
    # x < 1 and, extended there, turn negative (tau = -0.25 at 100 A for z_S = 3,
    # -362 for z_S = 20, i.e. "transmission" e^362; property test in
    # tests/galaxy/test_igm.py), against the documented 0 <= T <= 1.
    lc = np.flatnonzero(lobs < _INOUE_LYMAN_LIMIT * one_z)
    if lc.size:
        x = np.maximum(lobs[lc], _INOUE_LYMAN_LIMIT) / _INOUE_LYMAN_LIMIT
        oz, z_lc = one_z[lc], zs[lc]
        # LAF, eqs. 25 (z_S < 1.2), 26 (1.2 <= z_S < 4.7), 27 (z_S >= 4.7)
        laf_low = 0.325 * (x**1.2 - oz**-0.9 * x**2.1)
        laf_mid = np.where(
            x < 2.2,
            2.55e-2 * oz**1.6 * x**2.1 + 0.325 * x**1.2 - 0.250 * x**2.1,
            2.55e-2 * (oz**1.6 * x**2.1 - x**3.7))
        laf_high = np.where(
            x < 2.2,
            5.22e-4 * oz**3.4 * x**2.1 + 0.325 * x**1.2 - 3.14e-2 * x**2.1,
            np.where(x < 5.7,
                     5.22e-4 * oz**3.4 * x**2.1 + 0.218 * x**2.1 - 2.55e-2 * x**3.7,
                     5.22e-4 * (oz**3.4 * x**2.1 - x**5.5)))
        laf = np.where(z_lc < 1.2, laf_low, np.where(z_lc < 4.7, laf_mid, laf_high))
        # DLA, eqs. 28 (z_S < 2) and 29 (z_S >= 2)
        dla_low = 0.211 * oz**2 - 7.66e-2 * oz**2.3 * x**-0.3 - 0.135 * x**2
        dla_high = np.where(
            x < 3.0,
            0.634 + 4.70e-2 * oz**3 - 1.78e-2 * oz**3.3 * x**-0.3
            - 0.135 * x**2 - 0.291 * x**-0.3,
            4.70e-2 * oz**3 - 1.78e-2 * oz**3.3 * x**-0.3 - 2.92e-2 * x**3)
        dla = np.where(z_lc < 2.0, dla_low, dla_high)
        tau[lc] += laf + dla
    # Inside the domain the DLA fit of eq. 28 dips just below zero for z_S -> 0
    # (its constants give 0.211 - 0.0766 - 0.135 = -6e-4 at x = 1 + z_S = 1;
    # measured tau = -3.7e-4 at z_S = 0.001, lobs = 912.3 A): an optical depth
    # cannot be negative (as for Madau's continuum fit below).
    np.maximum(tau, 0.0, out=tau)
    return tau.reshape(shape)


def _tau_madau95(lobs: np.ndarray, zs: np.ndarray) -> np.ndarray:
    tau = np.zeros(lobs.shape)
    one_z = 1.0 + zs
    for lj, aj in zip(_MADAU_LINES, _MADAU_COEFFS):
        x = lobs / lj
        tau += np.where((x > 1.0) & (x < one_z), aj * x**3.46, 0.0)
    # Photoelectric absorption by intervening Lyman-limit systems, Madau (1995)
    # footnote 3 (his approximation to the integral over absorber redshift,
    # quoted as good to about 5 per cent in tau).
    xc = lobs / LYLIMIT_REST_ANGSTROM
    lc = xc < one_z
    if np.any(lc):
        xc_safe = np.where(lc, xc, 1.0)
        t = (0.25 * xc_safe**3 * (one_z**0.46 - xc_safe**0.46)
             + 9.4 * xc_safe**1.5 * (one_z**0.18 - xc_safe**0.18)
             - 0.7 * xc_safe**3 * (xc_safe**-1.32 - one_z**-1.32)
             - 0.023 * (one_z**1.68 - xc_safe**1.68))
        # The fit can dip slightly below zero just under the Lyman limit of a
        # low-z source; an optical depth cannot be negative.
        tau += np.where(lc, np.maximum(t, 0.0), 0.0)
    return tau


def igm_optical_depth(wave_obs_angstrom, z, model: str = "inoue14") -> np.ndarray:
    """Effective IGM optical depth towards a source at redshift ``z``.

    Parameters
    ----------
    wave_obs_angstrom : array_like
        Observed-frame wavelengths [Angstrom].
    z : float or array_like
        Source redshift(s), broadcast against ``wave_obs_angstrom``.
    model : {"inoue14", "madau95", "sharp"}
        IGM model (see the module docstring).  ``"sharp"`` gives ``inf``
        blueward of rest-frame Lyman alpha and 0 elsewhere.

    Returns
    -------
    numpy.ndarray
        tau_eff >= 0, with the broadcast shape of the inputs.
    """
    _check_model(model)
    lobs, zs = _prepare(wave_obs_angstrom, z)
    if model == "sharp":
        return np.where(lobs < LYA_REST_ANGSTROM * (1.0 + zs), np.inf, 0.0)
    if model == "madau95":
        return _tau_madau95(lobs, zs)
    return _tau_inoue14(lobs, zs)


def igm_transmission(wave_obs_angstrom, z, model: str = "inoue14") -> np.ndarray:
    """Mean IGM transmission exp(-tau_eff) towards a source at redshift ``z``.

    Parameters
    ----------
    wave_obs_angstrom : array_like
        Observed-frame wavelengths [Angstrom].
    z : float or array_like
        Source redshift(s) (>= 0), broadcast against ``wave_obs_angstrom``
        (e.g. ``z[:, None]`` with a 1-D wavelength grid gives one row per z).
    model : {"inoue14", "madau95", "sharp"}
        ``"inoue14"``: Inoue et al. (2014) LAF + DLA, Lyman series and
        continuum (default).  ``"madau95"``: Madau (1995) Ly alpha-delta
        blanketing plus photoelectric absorption.  ``"sharp"``: 0 blueward
        of rest-frame Lyman alpha (1215.67 A), 1 redward (original GLACiAR).

    Returns
    -------
    numpy.ndarray
        Transmission in [0, 1], with the broadcast shape of the inputs.
        It is exactly 1 redward of Lyman alpha at the source redshift.
    """
    tau = igm_optical_depth(wave_obs_angstrom, z, model)
    return np.exp(-tau)


def igm_discontinuities(z: float, model: str = "inoue14") -> np.ndarray:
    """Observed wavelengths [Angstrom] where the model's transmission is not smooth.

    These are the onsets lambda_j (1 + z) of every Lyman-series line the model
    includes (jumps) and of the Lyman continuum (a kink); for ``"sharp"``,
    Lyman alpha only.  Quadrature with nodes on both sides of them does not
    straddle a jump.

    Parameters
    ----------
    z : float
        Source redshift.
    model : {"inoue14", "madau95", "sharp"}

    Returns
    -------
    numpy.ndarray
        Sorted observed wavelengths [Angstrom].
    """
    _check_model(model)
    if model == "sharp":
        rest = np.array([LYA_REST_ANGSTROM])
    elif model == "madau95":
        rest = np.concatenate([_MADAU_LINES, [LYLIMIT_REST_ANGSTROM]])
    else:
        rest = np.concatenate([_inoue14_table()[0], [_INOUE_LYMAN_LIMIT]])
    return np.sort(rest) * (1.0 + float(z))
