"""Per-source draws of the artificial galaxies: shapes, sizes and UV slopes.

Every function that draws takes a ``numpy.random.Generator`` and is otherwise
pure, so a task's sources are fixed by its seed.  `SourceModel` carries the
``source:`` section of the configuration (docs/config-schema.yaml).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from glaciar.galaxy.igm import IGM_MODELS

__all__ = ["SourceModel", "get_cosmology", "r_eff_kpc", "kpc_to_arcsec",
           "draw_beta", "draw_shapes", "M_UV_SIZE_PIVOT", "Z_MIN_DISTANCE"]

#: Absolute UV magnitude at which the size-luminosity relation is pivoted.
M_UV_SIZE_PIVOT = -21.0
#: Smallest redshift given a distance (angular sizes, absolute magnitudes): a luminosity
#: distance of ~0.04 pc, far below any use.  Not just z > 0: float64 distances break
#: down for denormal z (found by tests/galaxy/test_population.py): at z = 5e-324 astropy's
#: D_L is 0 (distmod -inf, with a divide-by-zero warning), at z = 2e-313 its
#: arcsec per kpc overflows to inf.
Z_MIN_DISTANCE = 1e-8
_BETA_PER = ("source", "iteration")


@dataclass(frozen=True)
class SourceModel:
    """Population model of the injected sources (config section ``source:``).

    Parameters
    ----------
    r_eff_kpc_z6 : float
        Effective (half-light, semi-major axis) radius at z = 6 [proper kpc].
    size_evolution : float
        Exponent a of r_e ∝ ((1 + z) / 7)^a.
    r_eff_scatter_dex : float
        Standard deviation of log10 r_e about the relation [dex], >= 0.
    size_luminosity_slope : float
        Exponent s of r_e ∝ L^s, pivoted at M_UV = -21.
    sersic_indices : tuple of float
        Sérsic indices n of the population's components.
    sersic_fractions : tuple of float
        Probability of each index (same length, >= 0, summing to 1).
    ellipticity_bins : int
        Ellipticities e = 1 - q take the values j / ellipticity_bins,
        j = 0 .. ellipticity_bins - 1 (1: all round).
    position_angle_bins : int
        Position angles take the values k * 180 / position_angle_bins deg.
    round_de_vaucouleurs : bool
        If True, n = 4 sources are round (q = 1, PA = 0).
    beta_mean, beta_sd : float
        Normal distribution of the UV slope beta (f_lambda ∝ lambda^beta).
    beta_per : {"source", "iteration"}
        Draw beta per source, or once per iteration (GLACiAR's choice).
    igm : {"inoue14", "madau95", "sharp"}
        IGM attenuation model.
    cosmology : str
        Name of an ``astropy.cosmology`` realisation (e.g. ``"Planck18"``).
    stamp_flux_fraction : float
        Fraction of the total flux a stamp must hold, in (0, 1).
    shot_noise : bool or None
        Photon noise on the injected stamps in the bands with a gain
        (:mod:`glaciar.engine.shotnoise`): None (default) or True = on there,
        False = off.  Read by the engine, not by the draws here.
    """

    r_eff_kpc_z6: float = 1.075
    size_evolution: float = -1.0
    r_eff_scatter_dex: float = 0.0
    size_luminosity_slope: float = 0.0
    sersic_indices: tuple[float, ...] = (1.0, 4.0)
    sersic_fractions: tuple[float, ...] = (0.5, 0.5)
    ellipticity_bins: int = 1
    position_angle_bins: int = 1
    round_de_vaucouleurs: bool = False
    beta_mean: float = -2.2
    beta_sd: float = 0.4
    beta_per: str = "source"
    igm: str = "inoue14"
    cosmology: str = "Planck18"
    stamp_flux_fraction: float = 0.995
    shot_noise: bool | None = None

    def __post_init__(self):
        def err(field: str, msg: str) -> ValueError:
            return ValueError(f"source.{field}: {msg}")

        def real(field: str) -> float:
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise err(field, f"expected a number, got {value!r}")
            if not math.isfinite(value):
                raise err(field, f"must be finite, got {value!r}")
            object.__setattr__(self, field, float(value))
            return float(value)

        def integer(field: str) -> int:
            value = getattr(self, field)
            if (isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating))
                    or not float(value).is_integer()):
                raise err(field, f"expected an integer >= 1, got {value!r}")
            if int(value) < 1:
                raise err(field, f"must be >= 1, got {value!r}")
            object.__setattr__(self, field, int(value))
            return int(value)

        if real("r_eff_kpc_z6") <= 0:
            raise err("r_eff_kpc_z6", f"must be > 0, got {self.r_eff_kpc_z6}")
        real("size_evolution")
        if real("r_eff_scatter_dex") < 0:
            raise err("r_eff_scatter_dex", f"must be >= 0, got {self.r_eff_scatter_dex}")
        real("size_luminosity_slope")
        real("beta_mean")
        if real("beta_sd") < 0:
            raise err("beta_sd", f"must be >= 0, got {self.beta_sd}")
        frac = real("stamp_flux_fraction")
        if not 0 < frac < 1:
            raise err("stamp_flux_fraction", f"must be in (0, 1), got {frac}")
        integer("ellipticity_bins")
        integer("position_angle_bins")
        if not isinstance(self.round_de_vaucouleurs, (bool, np.bool_)):
            raise err("round_de_vaucouleurs", f"expected true or false, got {self.round_de_vaucouleurs!r}")
        object.__setattr__(self, "round_de_vaucouleurs", bool(self.round_de_vaucouleurs))
        if self.shot_noise is not None:
            if not isinstance(self.shot_noise, (bool, np.bool_)):
                raise err("shot_noise", f"expected true, false or null, got {self.shot_noise!r}")
            object.__setattr__(self, "shot_noise", bool(self.shot_noise))

        for field in ("sersic_indices", "sersic_fractions"):
            value = getattr(self, field)
            try:
                arr = np.atleast_1d(np.asarray(value, dtype=float))
            except (TypeError, ValueError):
                raise err(field, f"expected a list of numbers, got {value!r}") from None
            if arr.ndim != 1 or arr.size == 0 or not np.all(np.isfinite(arr)):
                raise err(field, f"expected a non-empty list of finite numbers, got {value!r}")
            object.__setattr__(self, field, tuple(float(v) for v in arr))
        if any(n <= 0 for n in self.sersic_indices):
            raise err("sersic_indices", f"indices must be > 0, got {list(self.sersic_indices)}")
        if len(self.sersic_fractions) != len(self.sersic_indices):
            raise err("sersic_fractions", f"has {len(self.sersic_fractions)} entries but "
                      f"sersic_indices has {len(self.sersic_indices)}")
        if any(f < 0 for f in self.sersic_fractions):
            raise err("sersic_fractions", f"must be >= 0, got {list(self.sersic_fractions)}")
        if abs(sum(self.sersic_fractions) - 1.0) > 1e-6:
            raise err("sersic_fractions", f"must sum to 1, got {sum(self.sersic_fractions):.6g}")

        if self.beta_per not in _BETA_PER:
            raise err("beta_per", f"expected one of {', '.join(_BETA_PER)}, got {self.beta_per!r}")
        if self.igm not in IGM_MODELS:
            raise err("igm", f"expected one of {', '.join(IGM_MODELS)}, got {self.igm!r}")
        try:
            get_cosmology(self.cosmology)
        except (ValueError, TypeError) as e:
            raise err("cosmology", str(e)) from None

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> "SourceModel":
        """Build from the ``source:`` mapping of a config; unknown keys are errors."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(mapping) - known)
        if unknown:
            raise ValueError(f"source: unknown key(s) {', '.join(unknown)}; "
                             f"expected some of {', '.join(sorted(known))}")
        return cls(**dict(mapping))


@functools.lru_cache(maxsize=None)
def _cosmology_by_name(name: str):
    from astropy.cosmology import realizations

    if name not in realizations.available:
        raise ValueError(f"unknown cosmology {name!r}; expected one of "
                         f"{', '.join(realizations.available)}")
    return getattr(realizations, name)


def get_cosmology(name):
    """An ``astropy.cosmology`` realisation by name (e.g. ``"Planck18"``).

    Parameters
    ----------
    name : str or astropy.cosmology.Cosmology or None
        A realisation name from ``astropy.cosmology.realizations.available``;
        a ``Cosmology`` instance is returned unchanged; None gives Planck18.
    """
    from astropy.cosmology import Cosmology

    if name is None:
        name = "Planck18"
    if isinstance(name, Cosmology):
        return name
    if not isinstance(name, str):
        raise TypeError(f"cosmology must be a name or an astropy Cosmology, got {name!r}")
    return _cosmology_by_name(name)


def r_eff_kpc(z, model: SourceModel, M_uv=None, rng: np.random.Generator | None = None):
    """Effective radius [proper kpc] of sources at redshift ``z``.

    r_e = r_eff_kpc_z6 ((1+z)/7)^size_evolution 10^(-0.4 s (M_uv + 21)) 10^(sigma eps),
    with s = ``size_luminosity_slope``, sigma = ``r_eff_scatter_dex`` and
    eps ~ N(0, 1): the scatter is log-normal about the median relation.

    Parameters
    ----------
    z : float or array_like
        Redshift(s).
    model : SourceModel
    M_uv : float or array_like, optional
        Absolute UV magnitudes (1600 A); required when the slope is non-zero.
    rng : numpy.random.Generator, optional
        Required when ``r_eff_scatter_dex > 0``; one normal deviate is drawn
        per output element.

    Returns
    -------
    numpy.ndarray
        r_e [proper kpc], shape of ``z`` and ``M_uv`` broadcast together.
    """
    z = np.asarray(z, dtype=float)
    if np.any(~np.isfinite(z)) or np.any(z < 0):
        raise ValueError(f"z must be finite and >= 0, got {z}")
    r = model.r_eff_kpc_z6 * ((1.0 + z) / 7.0) ** model.size_evolution
    if model.size_luminosity_slope != 0.0:
        if M_uv is None:
            raise ValueError("r_eff_kpc: M_uv is required when source.size_luminosity_slope != 0")
        r = r * 10.0 ** (-0.4 * model.size_luminosity_slope
                         * (np.asarray(M_uv, dtype=float) - M_UV_SIZE_PIVOT))
    elif M_uv is not None:
        r = np.broadcast_to(r, np.broadcast_shapes(r.shape, np.shape(M_uv)))
    if model.r_eff_scatter_dex > 0:
        if rng is None:
            raise ValueError("r_eff_kpc: rng is required when source.r_eff_scatter_dex > 0")
        r = r * 10.0 ** (model.r_eff_scatter_dex * rng.standard_normal(np.shape(r)))
    return np.array(r, dtype=float)


def kpc_to_arcsec(r_kpc, z, cosmology="Planck18"):
    """Convert proper kpc to arcsec at redshift ``z`` (angular-diameter distance).

    Parameters
    ----------
    r_kpc : float or array_like
        Proper sizes [kpc].
    z : float or array_like
        Redshift(s) (>= :data:`Z_MIN_DISTANCE` = 1e-8; there is no angular size at
        z = 0), broadcast against ``r_kpc``.
    cosmology : str or astropy.cosmology.Cosmology
        See `get_cosmology`.

    Returns
    -------
    numpy.ndarray
        Angular sizes [arcsec].
    """
    cosmo = get_cosmology(cosmology)
    z = np.asarray(z, dtype=float)
    if np.any(~(z >= Z_MIN_DISTANCE)):
        raise ValueError(f"kpc_to_arcsec: z must be > 0 (at least {Z_MIN_DISTANCE:g}), got {z}")
    return np.asarray(r_kpc, dtype=float) * cosmo.arcsec_per_kpc_proper(z).value


def draw_beta(rng: np.random.Generator, n: int, model: SourceModel) -> np.ndarray:
    """UV slopes beta ~ N(beta_mean, beta_sd) for ``n`` sources.

    With ``model.beta_per == "iteration"`` one value is drawn and shared by
    all ``n`` sources (the GLACiAR convention); otherwise one per source.

    Returns
    -------
    numpy.ndarray
        Shape (n,).
    """
    n = _count(n)
    if model.beta_per == "iteration":
        return np.full(n, rng.normal(model.beta_mean, model.beta_sd))
    return rng.normal(model.beta_mean, model.beta_sd, size=n)


def draw_shapes(rng: np.random.Generator, n: int, model: SourceModel) -> dict[str, np.ndarray]:
    """Sérsic index, axis ratio and position angle for ``n`` sources.

    The index is drawn with probabilities ``sersic_fractions`` (independently
    per source, so the fractions hold in expectation, not by truncation);
    the ellipticity e = j / ellipticity_bins with j uniform on
    0 .. ellipticity_bins - 1 gives q = 1 - e; the position angle is
    k * 180 / position_angle_bins deg with k uniform on
    0 .. position_angle_bins - 1.  With ``round_de_vaucouleurs``, n = 4
    sources get q = 1 and PA = 0.  The three draws are always made, in this
    order, so the random stream does not depend on the settings' values.

    Returns
    -------
    dict
        ``sersic_n`` (float, (n,)), ``axis_ratio`` (float, (n,), in (0, 1]),
        ``position_angle_deg`` (float, (n,), in [0, 180)).
    """
    n = _count(n)
    idx = rng.choice(len(model.sersic_indices), size=n, p=np.asarray(model.sersic_fractions))
    sersic_n = np.asarray(model.sersic_indices, dtype=float)[idx]
    j = rng.integers(0, model.ellipticity_bins, size=n)
    k = rng.integers(0, model.position_angle_bins, size=n)
    axis_ratio = 1.0 - j / model.ellipticity_bins
    pa = k * (180.0 / model.position_angle_bins)
    if model.round_de_vaucouleurs:
        dev = sersic_n == 4.0
        axis_ratio = np.where(dev, 1.0, axis_ratio)
        pa = np.where(dev, 0.0, pa)
    return {"sersic_n": sersic_n, "axis_ratio": axis_ratio.astype(float),
            "position_angle_deg": pa.astype(float)}


def _count(n) -> int:
    if (isinstance(n, bool) or not isinstance(n, (int, float, np.integer, np.floating))
            or not float(n).is_integer() or n < 0):
        raise ValueError(f"number of sources must be an integer >= 0, got {n!r}")
    return int(n)
