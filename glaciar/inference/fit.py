"""Fit the surfaces: aggregate the flags, find the MAP, sample, choose the step.

Arrays in, results out: per-source flags (a table) or aggregated :class:`Cells`
in, a :class:`FitResult` out; nothing here reads or writes files (that is
:mod:`glaciar.pipeline`).  The sampler itself is :mod:`glaciar.inference.sampling`.

Aggregation (exact, or with a stated resolution)
------------------------------------------------
Sources with identical (z, mag_input) give identical Bernoulli terms; summing
them into binomial counts is exact.  When ``mag_input`` is continuous (it
varies with the UV slope), sources are grouped by z and by ``mag_input``
rounded to ``mag_resolution`` (default 0.01 mag), and each group is evaluated
at its mean ``mag_input``.  This is a Berkson-type grouping: the fit sees the
true step convolved with the within-group scatter (variance <= res^2 / 12),
which leaves m50 unbiased to first order and widens w by a relative
0.15 * res^2 / (12 w^2) = 1.3e-4 (0.1 mag / w)^2 at res = 0.01 mag -- far
below the posterior width of w for any realistic run (tested against the
exact per-source likelihood).
"""
from __future__ import annotations

import time
import warnings

import numpy as np
import pandas as pd
from scipy import optimize

from ..constants import COL_DEPTH, COL_MAG_INPUT, COL_RECOVERED, COL_SELECTED, COL_Z
from .diagnostics import compare_models, psis_loo
from .models import COMPLETENESS_SHAPES, Cells, SurfaceModel
from .sampling import (DEFAULT_MAX_STEPS, BlockChain, ConvergenceWarning, FitResult,
                       sample_block, split_rhat)

__all__ = ["ConvergenceWarning", "aggregate_cells", "find_map", "laplace_covariance",
           "BlockChain", "FitResult", "fit_surfaces", "fit_and_choose", "split_rhat",
           "DEFAULT_MAG_RESOLUTION", "DEFAULT_MAX_STEPS"]

DEFAULT_MAG_RESOLUTION = 0.01    #: [mag] grouping resolution for continuous mag_input


# --------------------------------------------------------------------------
# Aggregation
# --------------------------------------------------------------------------
def _flags(df: pd.DataFrame, col: str) -> np.ndarray:
    """A recovered/selected column as bool; NaN or values other than 0/1/True/False are an error."""
    v = df[col].to_numpy()
    if v.dtype == bool:
        return v
    bad = None
    try:
        f = np.asarray(v, dtype=float)
        bad = ~np.isin(f, (0.0, 1.0))          # NaN is not in {0, 1}
    except (TypeError, ValueError):
        bad = np.ones(len(v), bool)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"column {col!r} must be boolean: {int(bad.sum())} of {len(v)} values "
                         f"are not True/False (first: row {i}, value {v[i]!r})")
    return f.astype(bool)


def aggregate_cells(df: pd.DataFrame, mag_resolution: float | None = DEFAULT_MAG_RESOLUTION,
                    depth_ref: float | None = None, mag_column: str = COL_MAG_INPUT) -> Cells:
    """Sum per-source flags into binomial counts per (z, magnitude) cell.

    Parameters
    ----------
    df : pandas.DataFrame
        Per-source rows with columns ``z``, ``mag_column`` [mag], ``recovered``
        and ``selected`` (booleans; selected implies recovered) and, for a
        depth-aware fit, ``depth_local`` [AB mag].
    mag_resolution : float or None
        Magnitude grouping resolution [mag]; ``None`` or 0 groups identical
        values only (exact).  See the module docstring for its accuracy.
    depth_ref : float, optional
        Reference depth [AB mag] of a depth-aware model: the cells' magnitude
        is then ``m - (depth_local - depth_ref)``.
    mag_column : str
        The magnitude covariate: ``mag_input`` (apparent, detection band) or
        ``M_uv`` for an absolute-magnitude run.

    Returns
    -------
    Cells

    Raises
    ------
    ValueError
        A column is missing, a flag is NaN or not boolean, a selected source
        is not recovered, or nothing is left to fit.
    """
    need = [COL_Z, mag_column, COL_RECOVERED, COL_SELECTED] + ([COL_DEPTH] if depth_ref is not None else [])
    for col in need:
        if col not in df.columns:
            raise ValueError(f"per-source table lacks column {col!r} (have {list(df.columns)})")
    z = df[COL_Z].to_numpy(float)
    m = df[mag_column].to_numpy(float)
    if depth_ref is not None:
        m = m - (df[COL_DEPTH].to_numpy(float) - float(depth_ref))
    rec = _flags(df, COL_RECOVERED)
    sel = _flags(df, COL_SELECTED)
    good = np.isfinite(z) & np.isfinite(m)
    if not good.all():
        what = "z, magnitude or depth" if depth_ref is not None else "z or magnitude"
        warnings.warn(f"aggregate_cells: dropping {np.sum(~good)} sources with non-finite {what}")
        z, m, rec, sel = z[good], m[good], rec[good], sel[good]
    if np.any(sel & ~rec):
        raise ValueError(f"{np.sum(sel & ~rec)} sources are selected but not recovered; "
                         "'selected' must imply 'recovered'")
    if z.size == 0:
        raise ValueError("aggregate_cells: no sources to fit")
    mkey = np.round(m / mag_resolution) if mag_resolution else m
    _, zi = np.unique(z, return_inverse=True)
    _, mi = np.unique(mkey, return_inverse=True)
    key = zi.astype(np.int64) * (int(mi.max()) + 1) + mi
    ukey, inv = np.unique(key, return_inverse=True)
    nc = len(ukey)
    n = np.bincount(inv, minlength=nc)
    return Cells(z=np.bincount(inv, weights=z, minlength=nc) / n,
                 mag=np.bincount(inv, weights=m, minlength=nc) / n,
                 n=n.astype(np.int64),
                 k_rec=np.bincount(inv, weights=rec, minlength=nc).astype(np.int64),
                 k_sel=np.bincount(inv, weights=sel, minlength=nc).astype(np.int64))


# --------------------------------------------------------------------------
# MAP and Laplace approximation
# --------------------------------------------------------------------------
def _heuristic_start(model: SurfaceModel, cells: Cells) -> np.ndarray:
    """A data-driven starting point: m50 where the pooled recovered fraction halves."""
    theta = model.prior_mean.copy()
    names = model.param_names
    order = np.argsort(cells.mag)
    n = np.cumsum(cells.n[order])
    k = np.cumsum(cells.k_rec[order])
    frac_bright = k / n                                # recovered fraction brighter than m
    # Where the fraction of recovered sources among those fainter than m drops below half
    # of the overall bright-end fraction.
    nf = n[-1] - n + cells.n[order]
    kf = k[-1] - k + cells.k_rec[order]
    with np.errstate(invalid="ignore", divide="ignore"):
        f_faint = kf / nf
    top = np.nanmax(frac_bright[: max(1, len(order) // 10)])
    below = np.nonzero(f_faint < 0.5 * top)[0]
    if len(below) and 0 < top < 1 + 1e-12:
        theta[names.index("m50_0")] = cells.mag[order][below[0]]
        theta[names.index("logit_c_max_0")] = np.log((top + 0.01) / (1.01 - top))
    return theta


def _neg_log_post_and_grad(lp_fn, h):
    def fg(x):
        # Central differences, all 2P+1 points in one vectorised call.
        P = len(x)
        pts = np.repeat(x[None, :], 2 * P + 1, axis=0)
        idx = np.arange(P)
        pts[1 + idx, idx] += h
        pts[1 + P + idx, idx] -= h
        lp = lp_fn(pts)
        if not np.isfinite(lp[0]):
            return np.inf, np.zeros(P)
        g = (lp[1:P + 1] - lp[P + 1:]) / (2 * h)
        g = np.where(np.isfinite(g), g, 0.0)
        return -lp[0], -g
    return fg


def find_map(model: SurfaceModel, cells: Cells, starts=None) -> np.ndarray:
    """Maximum a posteriori parameters (BFGS from several starts).

    The posterior factorises into the completeness and the selection blocks
    (:meth:`SurfaceModel.block_indices`), so each block is maximised on its
    own (smaller problems, fewer iterations); the best start is kept per block.

    Parameters
    ----------
    model : SurfaceModel
    cells : Cells
    starts : sequence of ndarray, optional
        Starting points (full parameter vectors); default the prior mean and
        a data-driven guess.

    Returns
    -------
    ndarray, shape (P,)
    """
    if starts is None:
        starts = [_heuristic_start(model, cells), model.prior_mean]
    starts = [np.asarray(x0, float) for x0 in starts]
    out = np.array(starts[0], float)
    for part in model.parts:
        lp_fn = model.block_log_posterior(cells, part)
        idx = lp_fn.index
        fg = _neg_log_post_and_grad(lp_fn, 1e-5 * model.prior_sd[idx])
        best, tried = None, []
        for x0 in starts:
            xb = x0[idx]
            if any(np.array_equal(xb, t) for t in tried):
                continue                      # same start for this block: same optimum
            tried.append(xb)
            # BFGS: for <= 20 parameters its dense update is cheaper than L-BFGS-B's overhead.
            res = optimize.minimize(fg, xb, jac=True, method="BFGS",
                                    options={"maxiter": 2000, "gtol": 1e-6})
            if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
                best = res
        if best is None:
            raise RuntimeError("MAP search failed: the log posterior is not finite at any start")
        out[idx] = best.x
    return out


def laplace_covariance(model: SurfaceModel, cells: Cells, theta_map, part: str = "both") -> np.ndarray:
    """Inverse of minus the Hessian of the log posterior at ``theta_map``.

    The Hessian is taken by central differences (one vectorised call) with
    steps of 0.1 posterior sigma, refined once; eigenvalues are floored so the
    result is positive definite.  With ``part`` "c" or "s" only that block of
    parameters (:meth:`SurfaceModel.block_indices`) is returned.
    """
    full = np.asarray(theta_map, float)
    idx = np.arange(model.n_params) if part == "both" else model.block_indices(part)
    x = full[idx]
    P = len(x)
    sd = model.prior_sd[idx]
    h = 1e-3 * sd

    if part == "both":
        def lp(pts):
            return model.log_posterior(pts, cells, part)
    else:
        lp = model.block_log_posterior(cells, part)

    for _ in range(2):
        H = _hessian(lp, x, h)
        w, V = np.linalg.eigh(-H)
        w = np.maximum(w, 1e-8 * max(w.max(), 1e-300) + 1e-12)
        cov = (V / w) @ V.T
        h = np.clip(0.1 * np.sqrt(np.diag(cov)), 1e-7 * sd, sd)
    cov = 0.5 * (cov + cov.T)
    return cov + 1e-12 * np.eye(P) * np.max(np.diag(cov))


def _hessian(lp_fn, x, h):
    P = len(x)
    I, J = np.triu_indices(P)
    E = np.eye(P)
    d1, d2 = E[I] * h[I][:, None], E[J] * h[J][:, None]
    pts = np.concatenate([x + d1 + d2, x + d1 - d2, x - d1 + d2, x - d1 - d2])
    lp = lp_fn(pts)
    k = len(I)
    f_pp, f_pm, f_mp, f_mm = lp[:k], lp[k:2 * k], lp[2 * k:3 * k], lp[3 * k:]
    H = np.empty((P, P))
    off = (f_pp - f_pm - f_mp + f_mm) / (4 * h[I] * h[J])
    # On the diagonal d1 = d2, so f_pm = f_mp = f0 and the formula is f(x+2h)-2f+f(x-2h) over 4h^2.
    H[I, J] = off
    H[J, I] = off
    return H


def fit_surfaces(cells: Cells, model: SurfaceModel, *, seed=0, n_walkers: int | None = None,
                 max_steps: int = DEFAULT_MAX_STEPS, min_steps: int = 100, block: int = 100,
                 callback=None, resume: FitResult | None = None,
                 theta_map=None) -> FitResult:
    """MAP start, then emcee per block until 50 autocorrelation times or ``max_steps``.

    Each block (completeness, selection) is sampled by
    :func:`glaciar.inference.sampling.sample_block` on its own log posterior
    (:meth:`SurfaceModel.block_log_posterior`), from the MAP and the Laplace
    covariance of the block.

    Parameters
    ----------
    cells : Cells
        Aggregated counts (:func:`aggregate_cells`).
    model : SurfaceModel
    seed : int or sequence of int
        Seed of the samplers' random streams; same seed, same chains.
    n_walkers : int, optional
        Walkers per block; default ``max(32, 2 * P_block + 2)``.
    max_steps : int
        Cap on the steps each block runs in this call (a resumed chain may
        grow by this much past its earlier length).
    min_steps : int
        Shortest chain considered for convergence [steps].
    block : int
        Steps between convergence checks (a multiple of it for chains longer
        than 20 blocks, see :data:`glaciar.inference.sampling.CHECK_FRACTION`).
    callback : callable, optional
        Called with the number of steps just run (for a progress bar at the edge).
    resume : FitResult, optional
        A previous result of the same model and data to extend: sampling
        continues from its last state and random state (bit-identical to an
        uninterrupted run with the same ``block`` schedule).
    theta_map : ndarray, optional
        Skip the MAP search.

    Returns
    -------
    FitResult
    """
    t0 = time.perf_counter()
    if resume is not None:
        theta_map = resume.theta_map
    if theta_map is None:
        theta_map = find_map(model, cells)
    seeds = np.random.SeedSequence(seed).spawn(2)
    blocks = []
    for i, part in enumerate(model.parts):
        prev = None if resume is None else resume.blocks[i]
        cov = None if prev is not None else laplace_covariance(model, cells, theta_map, part)
        log_prob = model.block_log_posterior(cells, part)
        blocks.append(sample_block(log_prob, log_prob.index, np.asarray(theta_map, float)[log_prob.index],
                                   cov, seeds[i], part=part, n_walkers=n_walkers,
                                   max_steps=max_steps, min_steps=min_steps, block=block,
                                   callback=callback, resume=prev))
    return FitResult(model=model, theta_map=np.asarray(theta_map, float), blocks=blocks,
                     wall_time=time.perf_counter() - t0,
                     info={"n_cells": len(cells), "n_sources": cells.n_sources})


def fit_and_choose(cells: Cells, shapes=None, *, depth_ref=None, seed=0, n_walkers=None,
                   max_steps: int = DEFAULT_MAX_STEPS, loo_draws: int = 400, fit=None,
                   selection: bool = True, label: str = "fit"):
    """Fit every completeness step in ``shapes`` and keep one by PSIS-LOO.

    The selection block is the same for every step; the steps are compared on
    the recovered flags alone (leave-one-cell-out, :func:`psis_loo` over the
    aggregated cells), and the simplest step within 2 standard errors of the
    best elpd is kept (:func:`compare_models`; ``shapes`` in order of simplicity).

    Parameters
    ----------
    cells : Cells
    shapes : sequence of str, optional
        Default :data:`COMPLETENESS_SHAPES` (logistic, erf, fleming, sas).
    depth_ref : float, optional
        Reference depth of a depth-aware model (the cells must be depth-relative).
    seed, n_walkers, max_steps
        As :func:`fit_surfaces`.
    loo_draws : int
        Posterior draws used for PSIS-LOO.
    fit : callable, optional
        ``fit(cells, model) -> FitResult`` replacing :func:`fit_surfaces` (the
        pipeline passes one that resumes saved chains and shows progress).
    selection : bool
        False for a detection-only run: S = 1 exactly, only C is fitted.
    label : str
        Names the fit in the warnings (e.g. ``fit 'all'``).

    Warns
    -----
    ConvergenceWarning
        Once the model is chosen, each model's sampler warnings again, prefixed by
        ``label``, the model and whether it was kept (a warning about a model that
        was compared and dropped says so).

    Returns
    -------
    chosen : str
    results : dict
        ``{shape: FitResult}``.
    comparison : list of dict
        :func:`compare_models` table (empty for a single shape).
    """
    shapes = list(COMPLETENESS_SHAPES if shapes is None else shapes)
    if fit is None:
        def fit(c, mdl):
            return fit_surfaces(c, mdl, seed=seed, n_walkers=n_walkers, max_steps=max_steps)
    results, loos, held = {}, {}, {}
    for shape in shapes:
        mdl = SurfaceModel.for_data(cells.z, cells.mag, shape=shape, depth_ref=depth_ref,
                                    selection=selection)
        # The sampler's warnings know the block, not the model: held until the model is
        # chosen, then issued naming the model and whether it was kept.
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            results[shape] = fit(cells, mdl)
        held[shape] = caught
        if len(shapes) > 1:
            d = results[shape].draws(loo_draws)
            loos[shape] = psis_loo(mdl.cell_log_likelihood(d, cells, part="c"))
    if len(shapes) == 1:
        chosen, table = shapes[0], []
    else:
        chosen, table = compare_models(loos)
    for shape in shapes:
        role = ("kept" if shape == chosen else "compared by PSIS-LOO, not kept") \
            if len(shapes) > 1 else "the only model fitted"
        for w in held[shape]:
            if issubclass(w.category, ConvergenceWarning):
                warnings.warn(f"{label}, model {shape} ({role}): {w.message}", w.category,
                              stacklevel=2)
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return chosen, results, table
