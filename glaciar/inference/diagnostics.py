"""Does the fit describe the data?  Posterior-predictive checks, PSIS-LOO, edge checks.

Arrays in, results out; no file I/O.

* :func:`ppc_cells` -- binned fractions beside the model, per simulated cell
  (z, nominal magnitude, depth bin), with posterior-predictive mid-p values;
  :func:`ppc_verdict` turns them into the "adequate" verdict (separate from
  the chains' "converged").
* :func:`psis_loo` -- Pareto-smoothed importance-sampling leave-one-out
  (Vehtari, Gelman & Gabry 2017) over aggregated cells, for model comparison.
* :func:`edge_report` -- whether C*S has fallen to ~0 at the ends of the
  simulated redshift range (otherwise V_eff misses volume).
"""
from __future__ import annotations

import numpy as np
from scipy import stats
from scipy.special import logsumexp

__all__ = ["PPC_EXTREME", "ppc_cells", "ppc_verdict", "psis_loo", "compare_models",
           "edge_report"]

#: A cell is "extreme" when its posterior-predictive mid-p value is below this or
#: above 1 minus this (two-sided 2 %).
PPC_EXTREME = 0.01
#: Depth bins of the posterior-predictive check [mag].
PPC_DEPTH_BIN = 0.25


def ppc_cells(z, mag_nominal, mag_covariate, recovered, selected, c_fn, s_fn, depth=None,
              depth_bin: float = PPC_DEPTH_BIN, counts=None) -> np.ndarray:
    """Binned fractions beside the fitted surfaces, per simulated cell.

    Cells are (z, nominal magnitude) and, when ``depth`` is given, local-depth
    bins of ``depth_bin`` mag.  For each cell: ``n``, ``k_rec``, ``k_sel``;
    binned estimates ``c_binned = (k_rec+1)/(n+2)``, ``s_binned =
    (k_sel+1)/(k_rec+2)``, ``p_binned = (k_sel+1)/(n+2)`` with 16/84 % Beta
    quantiles; the model's posterior median and 16/84 % of C, S and C*S
    averaged over the cell's sources; and posterior-predictive mid-p values
    of ``k_rec`` and ``k_sel`` (binomial replicates with the cell-mean
    probability of each draw; near 0 or 1 flags misfit).

    Parameters
    ----------
    z, mag_nominal, mag_covariate : array_like (N,)
        Per source: redshift, the task's nominal magnitude, the fitted
        magnitude covariate [mag].
    recovered, selected : array_like of bool (N,)
    c_fn, s_fn : callable
        ``c_fn(idx)`` and ``s_fn(idx)`` return C and S of the posterior draws
        for the sources ``idx``, shape (n_draws, len(idx)).
    depth : array_like (N,), optional
        Local depth [AB mag] of each source.
    counts : array_like of int (N,), optional
        Entries are groups of ``counts`` sources (stored counts) instead of
        single sources: ``recovered`` and ``selected`` are then the groups'
        counts, and C and S are evaluated at the group's mean covariates
        (within a group the covariate spans <= 0.06 mag, so the cell means
        differ from per-source ones by O(C'' * 0.06^2 / 12)).

    Returns
    -------
    numpy structured array
    """
    z = np.asarray(z, float)
    mn = np.asarray(mag_nominal, float)
    w = np.ones(len(z)) if counts is None else np.asarray(counts, float)
    rec = np.asarray(recovered, bool) if counts is None else np.asarray(recovered, float)
    sel = np.asarray(selected, bool) if counts is None else np.asarray(selected, float)
    dbin = (np.floor(np.asarray(depth, float) / depth_bin) if depth is not None
            else np.zeros(len(z)))
    keys = np.stack([z, mn, np.where(np.isfinite(dbin), dbin, -1e9)], axis=1)
    ukeys, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    nc = len(ukeys)
    n = np.bincount(inv, weights=w, minlength=nc).astype(np.int64)
    kr = np.bincount(inv, weights=rec, minlength=nc).astype(np.int64)
    ks = np.bincount(inv, weights=sel, minlength=nc).astype(np.int64)
    mcov = np.bincount(inv, weights=w * np.asarray(mag_covariate, float), minlength=nc) / n
    out = {"z": ukeys[:, 0], "mag": ukeys[:, 1],
           "depth_lo": np.where(ukeys[:, 2] > -1e8, ukeys[:, 2] * depth_bin, np.nan)
           if depth is not None else np.full(nc, np.nan),
           "mag_covariate_mean": mcov, "n": n, "k_rec": kr, "k_sel": ks}
    for name, k, nn in (("c", kr, n), ("s", ks, kr), ("p", ks, n)):
        out[f"{name}_binned"] = (k + 1.0) / (nn + 2.0)
        out[f"{name}_binned_q16"] = stats.beta.ppf(0.16, k + 1, nn - k + 1)
        out[f"{name}_binned_q84"] = stats.beta.ppf(0.84, k + 1, nn - k + 1)
    # Cell means of C and C*S per draw, summed over sources in chunks (bounded memory).
    from scipy.sparse import csr_matrix
    onehot = csr_matrix((w, (np.arange(len(z)), inv)), shape=(len(z), nc))
    sums = None
    for a in range(0, len(z), 20000):
        idx = np.arange(a, min(a + 20000, len(z)))
        c, s = c_fn(idx), s_fn(idx)
        part = np.stack([(onehot[idx].T @ c.T).T, (onehot[idx].T @ (c * s).T).T])
        sums = part if sums is None else sums + part
    c_mean, p_mean = sums[0] / n, sums[1] / n
    cm = np.stack([c_mean, p_mean / np.maximum(c_mean, 1e-300), p_mean])   # C, S, P
    for i, name in enumerate(("c", "s", "p")):
        q = np.quantile(cm[i], [0.5, 0.16, 0.84], axis=0)
        out[f"{name}_model"], out[f"{name}_model_q16"], out[f"{name}_model_q84"] = q
    for name, k, nn, p in (("rec", kr, n, cm[0]), ("sel", ks, kr, cm[1])):
        # scipy's binomial pmf overflows (boost ibeta_derivative) for p ~ 1e-26; a
        # probability clipped at 1e-12 changes no mid-p value at the precision it is used.
        p = np.clip(p, 1e-12, 1.0 - 1e-12)
        midp = stats.binom.sf(k, nn, p) + 0.5 * stats.binom.pmf(k, nn, p)
        out[f"ppc_p_{name}"] = midp.mean(axis=0)
    rec_ext = (out["ppc_p_rec"] < PPC_EXTREME) | (out["ppc_p_rec"] > 1 - PPC_EXTREME)
    sel_ext = kr > 0
    sel_ext &= (out["ppc_p_sel"] < PPC_EXTREME) | (out["ppc_p_sel"] > 1 - PPC_EXTREME)
    out["extreme"] = rec_ext | sel_ext
    dtype = [(k, np.asarray(v).dtype if k not in ("extreme",) else bool) for k, v in out.items()]
    arr = np.empty(nc, dtype=dtype)
    for k, v in out.items():
        arr[k] = v
    return arr


def ppc_verdict(ppc: np.ndarray, alpha: float = 0.01) -> dict:
    """The "adequate" verdict of a posterior-predictive table.

    A cell is extreme when either mid-p value (recovered, or selected among
    the recovered) is beyond :data:`PPC_EXTREME` on either side; under an
    adequate model each is so with probability <= 2 * PPC_EXTREME (posterior-
    predictive p values are, if anything, conservative), so at most
    4 * PPC_EXTREME of the cells.  The fit is *adequate* unless more cells are
    extreme than the ``1 - alpha`` quantile of Binomial(n_cells, 4 PPC_EXTREME).

    Returns
    -------
    dict
        ``n_cells``, ``n_extreme``, ``fraction_extreme``, ``max_allowed``,
        ``adequate`` (bool).
    """
    n = int(len(ppc))
    k = int(np.sum(ppc["extreme"])) if n else 0
    allowed = int(stats.binom.isf(alpha, n, 4 * PPC_EXTREME)) if n else 0
    return {"n_cells": n, "n_extreme": k, "fraction_extreme": k / n if n else 0.0,
            "max_allowed": allowed, "adequate": bool(k <= allowed)}


# --------------------------------------------------------------------------
# PSIS-LOO
# --------------------------------------------------------------------------
def _gpd_fit(x):
    """Generalised Pareto (shape k, scale sigma) of exceedances ``x`` (sorted, > 0).

    The empirical-Bayes estimator of Zhang & Stephens (2009) with the weakly
    informative shrinkage of k toward 0.5 used in PSIS (Vehtari et al. 2017,
    appendix).
    """
    n = len(x)
    m = 30 + int(np.sqrt(n))
    b = 1.0 - np.sqrt(m / (np.arange(1, m + 1) - 0.5))
    b /= 3.0 * x[int(n / 4 + 0.5) - 1]
    b += 1.0 / x[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.mean(np.log1p(-b[:, None] * x), axis=1)
        ll = n * (np.log(-b / k) - k - 1.0)
    w = 1.0 / np.sum(np.exp(ll[None, :] - ll[:, None]), axis=1)
    w = np.where(np.isfinite(w), w, 0.0)
    w /= w.sum()
    bb = np.sum(b * w)
    kk = np.mean(np.log1p(-bb * x))
    sigma = -kk / bb
    kk = (n * kk + 10 * 0.5) / (n + 10)
    return kk, sigma


def _gpd_quantile(p, k, sigma):
    if abs(k) < 1e-12:
        return -sigma * np.log1p(-p)
    return sigma * np.expm1(-k * np.log1p(-p)) / k


def _psis_log_weights(log_ratio):
    """Pareto-smoothed log importance weights (normalised) and the shape k-hat."""
    lw = np.asarray(log_ratio, float) - np.max(log_ratio)
    s = len(lw)
    n_tail = int(np.ceil(min(0.2 * s, 3.0 * np.sqrt(s))))
    order = np.argsort(lw)
    k_hat = np.inf
    if n_tail >= 5:
        cut = lw[order[s - n_tail - 1]]
        tail_idx = order[s - n_tail:]
        x = np.exp(lw[tail_idx]) - np.exp(cut)
        if np.all(x > 0):
            k_hat, sigma = _gpd_fit(x)
            if np.isfinite(k_hat):
                p = (np.arange(1, n_tail + 1) - 0.5) / n_tail
                smooth = np.log(_gpd_quantile(p, k_hat, sigma) + np.exp(cut))
                lw = lw.copy()
                lw[tail_idx] = np.minimum(smooth, 0.0)
    return lw - logsumexp(lw), float(k_hat)


def psis_loo(log_lik) -> dict:
    """PSIS-LOO expected log predictive density (Vehtari, Gelman & Gabry 2017).

    Parameters
    ----------
    log_lik : ndarray (n_draws, n_obs)
        Log-likelihood of every observation (here: aggregated cell) per draw.

    Returns
    -------
    dict
        ``elpd`` (sum), ``se`` (its standard error), ``pointwise`` (n_obs,),
        ``k_hat`` (n_obs,) Pareto shapes (> 0.7: unreliable for that cell),
        ``p_loo`` effective number of parameters.
    """
    ll = np.asarray(log_lik, float)
    pts, ks = np.empty(ll.shape[1]), np.empty(ll.shape[1])
    for i in range(ll.shape[1]):
        lw, ks[i] = _psis_log_weights(-ll[:, i])
        pts[i] = logsumexp(ll[:, i] + lw)
    lpd = logsumexp(ll, axis=0) - np.log(ll.shape[0])
    n = len(pts)
    return {"elpd": float(pts.sum()), "se": float(np.sqrt(n * np.var(pts))), "pointwise": pts,
            "k_hat": ks, "p_loo": float(np.sum(lpd - pts))}


def compare_models(loos: dict) -> tuple[str, list[dict]]:
    """Pick a model by PSIS-LOO: the highest elpd, unless a simpler one is within 2 se.

    Parameters
    ----------
    loos : dict
        ``{name: psis_loo result}`` in order of preference (simplest first).

    Returns
    -------
    best : str
    table : list of dict
        Per model: ``model``, ``elpd``, ``se``, ``delta_elpd`` (to the highest),
        ``se_delta`` (s.e. of the pointwise difference), ``max_k_hat``.
    """
    names = list(loos)
    top = max(names, key=lambda n: loos[n]["elpd"])
    table = []
    best = top
    for name in names:
        d = loos[name]["pointwise"] - loos[top]["pointwise"]
        se_d = float(np.sqrt(len(d) * np.var(d)))
        table.append({"model": name, "elpd": loos[name]["elpd"], "se": loos[name]["se"],
                      "delta_elpd": float(d.sum()), "se_delta": se_d,
                      "max_k_hat": float(np.max(loos[name]["k_hat"]))})
    for row in table:            # simplest model statistically tied with the best
        if row["delta_elpd"] >= -2.0 * row["se_delta"]:
            best = row["model"]
            break
    return best, table


# --------------------------------------------------------------------------
# Redshift edges
# --------------------------------------------------------------------------
def edge_report(p_draws, z_grid, m_grid, threshold: float = 0.05, extrapolate=None) -> list[dict]:
    """Where C*S has not fallen to ~0 at an end of the simulated z range.

    Parameters
    ----------
    p_draws : ndarray (n_draws, n_z, n_m)
        Draws of P = C*S on the grid (z_grid spanning the simulated range).
    z_grid, m_grid : ndarray
    threshold : float
        P at an end, relative to its peak over z, above which V_eff is truncated.
    extrapolate : callable, optional
        ``extrapolate(z) -> draws of P (n_draws, len(z), n_m)`` beyond the range
        (the fitted parametric surface): used to say how far the grid should
        extend.  Without it, or when the extrapolation has not fallen within
        one more range, ``extend_dz`` is NaN.

    Returns
    -------
    list of dict
        One per end ("low", "high") where, at some magnitude with a peak P
        above 0.05, the posterior median of P(end) / max_z P exceeds
        ``threshold``: ``end``, ``z``, ``ratio`` (largest such median),
        ``mag`` (where), ``extend_dz`` (distance beyond the end at which the
        extrapolated median P falls to ``threshold`` x peak at that magnitude,
        searched in steps of 1 % of the range).
    """
    med = np.median(p_draws, axis=0)
    peak = med.max(axis=0)
    ok = peak > 0.05
    out = []
    if len(z_grid) < 2 or not ok.any():
        return out
    span = float(z_grid[-1] - z_grid[0])
    for end, i, sign in (("low", 0, -1.0), ("high", -1, 1.0)):
        ratio = np.where(ok, med[i] / np.maximum(peak, 1e-300), 0.0)
        if ratio.max() <= threshold:
            continue
        k = int(np.argmax(ratio))
        extend = np.nan
        if extrapolate is not None:
            dz = np.linspace(0.0, span, 101)[1:]
            pz = np.median(extrapolate(z_grid[i] + sign * dz), axis=0)[:, k]
            below = np.flatnonzero(pz <= threshold * peak[k])
            if below.size:
                extend = float(dz[below[0]])
        out.append({"end": end, "z": float(z_grid[i]), "ratio": float(ratio[k]),
                    "mag": float(m_grid[k]), "extend_dz": extend})
    return out
