"""The interloper population of a run: its model, its tasks' draws, its weights.

An interloper task is (field, z node, magnitude cell, iteration) of the ``interlopers:``
section (:class:`glaciar.config.interlopers.InterloperConfig`): ``n_per_task`` sources at
the node's redshift, each with a detection-band magnitude uniform in the cell, a family
drawn with the configured weights, its spectral parameters uniform in their ranges
(:mod:`glaciar.galaxy.interloper_seds`) and sizes from the ``source:`` size law with the
section's own parameters, its log-normal scatter drawn from ``size_bins`` equal-probability
nodes scaled to the scatter's variance (shared templates: see :func:`draw_interlopers`).  Its random stream is keyed by the same values as a high-z
task's plus the population (:meth:`glaciar.engine.task.TaskSpec.spawn_key`), so the
high-z tasks' streams and rows are those of a run without interlopers.

Weights (:func:`count_weights`): each source stands for ``n(m) Δm / N_cell`` interlopers
per arcmin^2, n(m) the configured number counts times the families' share of them
(``dusty.weight + balmer.weight``), Δm the cell width, N_cell the sources
injected in its cell (over fields, z nodes and iterations): the weighted sums over a cell
are the counts' integral over it, with the z nodes equally weighted (a flat z
distribution) and the families in the configured proportions.

Pure functions and a frozen dataclass; no I/O.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..galaxy import population
from ..galaxy.interloper_seds import (InterloperParams, interloper_band_magnitudes, number_counts,
                                      number_counts_integral)

__all__ = ["POPULATION", "COL_POPULATION", "COL_FAMILY", "COL_A_V", "COL_D4000", "COL_BETA_RED",
           "InterloperModel", "draw_interlopers", "count_weights"]

#: The population name of interloper tasks (their spawn key and ``population`` column).
POPULATION = "interloper"
#: Columns interloper rows have beyond a high-z task's.
COL_POPULATION = "population"
COL_FAMILY = "interloper_family"
COL_A_V = "a_v"
COL_D4000 = "d4000"
COL_BETA_RED = "beta_red"


@dataclass(frozen=True)
class InterloperModel:
    """The ``interlopers:`` section as the engine uses it (tuples of floats)."""

    z_nodes: tuple
    mag_cells: tuple
    mag_step: float
    n_per_task: int
    n_iterations: int
    weights: tuple          #: (dusty, balmer), normalised: the families' mix
    share: float            #: dusty.weight + balmer.weight: their fraction of the counts
    dusty_beta: tuple
    dusty_a_v: tuple
    balmer_d4000: tuple
    balmer_beta_blue: float
    balmer_beta_red: float
    balmer_a_v: tuple
    counts: tuple           #: (a, b, m0) of log10 dN/dm = a + b (m - m0) [arcmin^-2 mag^-1]
    size: population.SourceModel    #: the r_e law without its scatter, the shapes' settings
    size_scatter_dex: float = 0.0
    size_bins: int = 1

    @classmethod
    def from_config(cls, section, source_model: population.SourceModel) -> "InterloperModel":
        """From :class:`~glaciar.config.interlopers.InterloperConfig` (or its dict) and the run's
        source model (ellipticity and position-angle bins, IGM and cosmology are shared)."""
        if isinstance(section, dict):
            from ..config.interlopers import InterloperConfig
            section = InterloperConfig.model_validate(section)
        w = np.array([section.dusty.weight, section.balmer.weight], float)
        size = dataclasses.replace(
            source_model, r_eff_kpc_z6=float(section.r_eff_kpc_z6),
            size_evolution=float(section.size_evolution),
            r_eff_scatter_dex=0.0, size_luminosity_slope=0.0,
            sersic_indices=tuple(section.sersic_indices),
            sersic_fractions=tuple(section.sersic_fractions))
        c = section.counts
        return cls(z_nodes=tuple(section.z_nodes()), mag_cells=tuple(section.mag_cells()),
                   mag_step=float(section.mag_step), n_per_task=int(section.n_per_task),
                   n_iterations=int(section.n_iterations), weights=tuple(w / w.sum()),
                   share=float(w.sum()),
                   dusty_beta=tuple(section.dusty.beta), dusty_a_v=tuple(section.dusty.a_v),
                   balmer_d4000=tuple(section.balmer.d4000),
                   balmer_beta_blue=float(section.balmer.beta_blue),
                   balmer_beta_red=float(section.balmer.beta_red),
                   balmer_a_v=tuple(section.balmer.a_v), counts=(c.a, c.b, c.m0), size=size,
                   size_scatter_dex=float(section.r_eff_scatter_dex),
                   size_bins=int(section.size_bins))

    def size_nodes(self) -> np.ndarray:
        """log10 r_e offsets [dex] of the size bins: equal-probability nodes of N(0, 1)
        (quantiles (j + 1/2) / K), scaled so that their variance is the scatter's."""
        from scipy.stats import norm

        k = self.size_bins
        q = norm.ppf((np.arange(k) + 0.5) / k)
        if k > 1:
            q = q / np.sqrt(np.mean(q ** 2))
        return self.size_scatter_dex * q

    @property
    def family_counts(self) -> tuple:
        """(a, b, m0) of the injected families' own counts: the configured counts times
        ``share`` (a + log10 share)."""
        a, b, m0 = self.counts
        return (float(a + np.log10(self.share)), float(b), float(m0))

    def density(self, m) -> np.ndarray:
        """The families' number counts dN/dm [arcmin^-2 mag^-1] at magnitude(s) ``m``."""
        return number_counts(self.family_counts, m)

    def integral(self, lo, hi) -> np.ndarray:
        """∫ dN/dm dm of the families over [lo, hi] [arcmin^-2] (exact for the power law)."""
        return number_counts_integral(self.family_counts, lo, hi)


def draw_interlopers(rng: np.random.Generator, model: InterloperModel, z: float, mag: float,
                     filters, detection_index: int, cosmology, quantise) -> dict:
    """Draw ``model.n_per_task`` interlopers at redshift ``z`` in the magnitude cell centred on ``mag``.

    Parameters
    ----------
    rng : numpy.random.Generator
        The task's stream.
    model : InterloperModel
    z, mag : float
        The task's z node and magnitude-cell centre [AB mag].
    filters : list of Filter
        The survey's bands.
    detection_index : int
    cosmology : astropy Cosmology
    quantise : callable
        r_e [pixels] -> the value injected (the field's template lattice).

    Returns
    -------
    dict
        Arrays of length n: the fields of :class:`glaciar.engine.task.SourceDraws`
        (``M_uv`` NaN: no rest-1600 A normalisation is defined for them; ``beta`` the
        family's UV slope) and ``extra``: the columns only interloper rows have.
    """
    n = model.n_per_task
    fam = np.where(rng.random(n) < model.weights[0], "dusty", "balmer")
    mag_det = mag + (rng.random(n) - 0.5) * model.mag_step
    u = rng.random((n, 2))
    dusty = fam == "dusty"

    def span(r, x):
        return r[0] + (r[1] - r[0]) * x

    beta = np.where(dusty, span(model.dusty_beta, u[:, 0]), model.balmer_beta_blue)
    d4 = np.where(dusty, np.nan, span(model.balmer_d4000, u[:, 0]))
    a_v = np.where(dusty, span(model.dusty_a_v, u[:, 1]), span(model.balmer_a_v, u[:, 1]))
    beta_red = np.where(dusty, np.nan, model.balmer_beta_red)
    params = InterloperParams(family=fam, beta=beta, beta_red=np.nan_to_num(beta_red),
                              a_v=a_v, d4000=d4)
    mag_in = interloper_band_magnitudes(z, params, filters, mag_det, detection_index,
                                        igm=model.size.igm)
    shapes = population.draw_shapes(rng, n, model.size)
    # The scatter on a few nodes, not continuous: sources of one node share their
    # templates (a continuous scatter makes every stamp a new render: ~3x the CPU).
    nodes = model.size_nodes()
    r_kpc = population.r_eff_kpc(np.full(n, float(z)), model.size) * 10.0 ** nodes[
        rng.integers(0, len(nodes), n)]
    r_arcsec = population.kpc_to_arcsec(r_kpc, z, cosmology)
    r_pix, r_arcsec = quantise(r_arcsec)
    return {"beta": beta, "mag_in": mag_in, "M_uv": np.full(n, np.nan),
            "sersic_n": shapes["sersic_n"], "axis_ratio": shapes["axis_ratio"],
            "position_angle_deg": shapes["position_angle_deg"], "r_eff_kpc": r_kpc,
            "r_eff_arcsec": r_arcsec, "r_eff_pix": r_pix,
            "extra": {COL_POPULATION: np.full(n, POPULATION, dtype=object),
                      COL_FAMILY: fam.astype(object), COL_A_V: a_v, COL_D4000: d4,
                      COL_BETA_RED: beta_red}}


def count_weights(mag_input, mag_cell, model: InterloperModel) -> np.ndarray:
    """Interlopers per arcmin^2 each row stands for (module docstring).

    Parameters
    ----------
    mag_input : array_like (N,)
        Input detection-band magnitudes of the rows [AB mag].
    mag_cell : array_like (N,)
        Their tasks' magnitude-cell centres (the ``mag`` column).
    model : InterloperModel
    """
    m = np.asarray(mag_input, float)
    cell = np.asarray(mag_cell, float)
    keys, inverse, n_cell = np.unique(cell, return_inverse=True, return_counts=True)
    return model.density(m) * model.mag_step / n_cell[inverse]
