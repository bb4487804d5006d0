"""Contamination by low-z interlopers: the fraction passing the selection per measured magnitude.

The rows of a run's interloper tasks (:mod:`glaciar.engine.interlopers`) are weighted to
the configured number counts n(m) [arcmin^-2 mag^-1]: row i stands for w_i interlopers
per arcmin^2 (:func:`glaciar.engine.interlopers.count_weights`).  In each bin k of the
measured detection-band magnitude (the ``mag_auto`` the transfer function and ``glaciar
lf`` use; bins = the injected magnitude cells),

    f_k = Σ_i w_i [selected_i and m_obs,i in k] / Σ_i w_i [m_in,i in k],

the interlopers selected with a measured magnitude in k per interloper whose true
magnitude lies in k: N_int,k = Ω f_k ∫_k n(m) dm (Ω the area) are the expected
interlopers among the candidates of bin k.

Uncertainty: per bin a Beta posterior with Jeffreys' prior on the Kish effective counts,
n_eff = (Σ w)^2 / Σ w^2 over the bin's injected rows and k_eff = f_k n_eff:
Beta(k_eff + 1/2, n_eff - k_eff + 1/2) (for equal weights this is the binomial
posterior of the passing fraction; unequal weights inflate it by the design effect).
Why bins and not a smooth curve: the passing fraction of interlopers rises where
photometric scatter lets their colours pass and falls where they stop being detected;
no two- or three-parameter curve holds that shape for every selection, and the
injected cells already set the resolution.  Bins with no selected interloper get the
one-sided interval [0, 68th percentile of Beta(1/2, n_eff + 1/2)]: an upper limit, not a zero.
:meth:`Contamination.fraction` is the step function of the bins (0 outside them:
no interloper was injected there).

Arrays in, arrays out; the FITS extension ``CONTAM`` (:func:`contamination_hdu`,
:func:`read_contamination`) is the file's record (docs/selection-function-file.md).
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import numpy as np

from ..galaxy.interloper_seds import number_counts, number_counts_integral
from .counts import ExpectedCounts

__all__ = ["Contamination", "ContaminationMixin", "ExpectedCountsWithInterlopers",
           "fit_contamination", "contamination_hdu", "read_contamination", "CONTAM_EXTNAME",
           "CONTAM_DRAWS"]

#: Name of the selection-function file's extension.
CONTAM_EXTNAME = "CONTAM"
#: Posterior draws kept per bin.
CONTAM_DRAWS = 200


@dataclass(frozen=True)
class Contamination:
    """The interloper passing fraction per measured-magnitude bin (module docstring).

    Attributes
    ----------
    m_edges : ndarray (K + 1,)
        Measured detection-band magnitude bins [AB mag].
    fraction, lower, upper : ndarray (K,)
        Posterior median and 68 % interval of f_k (point estimate: ``estimate``).
    estimate : ndarray (K,)
        The weighted fraction itself.
    draws : ndarray (D, K)
        Posterior draws.
    n_injected, n_selected : ndarray (K,)
        Rows with m_in in the bin; selected rows with m_obs in it.
    n_eff : ndarray (K,)
        Kish effective number of injected rows.
    counts : tuple
        (a, b, m0): log10 dN/dm = a + b (m - m0) [arcmin^-2 mag^-1].
    family_estimate : dict
        Per family, its part of ``estimate`` (they add up to it).
    z_range : tuple
        Redshifts of the interlopers.
    """

    m_edges: np.ndarray
    fraction: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    estimate: np.ndarray
    draws: np.ndarray
    n_injected: np.ndarray
    n_selected: np.ndarray
    n_eff: np.ndarray
    counts: tuple
    family_estimate: dict
    z_range: tuple

    def density(self, m) -> np.ndarray:
        """Number counts dN/dm [arcmin^-2 mag^-1]."""
        return number_counts(self.counts, m)

    def _integral(self, lo, hi):
        return number_counts_integral(self.counts, lo, hi)

    def fraction_at(self, m_obs, which: str = "median") -> np.ndarray:
        """f at measured magnitude(s) ``m_obs``: the bin's value, 0 outside the bins.

        ``which``: "median", "lower", "upper" or "estimate".
        """
        vals = {"median": self.fraction, "lower": self.lower, "upper": self.upper,
                "estimate": self.estimate}[which]
        m = np.asarray(m_obs, float)
        k = np.searchsorted(self.m_edges, m, side="right") - 1
        inside = (k >= 0) & (k < len(vals))
        return np.where(inside, vals[np.clip(k, 0, len(vals) - 1)], 0.0)

    def surface_density(self, m_obs_edges, draws: bool = False) -> np.ndarray:
        """Expected interlopers passing the selection per bin of ``m_obs_edges`` [arcmin^-2].

        ∫_bin n(m) f(m) dm with f the step function of the bins; (n_bins,), or
        (D, n_bins) per posterior draw with ``draws``.
        """
        E = np.asarray(m_obs_edges, float)
        lo = np.clip(E[:-1, None], self.m_edges[None, :-1], self.m_edges[None, 1:])
        hi = np.clip(E[1:, None], self.m_edges[None, :-1], self.m_edges[None, 1:])
        ov = np.where(hi > lo, self._integral(lo, hi), 0.0)                   # (n_bins, K)
        if draws:
            return self.draws @ ov.T
        return ov @ self.fraction


def _beta_draws(k_eff, n_eff, size, rng):
    a = k_eff + 0.5
    b = np.maximum(n_eff - k_eff, 0.0) + 0.5
    return rng.beta(a, b, size=(size,) + np.shape(a))


def fit_contamination(rows, weights, m_edges, *, obs_column: str, counts, z_range=(np.nan,) * 2,
                      family_column: str | None = None, seed: int = 0,
                      n_draws: int = CONTAM_DRAWS) -> Contamination:
    """The passing fraction per measured-magnitude bin from interloper rows (module docstring).

    Parameters
    ----------
    rows : pandas.DataFrame
        Interloper rows with ``mag_input``, ``selected`` and ``obs_column``.
    weights : array_like (N,)
        Interlopers per arcmin^2 each row stands for.
    m_edges : array_like (K + 1,)
        Bins [AB mag].
    obs_column : str
        The measured detection-band magnitude column.
    counts : tuple
        (a, b, m0) of the number counts.
    z_range : tuple
    family_column : str, optional
        Column naming each row's family (per-family estimates).
    seed : int
        Seed of the posterior draws.
    n_draws : int
    """
    from .. import constants as C

    E = np.asarray(m_edges, float)
    w = np.asarray(weights, float)
    m_in = np.asarray(rows[C.COL_MAG_INPUT], float)
    m_obs = np.asarray(rows[obs_column], float)
    sel = np.asarray(rows[C.COL_SELECTED], bool) & np.isfinite(m_obs)
    K = len(E) - 1
    k_in = np.searchsorted(E, m_in, side="right") - 1
    k_obs = np.searchsorted(E, m_obs, side="right") - 1
    ok_in = (k_in >= 0) & (k_in < K)
    ok_obs = sel & (k_obs >= 0) & (k_obs < K)
    W = np.bincount(k_in[ok_in], w[ok_in], minlength=K)
    W2 = np.bincount(k_in[ok_in], w[ok_in] ** 2, minlength=K)
    S = np.bincount(k_obs[ok_obs], w[ok_obs], minlength=K)
    with np.errstate(invalid="ignore", divide="ignore"):
        est = np.where(W > 0, S / np.where(W > 0, W, 1.0), 0.0)
        n_eff = np.where(W2 > 0, W ** 2 / np.where(W2 > 0, W2, 1.0), 0.0)
    k_eff = np.minimum(est, 1.0) * n_eff
    rng = np.random.default_rng(np.random.SeedSequence(int(seed)))
    # f may exceed 1 in principle (sources scattered in from brighter bins): the draws
    # scale the Beta by the estimate's excess over 1 then.
    draws = _beta_draws(k_eff, n_eff, int(n_draws), rng) * np.maximum(est, 1.0)
    q = np.quantile(draws, [0.5, 0.16, 0.84], axis=0)
    # No selected interloper: the one-sided 68 % interval [0, 68th percentile].
    none = S == 0
    q[1, none] = 0.0
    q[2, none] = np.quantile(draws[:, none], 0.68, axis=0)
    fam = {}
    if family_column is not None and family_column in rows:
        names = np.asarray(rows[family_column]).astype(str)
        for f in map(str, sorted(set(names))):
            mine = ok_obs & (names == f)
            Sf = np.bincount(k_obs[mine], w[mine], minlength=K)
            fam[f] = np.where(W > 0, Sf / np.where(W > 0, W, 1.0), 0.0)
    return Contamination(
        m_edges=E, fraction=q[0], lower=q[1], upper=q[2], estimate=est, draws=draws,
        n_injected=np.bincount(k_in[ok_in], minlength=K).astype(np.int64),
        n_selected=np.bincount(k_obs[ok_obs], minlength=K).astype(np.int64), n_eff=n_eff,
        counts=tuple(float(c) for c in counts), family_estimate=fam,
        z_range=tuple(float(z) for z in z_range))


# --------------------------------------------------------------------------
# The file's extension
# --------------------------------------------------------------------------
def contamination_hdu(c: Contamination):
    """The ``CONTAM`` binary table: one row per bin, the draws as a vector column."""
    from astropy.io import fits
    from astropy.table import Table

    cols = {"m_lo": c.m_edges[:-1], "m_hi": c.m_edges[1:], "fraction": c.fraction,
            "lo68": c.lower, "hi68": c.upper, "estimate": c.estimate,
            "n_injected": c.n_injected, "n_selected": c.n_selected, "n_eff": c.n_eff,
            "draws": c.draws.T}
    for f, v in c.family_estimate.items():
        cols[f"estimate_{f}"] = v
    h = fits.table_to_hdu(Table(cols))
    h.name = CONTAM_EXTNAME
    a, b, m0 = c.counts
    h.header["CNT_A"] = (a, "log10 dN/dm at CNT_M0 [arcmin-2 mag-1]")
    h.header["CNT_B"] = (b, "slope of log10 dN/dm [dex/mag]")
    h.header["CNT_M0"] = (m0, "pivot magnitude [AB]")
    h.header["ZMIN"] = (c.z_range[0], "interloper redshifts, lower end")
    h.header["ZMAX"] = (c.z_range[1], "interloper redshifts, upper end")
    h.header["FAMILIES"] = json.dumps(sorted(c.family_estimate))
    h.header["METHOD"] = ("beta-jeffreys-kish", "per-bin Beta posterior, Kish counts")
    return h


def read_contamination(hdul) -> Contamination | None:
    """The ``CONTAM`` extension of an open file, or None (a file written without interlopers)."""
    if CONTAM_EXTNAME not in hdul:
        return None
    h = hdul[CONTAM_EXTNAME]
    t = h.data
    hdr = h.header
    fams = json.loads(hdr.get("FAMILIES", "[]"))

    def col(name, dtype=float):
        return np.asarray(t[name]).astype(dtype)

    return Contamination(
        m_edges=np.append(col("m_lo"), col("m_hi")[-1]), fraction=col("fraction"),
        lower=col("lo68"), upper=col("hi68"), estimate=col("estimate"),
        draws=np.asarray(t["draws"], float).T.copy(), n_injected=col("n_injected", np.int64),
        n_selected=col("n_selected", np.int64), n_eff=col("n_eff"),
        counts=(float(hdr["CNT_A"]), float(hdr["CNT_B"]), float(hdr["CNT_M0"])),
        family_estimate={f: col(f"estimate_{f}") for f in fams},
        z_range=(float(hdr["ZMIN"]), float(hdr["ZMAX"])))


# --------------------------------------------------------------------------
# SelectionFunction's side
# --------------------------------------------------------------------------
@dataclass(frozen=True)
class ExpectedCountsWithInterlopers(ExpectedCounts):
    """:class:`ExpectedCounts` whose counts include the expected interlopers.

    Attributes
    ----------
    interlopers, interlopers_lower, interlopers_upper : ndarray (n_k,)
        The interlopers' part: median and interval over the contamination draws.
    """

    interlopers: np.ndarray = None
    interlopers_lower: np.ndarray = None
    interlopers_upper: np.ndarray = None


class ContaminationMixin:
    """What :class:`glaciar.SelectionFunction` knows about interlopers (its ``CONTAM``)."""

    #: The file's :class:`Contamination`, or None (no interlopers: section in the run).
    interlopers: Contamination | None = None

    def contamination(self, m_obs, which: str = "median") -> np.ndarray:
        """Fraction of interlopers passing the selection at measured magnitude(s) ``m_obs``.

        :meth:`Contamination.fraction_at` (0 outside the injected magnitudes).

        Raises
        ------
        ValueError
            The file holds no contamination (the run had no ``interlopers:`` section).
        """
        return self._contamination("contamination").fraction_at(m_obs, which)

    def expected_interlopers(self, m_obs_edges, area=None, draws: bool = False) -> np.ndarray:
        """Expected interlopers among the candidates per measured-magnitude bin.

        Ω ∫_bin n(m) f(m) dm, with Ω ``area`` [arcmin^2] (default the fit's).
        """
        c = self._contamination("expected_interlopers")
        if area is None:
            area = self.area_arcmin2()
            if area is None:
                raise ValueError("expected_interlopers: the fit records no area; pass area=")
        elif hasattr(area, "to_value"):
            area = area.to_value("arcmin2")
        return float(area) * c.surface_density(m_obs_edges, draws=draws)

    def _contamination(self, who: str) -> Contamination:
        if self.interlopers is None:
            raise ValueError(f"{who}: this selection function has no contamination (the run "
                             "had no interlopers: section; docs/contamination.md)")
        return self.interlopers

    def with_interlopers(self, ec: ExpectedCounts, interlopers=None, area=None,
                         interval: float = 0.68) -> ExpectedCounts:
        """``ec`` plus the expected interlopers: when ``interlopers`` is True, or None and the
        file holds a contamination; unchanged when False (or None without one)."""
        if interlopers is False or (interlopers is None and self.interlopers is None):
            return ec
        d = self.expected_interlopers(ec.m_obs_edges, area=area, draws=True)      # (D_c, n_k)
        q = np.quantile(d, [0.5, 0.5 - interval / 2, 0.5 + interval / 2], axis=0)
        if ec.draws is not None:
            per = ec.draws + d[np.arange(len(ec.draws)) % len(d)]
            t = np.quantile(per, [0.5, 0.5 - interval / 2, 0.5 + interval / 2], axis=0)
        else:
            per, t = None, (ec.median + q[0], ec.lower + q[1], ec.upper + q[2])
        base = {f.name: getattr(ec, f.name) for f in dataclasses.fields(ExpectedCounts)}
        base.update(median=t[0], lower=t[1], upper=t[2], draws=per)
        return ExpectedCountsWithInterlopers(**base, interlopers=q[0], interlopers_lower=q[1],
                                             interlopers_upper=q[2])
