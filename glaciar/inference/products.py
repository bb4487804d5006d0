"""What the selection function, the transfer function and the expected counts share.

The value types of the selection function's products (V_eff, the magnitude at a
completeness level, the injections' spectra, V_eff(M_UV) tables, transfer slices) and
the SED terms that map M_UV to the detection band (:func:`kcorrection`, with
:func:`beta_nodes` for the average over the UV slope).  A leaf of
:mod:`glaciar.inference` (numpy, scipy and :mod:`glaciar.galaxy` only), so that
``selection_function``, ``transfer`` and ``counts`` import it and not one another.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from ..constants import FAINT_MAG_LIMIT
from ..galaxy import sed
from ..galaxy.population import get_cosmology
from ..galaxy.sed import distance_term

__all__ = ["GRID_QUANTILES", "KCORR_DZ", "EffectiveVolume", "MagnitudeAt", "InjectionSED",
           "VeffTable", "TransferSlice", "beta_nodes", "band_colour", "kcorrection"]

#: Posterior quantiles tabulated per grid point (and per parameter) in the file.
GRID_QUANTILES = (0.5, 0.16, 0.84, 0.025, 0.975)
#: Redshift step of the exactly computed band colours behind :func:`kcorrection`.
KCORR_DZ = 0.05


@dataclass(frozen=True)
class EffectiveVolume:
    """V_eff(m) with its credible interval (astropy Quantities in Mpc^3).

    Attributes
    ----------
    median, lower, upper : Quantity
        Posterior median and the bounds of the requested credible interval.
    draws : Quantity, shape (n_draws,) + m.shape
    """

    median: object
    lower: object
    upper: object
    draws: object


@dataclass(frozen=True)
class MagnitudeAt:
    """Magnitude at which completeness reaches a level, per posterior draw.

    Attributes
    ----------
    median, lower, upper : ndarray
        Posterior median and central-interval bounds [mag]; NaN where the
        level is above C_max (never reached), and NaN where a bound (or the
        median) lies outside the simulated magnitude range or z outside the
        simulated redshift range (no extrapolation is reported as a value).
    draws : ndarray (n_draws,) + shape
        Per draw; -inf / +inf where the draw's level lies brighter / fainter
        than the simulated range, NaN where it is not reached.
    """

    median: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    draws: np.ndarray


@dataclass(frozen=True)
class InjectionSED:
    """The spectra the injections were made with: what maps M_UV to the detection band.

    Attributes
    ----------
    detection_filter : glaciar.galaxy.filters.Filter
        Throughput of the detection band (the file stores the curve, ``DETFILT``).
    beta_mean, beta_sd : float
        UV slope beta ~ N(beta_mean, beta_sd), f_lambda ∝ lambda^beta.
    igm : str
        IGM attenuation model ("inoue14", "madau95", "sharp").
    cosmology : str
        astropy realisation the injections used (e.g. "Planck18").
    """

    detection_filter: object
    beta_mean: float
    beta_sd: float
    igm: str = "inoue14"
    cosmology: str = "Planck18"


@dataclass(frozen=True)
class VeffTable:
    """V_eff(M_UV) tabulated in the file (``VEFF_MUV``).

    Attributes
    ----------
    M_uv : ndarray (n,)
        Absolute UV magnitudes at rest 1600 A [AB mag].
    volume : EffectiveVolume
        Median, bounds and draws [Mpc^3].
    interval : float
        Probability of the central credible interval of ``lower``/``upper``.
    area_arcmin2 : float
        Survey area integrated over [arcmin^2].
    cosmology : str
        Cosmology of dV/dz and of the M_UV -> m mapping.
    """

    M_uv: np.ndarray
    volume: EffectiveVolume
    interval: float
    area_arcmin2: float
    cosmology: str


@dataclass(frozen=True)
class TransferSlice:
    """p(m_obs | m_in) at one redshift slice (:meth:`SelectionFunction.transfer`).

    Attributes
    ----------
    m_in_edges : ndarray (n_in + 1,)
        Input detection-band magnitude bins [AB mag].
    m_obs_edges : ndarray (n_obs + 1,)
        Measured detection-band magnitude bins [AB mag]; the first edge is -inf,
        the last +inf.
    matrix : ndarray (n_in, 1 + n_obs)
        Column 0: fraction not recovered (or not selected); column 1 + b:
        fraction recovered (selected) with m_obs in bin b.  Rows sum to 1.
    draws : ndarray (n_draws, n_in, 1 + n_obs)
        Dirichlet posterior draws of the rows.
    counts : ndarray (n_in, 1 + n_obs)
        Injected sources per entry.
    z_lo, z_hi : float
        The redshift slice [z_lo, z_hi).
    kind : str
        "recovered" or "selected".
    """

    m_in_edges: np.ndarray
    m_obs_edges: np.ndarray
    matrix: np.ndarray
    draws: np.ndarray
    counts: np.ndarray
    z_lo: float
    z_hi: float
    kind: str


def beta_nodes(beta_mean: float, beta_sd: float, n: int = 7):
    """Gauss-Hermite nodes and weights of beta ~ N(beta_mean, beta_sd).

    The average of a smooth function of beta over the normal distribution is
    Σ_k w_k f(beta_k), exact for polynomials of degree < 2n.  One node for beta_sd = 0.
    """
    if not (np.isfinite(beta_mean) and np.isfinite(beta_sd) and beta_sd >= 0):
        raise ValueError(f"beta distribution: need finite beta_mean and beta_sd >= 0, "
                         f"not {beta_mean}, {beta_sd}")
    if beta_sd == 0 or int(n) <= 1:
        return np.array([float(beta_mean)]), np.array([1.0])
    x, w = np.polynomial.hermite_e.hermegauss(int(n))
    return beta_mean + beta_sd * x, w / w.sum()


def band_colour(z, beta, detection_filter, igm, cosmology):
    """c(beta) = m_det - m(observed 1600 A (1+z)) at one z, +inf where the band has no flux."""
    k = sed.band_magnitudes(z, beta, [detection_filter], M_uv=0.0, cosmology=cosmology,
                            igm=igm, faint_limit=None)[:, 0]
    c = k - sed.apparent_uv_magnitude(0.0, z, cosmology=cosmology)
    return np.where(c <= FAINT_MAG_LIMIT, c, np.inf)


def kcorrection(z, beta, detection_filter, *, igm: str = "inoue14", cosmology=None,
                dz: float | None = KCORR_DZ) -> np.ndarray:
    """m_det - M_UV of a UV power law at redshift ``z``: the map from M_UV to the detection band.

    m_det = M_UV + DM(z) - 2.5 log10(1 + z) + c(beta, z), c the band's magnitude
    relative to observed 1600 A (1 + z) (:func:`glaciar.galaxy.sed.band_magnitudes`,
    the function the injections used).

    Parameters
    ----------
    z : array_like (n_z,)
        Redshifts (> 0).
    beta : array_like (n_beta,)
        UV slopes.
    detection_filter : Filter or str
    igm : str
    cosmology : str or astropy Cosmology, optional
        Default Planck18.
    dz : float or None
        The colour c (one band integral per z, ~16 ms) is computed exactly on
        the multiples of ``dz`` that cover the z asked and interpolated by a cubic spline in z, when that
        takes fewer nodes than ``z`` has: with dz = 0.05 the error is < 2e-8 mag
        while the band is redward of Lyman-alpha and < 3e-4 mag where the IGM
        enters it (F160W, z = 6-12.5, measured).  The distance term is exact.
        None: exact at every z.

    Returns
    -------
    ndarray (n_z, n_beta)
        [mag]; ``+inf`` where the band receives no flux (a source of AB
        magnitude 0 at rest 1600 A would be fainter than ``FAINT_MAG_LIMIT``).
    """
    cosmology = get_cosmology(cosmology)
    z = np.atleast_1d(np.asarray(z, float))
    b = np.atleast_1d(np.asarray(beta, float))
    if z.size and not np.all(np.isfinite(z) & (z > 0)):
        raise ValueError("kcorrection: z must be finite and > 0")
    dist = distance_term(z, cosmology) if z.size else np.zeros(0)
    lo, hi = (float(z.min()), float(z.max())) if z.size else (0.0, 0.0)
    # Nodes on multiples of dz (covering [lo, hi]): they lie on the z lattice of
    # glaciar.galaxy.sed, whose tables are exact and cached there (another z costs
    # the five lattice tables around it).
    # (The tolerance: 8.2 / 0.05 is 163.99999..., whose floor would add a node 8.15 that
    # the clip below moves onto the next one, 8.2: a spline needs distinct nodes.)
    k = (np.arange(np.floor(lo / dz + 1e-9), np.ceil(hi / dz - 1e-9) + 1) if dz
         else np.zeros(z.size + 1))
    if k.size >= z.size or k.size < 4:
        col = np.array([band_colour(zi, b, detection_filter, igm, cosmology) for zi in z])
        return dist[:, None] + col.reshape(len(z), len(b))
    # Never below the lowest z asked (z = 0 has no distance).
    zn = np.unique(np.maximum(np.round(k * dz, 10), lo))
    cn = np.array([band_colour(zi, b, detection_filter, igm, cosmology) for zi in zn])
    fin = np.isfinite(cn).all(axis=1)
    # No flux happens above a redshift (the IGM eats the band): the finite nodes are a prefix.
    last = int(np.argmin(fin)) - 1 if not fin.all() else len(zn) - 1
    col = np.full((len(z), len(b)), np.inf)
    if last >= 3:
        inside = z <= zn[last]
        col[inside] = CubicSpline(zn[:last + 1], cn[:last + 1], axis=0)(z[inside])
    elif last >= 0:
        inside = z <= zn[last]
        col[inside] = np.array([band_colour(zi, b, detection_filter, igm, cosmology)
                                for zi in z[inside]])
    if 0 <= last < len(zn) - 1:
        # Between the last node with flux and the first without: exact (flux may end there).
        edge = (z > zn[last]) & (z < zn[last + 1])
        if np.any(edge):
            col[edge] = np.array([band_colour(zi, b, detection_filter, igm, cosmology)
                                  for zi in z[edge]])
    return dist[:, None] + col
