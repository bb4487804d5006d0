"""Size- and UV-slope-aware selection functions: C(m, z | r_e) and S(z, m | beta).

Route: tabulation with the smooth fit's own machinery
------------------------------------------------------
The injections are split into ``n_bins`` quantile bins of the covariate x
(x = log10(r_eff / arcsec) for the size, x = beta for the UV slope), and the
model of the pooled fit (:class:`~glaciar.inference.models.SurfaceModel`: same
step shape, normalisation, degrees and reference depth) is fitted to each bin
on its own (:func:`glaciar.inference.fit.fit_surfaces`).  Between the bins'
mean covariates ("nodes") the parameters are interpolated linearly in x, draw
by draw (draw i of node k with draw i of node k+1: the bins' posteriors are
independent, so the pair is a draw of their product), and extrapolated linearly
from the two outer nodes up to the ends of the injected range:

    theta(x) = (1 - t) theta_k + t theta_{k+1},   t = (x - x_k) / (x_{k+1} - x_k).

m50(z), ln w(z) and logit C_max(z) are linear in theta, so this is a
piecewise-linear dependence of the step's position, width and height on
log r_e -- the depth-style shift m - k_r (log r_e - log r_ref), with a k_r that
may change from bin to bin and a width term, without a new likelihood.  The size
covariate acts on C only (the completeness block of theta), beta on S only (the
selection block: the Lyman-break colour of a source of given magnitude moves
with beta); the other block keeps the pooled fit's draws.

Behind a lens the ``magnification`` covariate (x = log10|mu|, on C: a more magnified source
is more stretched at fixed observed flux) is fitted by ``glaciar fit`` on lensed runs and
read by the lensed V_eff and count tables (:mod:`glaciar.inference.lensed`).  Its bins have
the quantile levels :data:`MAGNIFICATION_QUANTILES` (the effect is in the high-|mu| tail),
theta is held at the outer nodes beyond them, and there is no recentring pass.

Without a covariate value the pooled fit is used: C and S marginalised over the
injected distribution of r_e and beta at each (z, m), exactly what a fit
without covariates gives (the pooled fit *is* that fit, bit for bit).

For the size, within a bin the sources' sizes still differ (and correlate with M_UV
through the size-luminosity law): a second pass fits each bin again with every
source's magnitude moved to the bin's mean size, m - s (x - x_k), s = dm50/dx the
slope of a straight line through the first pass's node m50_0 (medians) -- the
depth-style shift within each bin -- so that each node's fit is C at x_k, not the
bin's mixture (which is wider and, with a size-luminosity slope, displaced).

Each bin is checked by the posterior-predictive check of
:mod:`glaciar.inference.diagnostics`, with every source evaluated at its own
covariate through the interpolation (the model that is used, not the bin's fit
alone): for the size, on the recovered counts; for beta, on the selected ones.

Effective volume re-weighted to another size law or beta distribution
---------------------------------------------------------------------
V_eff(m) = Σ_j Ω_j ∫ dz dV/dz/dΩ <C(m, z | x, d_j)>_size <S(z, m | beta, d_j)>_beta,
with <.>_size the average over log r_e ~ N(mu(M_UV, z), sigma) of a
:class:`SizeRelation` (M_UV from m through the injections' spectra for an
apparent-magnitude fit) and <.>_beta over N(mean, sd) (:class:`BetaDistribution`).
Each average is exact for the piecewise-linear interpolant of the integrand on
``n_nodes`` equally spaced covariate nodes over the injected range (hat
functions integrated against the normal in closed form); the probability of
the law outside the injected range is assigned to the end nodes and warned about
when it exceeds :data:`OUTSIDE_WARN` (the fit says nothing there).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.special import ndtr

from ..constants import COL_BETA, COL_MAGNIFICATION, COL_R_EFF_ARCSEC

__all__ = ["COVARIATES", "CovariateSpec", "CovariateNodes", "SizeRelation", "BetaDistribution",
           "parse_covariates", "fit_covariate_nodes", "covariate_theta", "evaluate",
           "reweighted_volume_draws", "hat_weights", "OUTSIDE_WARN", "DEFAULT_BINS",
           "MAGNIFICATION_QUANTILES"]

#: Quantile bins per covariate (the nodes of the interpolation).
DEFAULT_BINS = 4
#: Fraction of a re-weighting law outside the injected covariate range that is warned about.
OUTSIDE_WARN = 0.05
#: Equally spaced covariate nodes of the re-weighted V_eff integrals.
VOLUME_NODES = 17
#: Quantile levels of the magnification bins' edges (behind a cluster ~90 % of the area has
#: |mu| < 2, where C hardly depends on it; the last bins hold the tail where it does).
MAGNIFICATION_QUANTILES = (0.0, 0.4, 0.75, 0.9, 0.97, 1.0)


@dataclass(frozen=True)
class CovariateSpec:
    """One covariate: its per-source column, its transform, the block of theta it moves."""

    name: str
    column: str
    log: bool
    block: str
    label: str
    #: Use |value| (the signed magnification: negative for odd-parity images).
    absolute: bool = False
    #: theta(x) beyond the outer bins' centres: extrapolated linearly (True) or held at the
    #: outer node (False: the outer bin's fit, for a skewed x whose tail bin is wide).
    extrapolate: bool = True
    #: Second pass moving each source to its bin's mean x along a straight-line m50(x)
    #: (for a covariate whose effect is close to a magnitude shift linear in x).
    recentre: bool = True

    @property
    def transform(self) -> str:
        """The file's ``COVXFORM``: how x follows from the column."""
        return ("log10abs" if self.absolute else "log10") if self.log else "none"

    def to_x(self, value):
        """The interpolation coordinate of ``value`` (log10 for the size, log10|mu|)."""
        v = np.asarray(value, float)
        if self.absolute:
            v = np.abs(v)
        if self.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.where(v > 0, np.log10(np.where(v > 0, v, 1.0)), np.nan)
        return v


COVARIATES = {
    "r_eff": CovariateSpec("r_eff", COL_R_EFF_ARCSEC, True, "c", "log10(r_eff_arcsec / arcsec)"),
    "beta": CovariateSpec("beta", COL_BETA, False, "s", "UV slope beta"),
    # Behind a lens, at fixed observed magnitude a more magnified source is more stretched
    # (lower surface brightness): C depends on |mu| (glaciar.inference.lensed).
    # Its effect is strongly non-linear (C falls at |mu| > 2) and most injections are weakly
    # magnified: bins by quantile levels that resolve the tail (MAGNIFICATION_QUANTILES),
    # held at the end nodes rather than extrapolated, without the straight-line recentring.
    "magnification": CovariateSpec("magnification", COL_MAGNIFICATION, True, "c", "log10|mu|",
                                   absolute=True, extrapolate=False, recentre=False),
}


def parse_covariates(value) -> tuple[str, ...]:
    """``"r_eff,beta"`` or a list of names -> validated tuple (``()`` for none)."""
    if value is None:
        return ()
    names = [s.strip() for s in (value.split(",") if isinstance(value, str) else value)]
    names = [s for s in names if s]
    bad = [s for s in names if s not in COVARIATES]
    if bad:
        raise ValueError(f"covariates: unknown name(s) {bad}; expected some of {sorted(COVARIATES)}")
    return tuple(dict.fromkeys(names))


@dataclass(frozen=True)
class CovariateNodes:
    """The per-bin fits of one covariate (file extension ``CV_<NAME>``).

    Attributes
    ----------
    name : str
        Key of :data:`COVARIATES`.
    centres : ndarray (K,)
        Mean covariate x of each bin's sources (the interpolation nodes), increasing.
    edges : ndarray (K + 1,)
        Bin edges in x (the injected minimum and maximum at the ends).
    draws : ndarray (K, D, P)
        Posterior draws of each bin's fit (parameters of the pooled fit's model).
    n_sources, n_cells, n_extreme : ndarray of int (K,)
        Sources per bin, its PPC cells and how many are extreme.
    adequate : ndarray of bool (K,)
        PPC verdict per bin (interpolated model against the bin's flags).
    """

    name: str
    centres: np.ndarray
    edges: np.ndarray
    draws: np.ndarray
    n_sources: np.ndarray
    n_cells: np.ndarray
    n_extreme: np.ndarray
    adequate: np.ndarray
    extra: dict = field(default_factory=dict)

    @property
    def spec(self) -> CovariateSpec:
        return COVARIATES[self.name]

    @property
    def covered(self) -> tuple[float, float]:
        """The injected range of x (the file's ``COVMIN``, ``COVMAX``)."""
        return float(self.edges[0]), float(self.edges[-1])

    def theta_at(self, x: float) -> np.ndarray:
        """Per-draw parameters at covariate x (linear in x between nodes; beyond them
        too, or held at the outer node for a covariate that does not extrapolate)."""
        c, d = self.centres, self.draws
        if len(c) == 1:
            return d[0].copy()
        if not self.spec.extrapolate:
            x = float(np.clip(x, c[0], c[-1]))
        k = int(np.clip(np.searchsorted(c, x) - 1, 0, len(c) - 2))
        t = (float(x) - c[k]) / (c[k + 1] - c[k])
        return (1.0 - t) * d[k] + t * d[k + 1]


# ------------------------------------------------------------------------ evaluation
def covariate_theta(sf, values: dict) -> np.ndarray:
    """The pooled fit's draws with the blocks of the given covariates replaced.

    Parameters
    ----------
    sf : glaciar.SelectionFunction
    values : dict
        ``{name: x}`` (x in interpolation units: log10 arcsec for r_eff).
    """
    n = min([len(sf.draws)] + [sf.covariates[k].draws.shape[1] for k in values])
    th = sf.draws[:n].copy()
    for name, x in values.items():
        nodes = sf.covariates[name]
        idx = sf.model.block_indices(nodes.spec.block)
        th[:, idx] = nodes.theta_at(x)[:n, idx]
    return th


def _check_given(sf, given):
    for name in given:
        if name not in getattr(sf, "covariates", {}):
            kw = {"r_eff": "r_eff_arcsec", "magnification": "magnification"}.get(name, name)
            raise ValueError(f"{kw}=: this selection function was fitted without the {name!r} "
                             f"covariate (fit it with `glaciar fit --covariates {name}`)")
        if COVARIATES[name].block == "s" and not sf.model.selection:
            raise ValueError(f"{name}=: a detection-only fit has S = 1; there is no {name} dependence")


def _one_like(sf, theta):
    return type(sf)(sf.model, theta, meta=sf.meta, field=sf.field, depth_area=sf.depth_area,
                    domain=sf.domain, sed=sf.sed)


def evaluate(sf, which, m, z, depth, field, draws, outside, **given):
    """C, S or P at covariate values (the work of ``SelectionFunction.completeness`` & co.).

    ``given``: ``r_eff_arcsec`` [arcsec] and/or ``beta``, broadcast with m, z (and
    depth).  Outside the injected covariate range the value is NaN unless
    ``outside="extrapolate"``.
    """
    vals = {("r_eff" if k == "r_eff_arcsec" else k): v for k, v in given.items() if v is not None}
    _check_given(sf, vals)
    names = list(vals)
    xs = [COVARIATES[k].to_x(vals[k]) for k in names]
    arrs = np.broadcast_arrays(np.asarray(m, float), np.asarray(z, float), *xs,
                               *([] if depth is None else [np.asarray(depth, float)]))
    shape = arrs[0].shape
    flat = [a.ravel() for a in arrs]
    mm, zz, xx = flat[0], flat[1], np.column_stack(flat[2:2 + len(names)])
    dd = flat[-1] if depth is not None else None
    n = min([len(sf.draws)] + [sf.covariates[k].draws.shape[1] for k in names])
    out = np.full((n, mm.size), np.nan)
    ok = np.all(np.isfinite(xx), axis=1)
    if ok.any():
        uniq, inv = np.unique(xx[ok], axis=0, return_inverse=True)
        where = np.flatnonzero(ok)
        for i, u in enumerate(uniq):
            sel = where[inv.ravel() == i]
            one = _one_like(sf, covariate_theta(sf, dict(zip(names, u))))
            dsub = None if dd is None else dd[sel]
            if which == "C":
                v = one.completeness(mm[sel], zz[sel], dsub, field=field, draws=True, outside=outside)
            elif which == "S":
                v = one.selection_given_recovered(zz[sel], mm[sel], dsub, field=field, draws=True,
                                                  outside=outside)
            else:
                v = one.selection_probability(zz[sel], mm[sel], dsub, field=field, draws=True,
                                              outside=outside)
            out[:, sel] = v
    if outside == "nan":
        for j, k in enumerate(names):
            lo, hi = sf.covariates[k].covered
            tol = 1e-9 * max(1.0, abs(hi))
            out[:, (xx[:, j] < lo - tol) | (xx[:, j] > hi + tol)] = np.nan
    out = out.reshape((n,) + shape)
    return out if draws else np.median(out, axis=0)


# ------------------------------------------------------------------------ re-weighting
@dataclass(frozen=True)
class SizeRelation:
    """A size-luminosity relation: log10 r_e ~ N(log10 median, r_eff_scatter_dex).

    median r_e = r_eff_kpc_z6 ((1+z)/7)^size_evolution 10^(-0.4 size_luminosity_slope (M_UV + 21))
    [proper kpc], the form and the names of the configuration's ``source:`` section
    (:func:`glaciar.galaxy.population.r_eff_kpc`).
    """

    r_eff_kpc_z6: float = 1.075
    size_evolution: float = -1.0
    size_luminosity_slope: float = 0.0
    r_eff_scatter_dex: float = 0.0

    def __post_init__(self):
        if not (self.r_eff_kpc_z6 > 0 and np.isfinite(self.r_eff_kpc_z6)):
            raise ValueError(f"SizeRelation: r_eff_kpc_z6 must be > 0, not {self.r_eff_kpc_z6}")
        if not (self.r_eff_scatter_dex >= 0):
            raise ValueError(f"SizeRelation: r_eff_scatter_dex must be >= 0, not "
                             f"{self.r_eff_scatter_dex}")

    def log_r_arcsec(self, M_uv, z, cosmology="Planck18") -> np.ndarray:
        """log10 of the median r_e [arcsec] at absolute magnitude ``M_uv`` and redshift ``z``."""
        from ..galaxy.population import SourceModel, kpc_to_arcsec, r_eff_kpc

        src = SourceModel(r_eff_kpc_z6=self.r_eff_kpc_z6, size_evolution=self.size_evolution,
                          size_luminosity_slope=self.size_luminosity_slope)
        z = np.asarray(z, float)
        M = np.asarray(M_uv, float)
        r = r_eff_kpc(np.broadcast_to(z, np.broadcast_shapes(z.shape, M.shape)), src, M)
        return np.log10(kpc_to_arcsec(r, z, cosmology))


@dataclass(frozen=True)
class BetaDistribution:
    """UV slope beta ~ N(mean, sd)."""

    mean: float = -2.0
    sd: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.mean) and self.sd >= 0):
            raise ValueError(f"BetaDistribution: need a finite mean and sd >= 0, not "
                             f"{self.mean}, {self.sd}")


def hat_weights(nodes, mu, sigma):
    """Weights of equally spaced ``nodes`` for the N(mu, sigma) average of a piecewise-linear
    function, and the probability outside [nodes[0], nodes[-1]] (given to the end nodes).

    Exact: each hat function is integrated against the normal in closed form.

    Returns
    -------
    w : ndarray, shape mu.shape + (K,)
        Weights summing to 1.
    outside : ndarray, shape mu.shape
    """
    x = np.asarray(nodes, float)
    mu = np.asarray(mu, float)[..., None]
    s = max(float(sigma), 1e-9)

    def G(u):                                       # P(X < u)
        return ndtr((u - mu) / s)

    def H(u):                                       # E[(X - mu) 1(X < u)]
        t = (u - mu) / s
        return -s * np.exp(-0.5 * t * t) / np.sqrt(2 * np.pi)

    K = len(x)
    w = np.zeros(mu.shape[:-1] + (K,))
    if K == 1:
        w[..., 0] = 1.0
        return w, np.zeros(mu.shape[:-1])
    a, b = x[:-1], x[1:]
    h = b - a
    g = G(b) - G(a)
    hb = H(b) - H(a)
    rise = (hb + (mu - a) * g) / h                  # ∫ (X - a)/h on [a, b]
    w[..., 1:] += rise
    w[..., :-1] += g - rise
    below, above = G(x[0])[..., 0], 1.0 - G(x[-1])[..., 0]
    w[..., 0] += below
    w[..., -1] += above
    return w, below + above


def _muv_of(sf, zz, mm):
    """M_UV at (z, m) (n_z, n_m): m itself for an absolute fit, else through the injections' SED."""
    if sf.magnitude_type == "absolute":
        return np.broadcast_to(mm[None, :], (len(zz), len(mm)))
    if sf.sed is None:
        raise ValueError("effective_volume(size_relation=...): the file records no injection "
                         "spectra (DETFILT) to turn m into M_UV; refit with this glaciar")
    from .products import kcorrection

    k = kcorrection(zz, [sf.sed.beta_mean], sf.sed.detection_filter, igm=sf.sed.igm,
                    cosmology=sf.sed.cosmology)[:, 0]
    # Where the band receives no flux the size is irrelevant (nothing is detected there).
    return np.where(np.isfinite(k)[:, None], mm[None, :] - np.where(np.isfinite(k), k, 0)[:, None],
                    -21.0)


def reweighted_volume_draws(sf, nodes, node_sr, zz, dvdz, mm, size_relation=None,
                            beta_distribution=None, n_nodes: int = VOLUME_NODES):
    """V_eff(m) per draw with C averaged over a size law and S over a beta distribution.

    Parameters
    ----------
    sf : glaciar.SelectionFunction
        With the covariates the laws need (:attr:`covariates`).
    nodes, node_sr, zz, dvdz, mm
        As :func:`glaciar.inference.volume.volume_draws`.
    size_relation : SizeRelation, optional
    beta_distribution : BetaDistribution, optional
    n_nodes : int
        Covariate nodes over the injected range.

    Returns
    -------
    ndarray, shape (n_draws, len(mm))
        V_eff [Mpc^3].
    """
    from scipy.integrate import simpson

    from .volume import M_BATCH

    given = {}
    if size_relation is not None:
        given["r_eff"] = size_relation
    if beta_distribution is not None:
        given["beta"] = beta_distribution
    _check_given(sf, given)
    parts = {}                                     # block -> (thetas per node, weights (n_z, n_m, K))
    for name, law in given.items():
        cov = sf.covariates[name]
        lo, hi = cov.covered
        xk = np.linspace(lo, hi, int(n_nodes))
        if name == "r_eff":
            cosmo = sf.sed.cosmology if sf.sed is not None else "Planck18"
            mu = size_relation.log_r_arcsec(_muv_of(sf, zz, mm), zz[:, None], cosmo)
            w, out = hat_weights(xk, mu, law.r_eff_scatter_dex)
            what = f"r_e {10 ** lo:.3g}-{10 ** hi:.3g} arcsec"
        else:
            w, out = hat_weights(xk, np.full((len(zz), len(mm)), law.mean), law.sd)
            what = f"beta {lo:.3g} to {hi:.3g}"
        if np.max(out) > OUTSIDE_WARN:
            warnings.warn(f"effective_volume: up to {np.max(out):.0%} of the {name} law lies outside "
                          f"the injected range ({what}); it is given the nearest injected "
                          "value's selection (simulate a wider range to cover it)", stacklevel=3)
        parts[cov.spec.block] = ([covariate_theta(sf, {name: x}) for x in xk], w)
    n = min(len(t) for th, _ in parts.values() for t in th) if parts else len(sf.draws)
    model = sf.model
    out = np.zeros((n, mm.size))
    for dj, sr in zip(nodes, node_sr):
        mrel = model.relative_magnitude(mm, dj)
        for i in range(0, n, M_BATCH):
            sl = slice(i, min(i + M_BATCH, n))
            c0, s0 = model.surfaces_on_grid(sf.draws[sl], zz, mrel)
            avg = {}
            for block, (ths, w) in parts.items():
                acc = 0.0
                for k, th in enumerate(ths):
                    c, s = model.surfaces_on_grid(th[sl], zz, mrel)
                    acc = acc + w[None, :, :, k] * (c if block == "c" else s)
                avg[block] = acc
            p = avg.get("c", c0) * avg.get("s", s0)
            out[sl] += simpson(p * dvdz[None, :, None], x=zz, axis=1) * sr
    return out


# ------------------------------------------------------------------------ fitting
def fit_covariate_nodes(rows, name, model, *, n_bins: int = DEFAULT_BINS, seed=0,
                        max_draws: int = 1000, mag_col: str = "mag_input",
                        mag_resolution=0.01, fit=None, quantiles=None) -> CovariateNodes:
    """Fit the pooled fit's model to each quantile bin of a covariate, and check the result.

    Parameters
    ----------
    rows : pandas.DataFrame
        Per-source rows: ``z``, ``mag_col``, ``recovered``, ``selected``, the
        covariate's column (:data:`COVARIATES`), ``depth_local`` for a
        depth-aware model and ``mag`` (the nominal magnitude, for the PPC cells).
    name : {"r_eff", "beta", "magnification"}
    model : SurfaceModel
        The pooled fit's model (every bin uses it: same shape, normalisation, degrees).
    n_bins : int
        Quantile bins (>= 1).
    seed : int
        Bin k is sampled with seed ``[seed, 7919, k]``.
    max_draws : int
        Draws kept per bin.
    fit : callable, optional
        ``fit(cells, model, seed) -> FitResult`` (default :func:`fit_surfaces`).
    quantiles : sequence of float, optional
        Quantile levels of the bin edges (from 0 to 1), instead of ``n_bins`` equal ones.

    Raises
    ------
    ValueError
        The rows lack the covariate's column, or the injections do not vary in it
        (a single size: set ``source.r_eff_scatter_dex`` or ``size_distribution``).
    """
    from .diagnostics import ppc_cells, ppc_verdict
    from .fit import aggregate_cells, fit_surfaces

    spec = COVARIATES[name]
    if spec.column not in rows.columns:
        raise ValueError(f"covariate {name!r}: the per-source table has no {spec.column!r} column")
    x = spec.to_x(rows[spec.column].to_numpy(float))
    good = np.isfinite(x)
    rows, x = rows[good].reset_index(drop=True), x[good]
    if x.size == 0 or np.ptp(x) < 1e-6:
        hint = {"r_eff": "simulate with source.r_eff_scatter_dex > 0",
                "beta": "set source.beta_sd > 0 with beta_per: source"}.get(
                    name, "a lensed run (survey.lens) spans a range of magnification")
        raise ValueError(f"covariate {name!r}: the injections span no range of {spec.column} "
                         f"(all {10 ** x[0] if spec.log and x.size else (x[0] if x.size else 'NaN')}); "
                         f"{hint}")
    n_bins = max(1, int(n_bins))
    levels = np.linspace(0.0, 1.0, n_bins + 1) if quantiles is None else np.asarray(quantiles, float)
    edges = np.quantile(x, levels)
    edges = np.unique(edges)
    k_of = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    if fit is None:
        def fit(cells, mdl, s):
            return fit_surfaces(cells, mdl, seed=s)
    present = [k for k in range(len(edges) - 1) if np.any(k_of == k)]
    centres = np.array([float(np.mean(x[k_of == k])) for k in present])
    nsrc = [int(np.sum(k_of == k)) for k in present]
    shift = np.zeros(len(x))
    two = spec.block == "c" and spec.recentre and len(present) > 1
    for attempt in range(2 if two else 1):
        draws = []
        for j, k in enumerate(present):
            sel = (k_of == k)
            sub = rows[sel].copy()
            # Second pass: each source's magnitude moved to its bin's mean size through the
            # first pass's local slope dm50/dx, so the bin's fit describes C at the node
            # rather than the mixture of the bin's sizes (which also correlate with M_UV).
            sub[mag_col] = sub[mag_col].to_numpy(float) - shift[sel]
            cells = aggregate_cells(sub, mag_resolution, model.depth_ref, mag_col)
            draws.append(fit(cells, model, [int(seed), 7919 + attempt, k]).draws(max_draws))
        if attempt == 0 and two:
            m50 = np.array([np.median(d[:, model.param_names.index("m50_0")]) for d in draws])
            # One straight-line slope through the nodes: the nodes' first-pass m50 are
            # the biased mixtures this pass removes, too noisy for local differences.
            slope = np.polyfit(centres, m50, 1)[0]             # dm50 / dx
            j_of = np.searchsorted(present, k_of)
            shift = slope * (x - centres[j_of])
    n = min(len(d) for d in draws)
    nodes = CovariateNodes(name=name, centres=centres, edges=edges,
                           draws=np.stack([d[:n] for d in draws]), n_sources=np.array(nsrc),
                           n_cells=np.zeros(len(centres), int), n_extreme=np.zeros(len(centres), int),
                           adequate=np.ones(len(centres), bool))
    # PPC per bin: each source at its own covariate, through the interpolation.
    depth = rows["depth_local"].to_numpy(float) if model.depth_ref is not None else None
    z = rows["z"].to_numpy(float)
    m = rows[mag_col].to_numpy(float)
    mnom = rows["mag"].to_numpy(float) if "mag" in rows.columns else np.round(m / 0.25) * 0.25
    rec = rows["recovered"].to_numpy().astype(bool)
    sel_ = rows["selected"].to_numpy().astype(bool)
    n_ppc = min(n, 400)

    def per_source(idx, which):
        out = np.empty((n_ppc, len(idx)))
        for j, i in enumerate(idx):
            th = nodes.theta_at(x[i])[:n_ppc]
            d = None if depth is None else depth[i]
            out[:, j] = (model.completeness(th, m[i], z[i], d) if which == "c"
                         else model.selection_given_recovered(th, z[i], m[i], d))
        return out

    extreme_col = "ppc_p_rec" if spec.block == "c" else "ppc_p_sel"
    cells_n, ext, ade = [], [], []
    for k in range(len(edges) - 1):
        idx = np.flatnonzero(k_of == k)
        if not idx.size:
            continue
        table = ppc_cells(z[idx], mnom[idx], model.relative_magnitude(m[idx], None if depth is None
                                                                      else depth[idx]),
                          rec[idx], sel_[idx], lambda j, idx=idx: per_source(idx[j], "c"),
                          lambda j, idx=idx: per_source(idx[j], "s"))
        p = np.asarray(table[extreme_col], float)
        table["extreme"] = (p < 0.01) | (p > 0.99)
        v = ppc_verdict(table)
        cells_n.append(v["n_cells"])
        ext.append(v["n_extreme"])
        ade.append(v["adequate"])
    return CovariateNodes(name=name, centres=nodes.centres, edges=edges, draws=nodes.draws,
                          n_sources=nodes.n_sources, n_cells=np.array(cells_n),
                          n_extreme=np.array(ext), adequate=np.array(ade, bool))


# ------------------------------------------------------------------------ file extensions
def _ext_name(name: str) -> str:
    return f"CV_{name.upper()}"


def covariate_hdus(sf, extver: int) -> list:
    """The ``CV_<NAME>`` image extensions of one fit (none without covariates).

    Data: float64, numpy shape (K, n_draws, n_params): the draws of each bin's fit, columns
    in the order of the fit's ``DRAWS`` table.  Header: the covariate (``COVNAME``, its
    column ``COVCOL``, transform ``COVXFORM``: x = log10(value) (``log10``), log10|value|
    (``log10abs``, the magnification) or x = value (``none``), the block
    of theta it replaces ``COVBLOCK``), the injected range ``COVMIN``/``COVMAX`` of x,
    ``NNODES`` and per node k (1-based) ``NODEk`` (mean x of the bin), ``EDGEk``
    (``EDGE0``..``EDGEK``: bin edges in x), ``NSRCk``, ``NCELLk``, ``NEXTk``, ``ADEQk`` (PPC).
    """
    from astropy.io import fits

    out = []
    for name, cov in sorted(getattr(sf, "covariates", {}).items()):
        h = fits.ImageHDU(np.asarray(cov.draws, float), name=_ext_name(name), ver=extver)
        hh = h.header
        sp = cov.spec
        hh["FIELD"] = sf.field
        hh["COVNAME"] = (name, "covariate")
        hh["COVCOL"] = (sp.column, "per-source column of the covariate")
        hh["COVXFORM"] = (sp.transform, "x = log10(value), log10(|value|) or value")
        hh["COVBLOCK"] = (sp.block, "c: C parameters; s: S parameters")
        lo, hi = cov.covered
        hh["COVMIN"] = (lo, "injected range of x, lower end")
        hh["COVMAX"] = (hi, "injected range of x, upper end")
        hh["NNODES"] = len(cov.centres)
        for k, e in enumerate(cov.edges):
            hh[f"EDGE{k}"] = float(e)
        for k in range(len(cov.centres)):
            hh[f"NODE{k + 1}"] = (float(cov.centres[k]), "mean x of the bin's sources")
            hh[f"NSRC{k + 1}"] = int(cov.n_sources[k])
            hh[f"NCELL{k + 1}"] = int(cov.n_cells[k])
            hh[f"NEXT{k + 1}"] = int(cov.n_extreme[k])
            hh[f"ADEQ{k + 1}"] = bool(cov.adequate[k])
        hh["COMMENT"] = "axis 3: bin (node); axis 2: posterior draw; axis 1: DRAWS column"
        out.append(h)
    return out


def read_covariates(hdul, extver: int) -> dict:
    """``{name: CovariateNodes}`` of fit ``extver`` (empty for files without ``CV_*``)."""
    out = {}
    for name in COVARIATES:
        if (_ext_name(name), extver) not in hdul:
            continue
        h = hdul[_ext_name(name), extver]
        hh = h.header
        K = int(hh["NNODES"])
        out[name] = CovariateNodes(
            name=name, centres=np.array([float(hh[f"NODE{k + 1}"]) for k in range(K)]),
            edges=np.array([float(hh[f"EDGE{k}"]) for k in range(K + 1)]),
            draws=np.asarray(h.data, float),
            n_sources=np.array([int(hh[f"NSRC{k + 1}"]) for k in range(K)]),
            n_cells=np.array([int(hh[f"NCELL{k + 1}"]) for k in range(K)]),
            n_extreme=np.array([int(hh[f"NEXT{k + 1}"]) for k in range(K)]),
            adequate=np.array([bool(hh[f"ADEQ{k + 1}"]) for k in range(K)]))
    return out
