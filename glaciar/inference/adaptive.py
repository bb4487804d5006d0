"""Acquisition for the adaptive loop: where to simulate next, how many, when to stop.

Arrays in, arrays out; no file I/O (the CLI writes the proposals and the
round log at the edge).

The acquisition rule
--------------------
One more injected source at (z, m) has three outcomes: missed (probability
1 - C), recovered but not selected (C (1 - S)) or selected (C S).  Its
*expected information gain* about the surface parameters theta is the
mutual information between the outcome y and theta,

    I(y; theta) = H(E_theta[p(y | theta)]) - E_theta[H(p(y | theta))]   [nats],

estimated from posterior draws (the entropy of the mean predictive minus the
mean entropy of the per-draw predictives): zero where all draws agree,
largest where they disagree most, at most ln 3 (ln 2 for a binary outcome).
For a small posterior spread it is ~ Var(p) / (2 p (1 - p)) per category,
so it ranks cells like the posterior width of the probability, rescaled by
its binomial noise.

By the chain rule ``I(y; theta) = I(b; theta) + I(y; theta | b)`` with b the
"selected" indicator: the three-outcome gain (``outcomes="all"``) adds what a
non-selected source tells about C alone, which is worth most where S ~ 0 and
nothing to P = C S.  The default ``outcomes="selected"`` scores the binary
selected / not-selected outcome, whose probability is P itself: the
information about the quantity a luminosity-function code uses.  (On the
demo's posterior it shares 9 of its top 10 cells with the 68 % width
criterion, Spearman 0.97 over all cells; the three-outcome gain shares 3,
Spearman 0.89, its extra picks being C's step at z where S ~ 0.)

The posterior-predictive check catches what the posterior cannot: a cell where
the parametric surface does not describe the data has a confident but wrong
posterior, and so a small gain.  Cells flagged there (``misfit``, a mask or
weight in [0, 1] on the candidates; :func:`misfit_on_candidates` maps the PPC
table's ``extreme`` cells onto them) get ``misfit_weight`` times the largest
gain on the grid added to their score, which puts them among the first
picks.  Finally the score is multiplied by an optional precision weight
w(z, m) >= 0 given by the caller (e.g. where a luminosity function needs
precision; zero outside the range that matters):

    score = w * (I + misfit_weight * max(I) * misfit).

A round of K sources is shared among the best cells in proportion to score
(:func:`allocate_sources`), and the loop stops when the largest posterior sd
of C S over the user's box (:func:`max_posterior_sd`) is below a target, or
the budget is spent (:func:`run_design`).

Scores are myopic (one more source, cells independent).  The batch rule
:func:`allocate_variance_reduction` (``plan_round(..., criterion="variance")``)
instead places the round chunk by chunk where it most reduces the integrated
posterior variance of C S over the box, updating the draws' covariance after
each chunk, so it accounts for neighbouring cells informing each other and
for the diminishing return of a second batch at the same cell.

Candidates come from the values simulated so far (:func:`candidate_grid`:
the values and the midpoints between neighbours, inside the box), so a grid
grown unevenly by earlier rounds is refined where it was grown.
``benchmarks/adaptive.py`` compares the designs against uniform grids on a
surrogate with a known surface.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .models import Cells

__all__ = ["propose_cells", "candidate_grid", "information_gain", "acquisition_score",
           "misfit_on_candidates", "allocate_sources", "allocate_variance_reduction",
           "max_posterior_sd", "in_box",
           "merge_cells", "plan_round", "round_seed", "run_design", "DesignRound", "DesignResult",
           "REQUEST_DTYPE", "OUTCOMES", "CRITERIA", "COARSE_FRACTION", "coarse_axis",
           "coarse_plan"]

#: The coarse start of a budget below the design costs at most this fraction of the
#: budget (the rest is left to the rounds).
COARSE_FRACTION = 0.5


def coarse_axis(n: int, k: int) -> list[int]:
    """Indices of every ``k``-th of ``n`` sorted grid values, the first and last always kept.

    >>> coarse_axis(7, 3)
    [0, 3, 6]
    >>> coarse_axis(6, 4)
    [0, 4, 5]
    """
    if n < 1 or k < 1:
        raise ValueError(f"coarse_axis: expected n >= 1 and k >= 1, got n={n}, k={k}")
    idx = list(range(0, n, k))
    if idx[-1] != n - 1:
        idx.append(n - 1)
    return idx


def coarse_plan(n_z: int, n_mag: int, n_iterations: int, sources_per_iteration: int,
                budget: int, fraction: float = COARSE_FRACTION) -> tuple[int, int, int]:
    """The coarse start of the adaptive loop when the design costs more than the budget.

    The rule: the smallest stride ``k`` >= 1 such that every ``k``-th z and
    magnitude value (:func:`coarse_axis`: the extreme values are always kept),
    at the design's iterations per cell, costs at most ``fraction`` of the
    budget; when even the grid's corners cost more, the corners with fewer
    iterations (the most that fit in ``fraction`` of the budget, at least one).

    Parameters
    ----------
    n_z, n_mag : int
        Values on the design's z and magnitude axes.
    n_iterations : int
        Iterations (tasks per field) of each design cell.
    sources_per_iteration : int
        Sources of one iteration of one cell over all its fields
        (``n_galaxies`` x fields).
    budget : int
        Sources the whole loop may inject.
    fraction : float
        Share of the budget the coarse start may spend.

    Returns
    -------
    k, n_iterations, cost : int
        Stride, iterations per coarse cell, and the coarse start's sources.

    Raises
    ------
    ValueError
        When one iteration of the corner cells already costs more than ``budget``
        (the message gives the smallest budget that works).
    """
    target = fraction * budget

    def cells_at(k):
        return len(coarse_axis(n_z, k)) * len(coarse_axis(n_mag, k))

    k_max = max(n_z, n_mag, 2) - 1          # beyond it only the extreme values remain
    for k in range(1, k_max + 1):
        cost = cells_at(k) * n_iterations * sources_per_iteration
        if cost <= target:
            return k, n_iterations, cost
    per_iteration = cells_at(k_max) * sources_per_iteration
    n_it = max(1, min(n_iterations, int(target // per_iteration)))
    cost = per_iteration * n_it
    if cost > budget:
        raise ValueError(f"--budget {budget}: below the smallest coarse design, the grid's "
                         f"{cells_at(k_max)} corner cell(s) with one iteration ({cost} sources); "
                         f"raise --budget to at least {cost}")
    return k_max, n_it, cost


#: Dtype of a simulation request: cells and the number of sources to inject in each.
REQUEST_DTYPE = [("z", float), ("mag", float), ("n", np.int64)]
#: Outcome sets scored by :func:`information_gain`.
OUTCOMES = ("selected", "all")
#: Coordinates closer than this are the same candidate (float noise of midpoints).
_SAME = 1e-9


# --------------------------------------------------------------------------
# Candidates and the box
# --------------------------------------------------------------------------
def _box(box):
    """``((z_lo, z_hi), (m_lo, m_hi))`` as floats; None is unbounded."""
    if box is None:
        return (-np.inf, np.inf), (-np.inf, np.inf)
    try:
        (zl, zh), (ml, mh) = box
        zl, zh, ml, mh = float(zl), float(zh), float(ml), float(mh)
    except (TypeError, ValueError):
        raise ValueError(f"box must be ((z_lo, z_hi), (m_lo, m_hi)), not {box!r}") from None
    if not (zl <= zh and ml <= mh):
        raise ValueError(f"box must have z_lo <= z_hi and m_lo <= m_hi, not {box!r}")
    return (zl, zh), (ml, mh)


def in_box(z, m, box=None) -> np.ndarray:
    """Boolean mask of the outer grid ``z`` x ``m`` inside ``box`` (edges included).

    Parameters
    ----------
    z, m : array_like, 1-D
        Redshifts and magnitudes [mag] of the grid.
    box : ((z_lo, z_hi), (m_lo, m_hi)), optional
        Default: everything.

    Returns
    -------
    ndarray of bool, shape (len(z), len(m))
    """
    (zl, zh), (ml, mh) = _box(box)
    z = np.asarray(z, float).ravel()
    m = np.asarray(m, float).ravel()
    zin = (z >= zl - _SAME) & (z <= zh + _SAME)
    min_ = (m >= ml - _SAME) & (m <= mh + _SAME)
    return zin[:, None] & min_[None, :]


def _refined(values, refine, name, min_step):
    v = np.asarray(values, float).ravel()
    if v.size == 0 or not np.all(np.isfinite(v)):
        raise ValueError(f"candidate_grid: {name} values must be finite and non-empty")
    v = np.unique(v)
    if v.size == 1 or refine == 1:
        return v
    frac = np.arange(1, refine) / refine                        # 1/r, ..., (r-1)/r
    gap = np.diff(v)
    split = gap / refine >= min_step - _SAME                    # intervals wide enough to split
    inner = (v[:-1][split, None] + gap[split, None] * frac[None, :]).ravel()
    return np.sort(np.concatenate([v, inner]))


def candidate_grid(z_values, m_values, box=None, refine: int = 2, min_step=(0.0, 0.0)):
    """Candidate (z, m) cells from the values simulated so far, however spaced.

    Each interval between consecutive simulated values is split into
    ``refine`` equal parts (``refine=2``: the values and the midpoints
    between neighbours), so the grid follows a non-uniform history (a grid
    grown by earlier rounds) instead of assuming one spacing.

    Parameters
    ----------
    z_values, m_values : array_like
        Simulated redshifts and magnitudes [mag] (any order, repeats allowed).
    box : ((z_lo, z_hi), (m_lo, m_hi)), optional
        Keep only candidates inside (edges included).
    refine : int
        Parts per interval, >= 1 (1: the simulated values only).
    min_step : (float, float)
        Smallest spacing (dz, dm [mag]) the refinement creates: an interval
        is split only if its parts are at least this wide.  Repeated rounds
        otherwise halve the spacing where they concentrate, without limit
        (the candidate grid, and the memory of the draws on it, grows each
        round).  Sources drawn continuously in z or m should be given as
        their bin values.

    Returns
    -------
    z_cand, m_cand : ndarray
        Sorted candidate redshifts and magnitudes; the candidate cells are
        their outer product.

    Raises
    ------
    ValueError
        Non-finite or empty values, ``refine`` < 1, or no candidate in the box.
    """
    if int(refine) != refine or refine < 1:
        raise ValueError(f"candidate_grid: refine must be an integer >= 1, not {refine!r}")
    refine = int(refine)
    try:
        dz_min, dm_min = (float(x) for x in min_step)
    except (TypeError, ValueError):
        raise ValueError(f"candidate_grid: min_step must be (dz, dm), not {min_step!r}") from None
    if not (dz_min >= 0 and dm_min >= 0):
        raise ValueError(f"candidate_grid: min_step must be >= 0, not {min_step!r}")
    (zl, zh), (ml, mh) = _box(box)
    zc = _refined(z_values, refine, "z", dz_min)
    mc = _refined(m_values, refine, "magnitude", dm_min)
    zc = zc[(zc >= zl - _SAME) & (zc <= zh + _SAME)]
    mc = mc[(mc >= ml - _SAME) & (mc <= mh + _SAME)]
    if zc.size == 0 or mc.size == 0:
        raise ValueError(f"candidate_grid: no simulated z/magnitude inside the box {box!r}")
    return zc, mc


# --------------------------------------------------------------------------
# Scores
# --------------------------------------------------------------------------
def _entropy(p, axis):
    """Shannon entropy [nats] along ``axis``, with 0 ln 0 = 0."""
    p = np.clip(p, 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(p > 0, -p * np.log(p), 0.0)
    return t.sum(axis=axis)


def information_gain(c_draws, s_draws=None, outcomes: str = "selected") -> np.ndarray:
    """Expected information gain of one more source, from posterior draws.

    Parameters
    ----------
    c_draws : array_like, shape (D, ...)
        Draws of the completeness C; with ``s_draws=None``, draws of the
        probability of the binary outcome itself (e.g. P = C S).
    s_draws : array_like, shape (D, ...), optional
        Draws of S = P(selected | recovered), same shape (NaN where C = 0 is
        read as 0: nothing is selected there whatever S is).
    outcomes : {"selected", "all"}
        "selected": the binary outcome selected / not (probability C S);
        "all": missed / recovered-not-selected / selected.  Ignored without
        ``s_draws``.

    Returns
    -------
    ndarray, shape (...)
        Mutual information between the outcome and the parameters [nats]:
        H(mean predictive) - mean over draws of H(predictive).  In
        [0, ln 2] (binary) or [0, ln 3].
    """
    if outcomes not in OUTCOMES:
        raise ValueError(f"outcomes must be one of {OUTCOMES}, not {outcomes!r}")
    c = np.asarray(c_draws, float)
    if c.ndim < 1 or c.shape[0] < 1:
        raise ValueError("information_gain: draws must have a leading draw axis")
    if s_draws is None:
        probs = np.stack([c, 1.0 - c])
    else:
        s = np.nan_to_num(np.asarray(s_draws, float), nan=0.0)
        if s.shape != c.shape:
            raise ValueError(f"information_gain: C and S draws differ in shape {c.shape} != {s.shape}")
        p = c * s
        probs = np.stack([p, 1.0 - p]) if outcomes == "selected" else np.stack([p, c - p, 1.0 - c])
    gain = _entropy(probs.mean(axis=1), axis=0) - _entropy(probs, axis=0).mean(axis=0)
    # Both terms are sums of the same rounded logs: tiny negatives are rounding.
    return np.maximum(gain, 0.0)


def acquisition_score(gain, misfit=None, weight=None, misfit_weight: float = 1.0) -> np.ndarray:
    """score = weight * (gain + misfit_weight * max(gain) * misfit) (see the module docstring).

    Parameters
    ----------
    gain : array_like
        Per-cell information gain (:func:`information_gain`) or any other
        non-negative uncertainty score.
    misfit : array_like of bool or float in [0, 1], optional
        Cells flagged by the posterior-predictive check (same shape as ``gain``).
    weight : array_like, optional
        Precision weight w >= 0 (broadcast to ``gain``), e.g. where a
        luminosity function needs C S precisely.
    misfit_weight : float
        Bonus of a flagged cell in units of the largest gain.

    Returns
    -------
    ndarray, shape of ``gain``
    """
    g = np.asarray(gain, float)
    if np.any(~np.isfinite(g)) or np.any(g < 0):
        raise ValueError("acquisition_score: gain must be finite and >= 0")
    score = g.copy()
    if misfit is not None:
        f = np.asarray(misfit, float)
        if f.shape != g.shape or np.any(~np.isfinite(f)) or np.any((f < 0) | (f > 1)):
            raise ValueError(f"acquisition_score: misfit must have shape {g.shape} and values "
                             "in [0, 1] (a mask or a weight)")
        if not (np.isfinite(misfit_weight) and misfit_weight >= 0):
            raise ValueError(f"acquisition_score: misfit_weight must be >= 0, not {misfit_weight!r}")
        score = score + float(misfit_weight) * (g.max() if g.size else 0.0) * f
    if weight is not None:
        w = np.broadcast_to(np.asarray(weight, float), g.shape)
        if np.any(~np.isfinite(w)) or np.any(w < 0):
            raise ValueError("acquisition_score: weight must be finite and >= 0")
        score = score * w
    return score


def misfit_on_candidates(ppc, z_cand, m_cand, column: str = "extreme") -> np.ndarray:
    """The PPC's flagged cells as a mask on the candidate grid.

    A flagged simulated cell (z_e, m_e) marks the candidate nearest to it and
    that candidate's neighbours in z and in m (with ``candidate_grid(...,
    refine=2)``: the cell and the midpoints around it), since the misfit is
    a property of the surface there, not of one point.

    Parameters
    ----------
    ppc : numpy structured array or mapping
        The posterior-predictive table (:func:`glaciar.inference.diagnostics.ppc_cells`)
        with fields ``z``, ``mag`` and ``column``.
    z_cand, m_cand : array_like, 1-D, sorted
        Candidate redshifts and magnitudes.
    column : str
        Boolean flag column (default ``extreme``).

    Returns
    -------
    ndarray of bool, shape (len(z_cand), len(m_cand))
    """
    zc = np.asarray(z_cand, float).ravel()
    mc = np.asarray(m_cand, float).ravel()
    out = np.zeros((zc.size, mc.size), bool)
    flag = np.asarray(ppc[column], bool)
    for ze, me in zip(np.asarray(ppc["z"], float)[flag], np.asarray(ppc["mag"], float)[flag]):
        i, j = int(np.argmin(np.abs(zc - ze))), int(np.argmin(np.abs(mc - me)))
        out[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2] = True
    return out


def propose_cells(sf_or_draws, z_grid, m_grid, n: int, *, interval: float = 0.68,
                  relative: bool = False, criterion: str = "width", outcomes: str = "selected",
                  misfit=None, weight=None, misfit_weight: float = 1.0) -> np.ndarray:
    """The (z, m) cells where the posterior of P = C S is least certain.

    With ``criterion="width"`` (default) the score of a cell is the width of
    the central ``interval`` credible interval of P(selected | z, m) = C S --
    the absolute uncertainty of the quantity an LF code multiplies by, which
    is automatically small where P is certainly 0 or 1.  With
    ``relative=True`` the width is divided by the median (floored at 0.01),
    favouring the faint tail.  With ``criterion="information"`` the score is
    the expected information gain of one more source (:func:`information_gain`
    with ``outcomes``), plus the misfit term and times the precision weight
    (:func:`acquisition_score`; ``misfit`` and ``weight`` on the grid, shape
    (len(z_grid), len(m_grid)); they also apply to the width criterion).

    Parameters
    ----------
    sf_or_draws : SelectionFunction or ndarray
        A fitted selection function, or draws of P on the grid with shape
        ``(n_draws, len(z_grid), len(m_grid))`` (then ``outcomes="all"`` is
        not available: it needs C and S).
    z_grid, m_grid : array_like
        Candidate redshifts and magnitudes [AB mag].
    n : int
        Number of cells to return.

    Returns
    -------
    numpy structured array, length min(n, n_cells), fields ``z``, ``mag``,
    ``score``, ``median``, ``width``, ``sd`` (of P), ``info`` (information
    gain [nats]) and ``misfit``; sorted by decreasing score (ties by z, m).
    """
    if criterion not in ("width", "information"):
        raise ValueError(f"criterion must be 'width' or 'information', not {criterion!r}")
    z_grid = np.asarray(z_grid, float).ravel()
    m_grid = np.asarray(m_grid, float).ravel()
    if hasattr(sf_or_draws, "grid_draws"):
        g = sf_or_draws.grid_draws(z_grid, m_grid, outside="extrapolate")   # past the data too
        d, c, s = g["P"], g["C"], g["S"]
    else:
        d = np.asarray(sf_or_draws, float)
        if d.ndim != 3 or d.shape[1:] != (len(z_grid), len(m_grid)):
            raise ValueError(f"draws must have shape (n_draws, {len(z_grid)}, {len(m_grid)}), "
                             f"not {d.shape}")
        if outcomes == "all" and criterion == "information":
            raise ValueError("outcomes='all' needs C and S: pass a SelectionFunction")
        c, s = d, None
    med, qlo, qhi = np.quantile(d, [0.5, 0.5 - 0.5 * interval, 0.5 + 0.5 * interval], axis=0)
    width = qhi - qlo
    info = information_gain(c, s, outcomes)
    base = (width / np.maximum(med, 0.01) if relative else width) if criterion == "width" else info
    score = acquisition_score(base, misfit, weight, misfit_weight)
    zz, mm = np.meshgrid(z_grid, m_grid, indexing="ij")
    order = np.lexsort((mm.ravel(), zz.ravel(), -score.ravel()))[: int(n)]
    out = np.empty(len(order), dtype=[("z", float), ("mag", float), ("score", float),
                                      ("median", float), ("width", float), ("sd", float),
                                      ("info", float), ("misfit", bool)])
    out["z"], out["mag"] = zz.ravel()[order], mm.ravel()[order]
    out["score"], out["median"] = score.ravel()[order], med.ravel()[order]
    out["width"] = width.ravel()[order]
    out["sd"] = d.std(axis=0).ravel()[order]
    out["info"] = info.ravel()[order]
    out["misfit"] = (np.zeros(score.shape, bool) if misfit is None
                     else np.asarray(misfit, float) > 0).ravel()[order]
    return out


# --------------------------------------------------------------------------
# Allocation and stopping
# --------------------------------------------------------------------------
def allocate_sources(scores, k: int, *, n_cells: int | None = None,
                     min_per_cell: int = 1) -> np.ndarray:
    """Share ``k`` sources among the best-scoring cells, in proportion to score.

    The ``n_cells`` best cells (fewer if ``k`` cannot give each
    ``min_per_cell``, and only cells with a positive score when there are
    any) get ``min_per_cell`` each; the rest is shared in proportion to their
    scores by largest remainders.  Deterministic: ties go to the lower flat
    index.

    Parameters
    ----------
    scores : array_like
        Cell scores >= 0 (any shape).
    k : int
        Sources in the round, >= 0.
    n_cells : int, optional
        At most this many cells (default: as many as ``k`` allows).
    min_per_cell : int
        Smallest number of sources a chosen cell receives, >= 1.

    Returns
    -------
    ndarray of int64, shape of ``scores``, summing to exactly ``k``.
    """
    s = np.asarray(scores, float)
    if np.any(~np.isfinite(s)) or np.any(s < 0):
        raise ValueError("allocate_sources: scores must be finite and >= 0")
    if int(k) != k or k < 0:
        raise ValueError(f"allocate_sources: k must be an integer >= 0, not {k!r}")
    if int(min_per_cell) != min_per_cell or min_per_cell < 1:
        raise ValueError(f"allocate_sources: min_per_cell must be an integer >= 1, not {min_per_cell!r}")
    if n_cells is not None and (int(n_cells) != n_cells or n_cells < 1):
        raise ValueError(f"allocate_sources: n_cells must be an integer >= 1, not {n_cells!r}")
    k, min_per_cell = int(k), int(min_per_cell)
    flat = s.ravel()
    out = np.zeros(flat.size, np.int64)
    if k == 0 or flat.size == 0:
        return out.reshape(s.shape)
    order = np.argsort(-flat, kind="stable")
    n_pos = int(np.sum(flat > 0))
    n_max = n_pos if n_pos else flat.size
    n_use = min(n_max, k // min_per_cell, flat.size if n_cells is None else int(n_cells))
    if n_use < 1:                  # k < min_per_cell: all of it to the best cell
        out[order[0]] = k
        return out.reshape(s.shape)
    chosen = order[:n_use]
    w = flat[chosen]
    w = w / w.sum() if w.sum() > 0 else np.full(n_use, 1.0 / n_use)
    rest = k - n_use * min_per_cell
    share = rest * w
    base = np.floor(share).astype(np.int64)
    left = rest - int(base.sum())
    # Largest remainders; on equal remainders the better-ranked cell (stable order).
    base[np.argsort(-(share - base), kind="stable")[:left]] += 1
    out[chosen] = min_per_cell + base
    return out.reshape(s.shape)


def _chunks(k, min_per_cell):
    """k split into chunks of min_per_cell, the remainder dealt one by one from the first."""
    n = max(1, k // min_per_cell)
    sizes = np.full(n, min(min_per_cell, k), np.int64)
    extra = k - int(sizes.sum())
    sizes += extra // n
    sizes[: extra % n] += 1
    return sizes


def allocate_variance_reduction(p_cand, k: int, *, p_eval=None, eval_weight=None, misfit=None,
                                min_per_cell: int = 1, max_draws: int = 200) -> np.ndarray:
    """Share ``k`` sources so as to shrink the integrated posterior variance of C S most.

    A batch rule that sees what the proportional one does not: sources at one
    cell also inform its neighbours (the draws are correlated), and the
    second batch at a cell is worth less than the first.  The draws define a
    linear-Gaussian (ensemble Kalman) approximation of the posterior of
    P = C S: observing the selected fraction of n sources at candidate x
    (noise variance pbar_x (1 - pbar_x) / n) reduces the w-weighted sum of
    variances over the evaluation points e by

        sum_e w_e Cov(P_e, P_x)^2 / (Var P_x + pbar_x (1 - pbar_x) / n).

    Chunks of ``min_per_cell`` sources go one at a time to the candidate with
    the largest reduction, and the covariance is updated after each (square-
    root form, so the cost per chunk is O(D^2 N) for D draws, N candidates).
    Cells flagged by the PPC (``misfit``) are given a chunk first, since the
    posterior there cannot be trusted to say how uncertain it is.

    Parameters
    ----------
    p_cand : array_like, shape (D, ...)
        Draws of P at the candidate cells.
    k : int
        Sources in the round.
    p_eval : array_like, shape (D, ...), optional
        The same draws at the points where precision is wanted (e.g. a fixed
        grid over the user's box, so that the objective does not depend on
        how densely earlier rounds refined the candidates); default ``p_cand``.
    eval_weight : array_like, optional
        Weight w >= 0 of each evaluation point (broadcast to ``p_eval``'s
        cells), e.g. where a luminosity function needs precision; default 1.
    misfit : array_like of bool, optional
        Flagged candidates (shape ``p_cand.shape[1:]``).
    min_per_cell : int
        Chunk size, the smallest number of sources a chosen cell receives
        (unless ``k`` is smaller).
    max_draws : int
        Draws used (evenly spaced), bounding the cost.

    Returns
    -------
    ndarray of int64, shape ``p_cand.shape[1:]``, summing to exactly ``k``;
    deterministic (ties go to the lower flat index).
    """
    pc = np.asarray(p_cand, float)
    if pc.ndim < 2 or not np.all(np.isfinite(pc)):
        raise ValueError("allocate_variance_reduction: p_cand must be finite draws (D, ...)")
    if int(k) != k or k < 0:
        raise ValueError(f"allocate_variance_reduction: k must be an integer >= 0, not {k!r}")
    if int(min_per_cell) != min_per_cell or min_per_cell < 1:
        raise ValueError("allocate_variance_reduction: min_per_cell must be an integer >= 1")
    shape = pc.shape[1:]
    out = np.zeros(int(np.prod(shape)), np.int64)
    if k == 0:
        return out.reshape(shape)
    pe = pc if p_eval is None else np.asarray(p_eval, float)
    if pe.shape[0] != pc.shape[0] or not np.all(np.isfinite(pe)):
        raise ValueError("allocate_variance_reduction: p_eval must be finite draws with "
                         f"{pc.shape[0]} draws, like p_cand")
    w = np.ones(pe.shape[1:]) if eval_weight is None else np.broadcast_to(
        np.asarray(eval_weight, float), pe.shape[1:])
    w = w.ravel()
    pc = pc.reshape(pc.shape[0], -1)
    pe = pe.reshape(pe.shape[0], -1)
    if np.any(~np.isfinite(w)) or np.any(w < 0):
        raise ValueError("allocate_variance_reduction: eval_weight must be finite and >= 0")
    if pc.shape[0] > max_draws:
        keep = np.linspace(0, pc.shape[0] - 1, int(max_draws)).round().astype(int)
        pc, pe = pc[keep], pe[keep]
    d = pc.shape[0]
    pbar = pc.mean(axis=0)
    # Per-source noise variance of the selected indicator; floored so that a
    # certain cell (pbar = 0 or 1, zero posterior variance) scores 0, not 0/0.
    q = np.maximum(pbar * (1.0 - pbar), 1e-9)
    a_c = (pc - pbar) / np.sqrt(d)                             # Cov = a^T a
    a_e = (pe - pe.mean(axis=0)) / np.sqrt(d)
    g = (a_e * w) @ a_e.T                                      # (D, D)
    first = []
    if misfit is not None:
        f = np.asarray(misfit, bool).ravel()
        if f.size != out.size:
            raise ValueError(f"allocate_variance_reduction: misfit must have shape {shape}")
        first = list(np.flatnonzero(f)[np.argsort(-np.sum(a_c[:, f] ** 2, axis=0), kind="stable")])
    for step, n in enumerate(_chunks(int(k), int(min_per_cell))):
        r = q / n
        if step < len(first):
            x = int(first[step])
        else:
            num = np.sum(a_c * (g @ a_c), axis=0)
            den = np.sum(a_c ** 2, axis=0) + r
            gain = num / den
            x = int(np.argmax(gain)) if gain.max() > 0 else int(np.argmax(q))
        out[x] += n
        a = a_c[:, x].copy()
        s2 = float(a @ a)
        if s2 > 0:
            beta = (1.0 - np.sqrt(r[x] / (s2 + r[x]))) / s2
            # T = I - beta a a^T: T^T T = I - a a^T / (|a|^2 + r), the Kalman update.
            a_c -= beta * np.outer(a, a @ a_c)
            ga = g @ a
            g = g - beta * (np.outer(a, ga) + np.outer(ga, a)) + beta ** 2 * float(a @ ga) * np.outer(a, a)
    return out.reshape(shape)


def max_posterior_sd(p_draws, z_grid=None, m_grid=None, box=None) -> float:
    """The stopping statistic: the largest posterior sd of C S over the box.

    Parameters
    ----------
    p_draws : array_like, shape (D, n_z, n_m)
        Draws of P = C S on the outer grid ``z_grid`` x ``m_grid``.
    z_grid, m_grid : array_like, optional
        The grid (needed with ``box``).
    box : ((z_lo, z_hi), (m_lo, m_hi)), optional
        The user's region; default the whole grid.

    Returns
    -------
    float
        max over grid points in the box of the standard deviation over draws
        (``ddof=0``, numpy's default) [probability units].
    """
    d = np.asarray(p_draws, float)
    if d.ndim != 3:
        raise ValueError(f"max_posterior_sd: draws must be (n_draws, n_z, n_m), not {d.shape}")
    sd = d.std(axis=0)
    if box is not None:
        if z_grid is None or m_grid is None:
            raise ValueError("max_posterior_sd: a box needs z_grid and m_grid")
        mask = in_box(z_grid, m_grid, box)
        if mask.shape != sd.shape:
            raise ValueError(f"max_posterior_sd: grid {mask.shape} does not match draws {sd.shape}")
        if not mask.any():
            raise ValueError(f"max_posterior_sd: no grid point inside the box {box!r}")
        sd = sd[mask]
    return float(np.max(sd))


# --------------------------------------------------------------------------
# Rounds
# --------------------------------------------------------------------------
def merge_cells(a: Cells | None, b: Cells) -> Cells:
    """The counts of ``a`` and ``b`` summed cell by cell (same (z, mag) to 1e-9)."""
    if a is None:
        return b
    z = np.concatenate([a.z, b.z])
    m = np.concatenate([a.mag, b.mag])
    key = np.stack([np.round(z / _SAME), np.round(m / _SAME)], axis=1)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    nc = len(first)

    def add(x, y):
        return np.bincount(inv, weights=np.concatenate([x, y]), minlength=nc).astype(np.int64)

    return Cells(z=z[first], mag=m[first], n=add(a.n, b.n), k_rec=add(a.k_rec, b.k_rec),
                 k_sel=add(a.k_sel, b.k_sel))


#: Criteria of :func:`plan_round`.
CRITERIA = ("information", "sd", "variance")


def plan_round(c_draws, s_draws, candidates, k: int, *, criterion: str = "information",
               outcomes: str = "selected", misfit=None, weight=None, misfit_weight: float = 1.0,
               n_cells: int | None = None, min_per_cell: int = 1, p_eval=None) -> np.ndarray:
    """One round's request: where the next ``k`` sources go, and how many in each cell.

    Parameters
    ----------
    c_draws, s_draws : array_like, shape (D, len(z_cand), len(m_cand))
        Posterior draws of C and S on the candidate grid (``s_draws=None``:
        ``c_draws`` are draws of P).
    candidates : (z_cand, m_cand) of array_like
        Candidate redshifts and magnitudes [mag], the cells their outer product
        (what :func:`candidate_grid` returns).
    k : int
        Sources in the round.
    criterion : {"information", "sd", "variance"}
        "information": score = expected information gain
        (:func:`information_gain`, with the misfit and weight terms of
        :func:`acquisition_score`), shared in proportion to score
        (:func:`allocate_sources`); "sd": the same with the posterior sd of
        P = C S as the base score; "variance": the batch rule
        :func:`allocate_variance_reduction` (integrated variance of P over
        ``p_eval``, weighted by ``weight``; misfit cells first).
    outcomes, misfit, weight, misfit_weight
        As :func:`information_gain` and :func:`acquisition_score` (for
        "variance", ``weight`` is the weight of the evaluation points).
    n_cells, min_per_cell
        As :func:`allocate_sources` (``n_cells`` is not used by "variance").
    p_eval : array_like, shape (D, ...), optional
        "variance" only: the same draws of P at the evaluation points
        (default the candidates).

    Returns
    -------
    numpy structured array, dtype :data:`REQUEST_DTYPE`: the cells with n > 0,
    sorted by z then mag.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"plan_round: criterion must be one of {CRITERIA}, not {criterion!r}")
    z_cand, m_cand = candidates
    zc = np.asarray(z_cand, float).ravel()
    mc = np.asarray(m_cand, float).ravel()
    c = np.asarray(c_draws, float)
    if c.shape[1:] != (zc.size, mc.size):
        raise ValueError(f"plan_round: draws cover {c.shape[1:]}, the candidates "
                         f"{(zc.size, mc.size)}")
    p = c if s_draws is None else c * np.nan_to_num(np.asarray(s_draws, float), nan=0.0)
    if criterion == "variance":
        alloc = allocate_variance_reduction(p, k, p_eval=p_eval, eval_weight=weight,
                                            misfit=misfit, min_per_cell=min_per_cell)
    else:
        gain = information_gain(c_draws, s_draws, outcomes) if criterion == "information" \
            else p.std(axis=0)
        score = acquisition_score(gain, misfit, weight, misfit_weight)
        alloc = allocate_sources(score, k, n_cells=n_cells, min_per_cell=min_per_cell)
    i, j = np.nonzero(alloc)                     # row-major: sorted by z, then mag
    out = np.empty(i.size, dtype=REQUEST_DTYPE)
    out["z"], out["mag"], out["n"] = zc[i], mc[j], alloc[i, j]
    return out


@dataclass(frozen=True)
class DesignRound:
    """One round of :func:`run_design` (the log line of the adaptive loop).

    Attributes
    ----------
    index : int
        0 for the initial design.
    request : ndarray
        The cells simulated, dtype :data:`REQUEST_DTYPE`.
    n_sources, n_total : int
        Sources in this round and so far.
    max_sd : float
        Stopping statistic after this round's fit (NaN without one).
    cpu_s : float
        CPU seconds of this process for the round (simulate + fit + propose;
        work done by other processes is not counted).
    """

    index: int
    request: np.ndarray
    n_sources: int
    n_total: int
    max_sd: float
    cpu_s: float


@dataclass(frozen=True)
class DesignResult:
    """What :func:`run_design` returns: the counts, the last posterior, the rounds."""

    cells: Cells
    posterior: object
    rounds: tuple
    stopped: str     #: "target" (max_sd below target_sd), "budget" or "no-proposal"


def round_seed(seed, index: int) -> np.random.SeedSequence:
    """The random stream of round ``index``: independent of how many rounds ran before
    (so an interrupted loop resumes with the same draws)."""
    entropy = seed.entropy if isinstance(seed, np.random.SeedSequence) else seed
    return np.random.SeedSequence(entropy, spawn_key=(int(index),))


def run_design(simulate, fit, propose, initial, *, budget: int, round_size: int, seed=0,
               target_sd: float | None = None, statistic=None, callback=None) -> DesignResult:
    """The adaptive loop: initial design, then rounds of fit -> propose -> simulate.

    Pure in the sense that everything it touches comes in as a callable:

    * ``simulate(request, seed) -> Cells``: inject ``request["n"]`` sources at
      each ``(request["z"], request["mag"])`` and return their counts;
    * ``fit(cells, seed) -> posterior``: fit all counts so far;
    * ``propose(posterior, cells, k, seed) -> request``: the next round of
      ``k`` sources (e.g. :func:`candidate_grid` + :func:`plan_round`);
    * ``statistic(posterior) -> float``: the stopping statistic (e.g.
      :func:`max_posterior_sd` over the user's box).

    Each call gets the seed of its round, a :class:`numpy.random.SeedSequence`
    (:func:`round_seed`; simulate, fit and propose get independent children;
    ``int(seed.generate_state(1)[0])`` where an int is needed), so a seed fixes every draw
    and a resumed loop repeats the interrupted round exactly.

    Parameters
    ----------
    initial : ndarray, dtype :data:`REQUEST_DTYPE`
        The coarse design (round 0); counts towards the budget.
    budget : int
        Total sources, >= the initial design.
    round_size : int
        Sources per later round (the last one takes what is left).
    seed : int or SeedSequence
    target_sd : float, optional
        Stop once ``statistic(posterior) < target_sd`` (needs ``statistic``).
    callback : callable, optional
        Called with each :class:`DesignRound` as it finishes (logging).

    Returns
    -------
    DesignResult
    """
    initial = np.asarray(initial)
    n0 = int(np.sum(initial["n"]))
    if int(budget) != budget or budget < n0:
        raise ValueError(f"run_design: budget must be an integer >= the initial design's "
                         f"{n0} sources, not {budget!r}")
    if int(round_size) != round_size or round_size < 1:
        raise ValueError(f"run_design: round_size must be an integer >= 1, not {round_size!r}")
    if target_sd is not None and (statistic is None or not (np.isfinite(target_sd) and target_sd > 0)):
        raise ValueError("run_design: target_sd must be a positive number and needs a statistic")
    cells, posterior, rounds, request, spent = None, None, [], initial, 0
    stopped = "budget"
    for index in range(int(budget) + 1):            # at least one source per round
        t0 = time.process_time()
        s_sim, s_fit, s_prop = round_seed(seed, index).spawn(3)
        if index > 0:
            k = min(int(round_size), int(budget) - spent)
            request = np.asarray(propose(posterior, cells, k, s_prop))
            if request.size == 0 or int(np.sum(request["n"])) == 0:
                stopped = "no-proposal"
                break
            if int(np.sum(request["n"])) > k or np.any(request["n"] < 0):
                raise ValueError(f"run_design: propose asked for {int(np.sum(request['n']))} "
                                 f"sources in round {index}, more than the {k} left to it")
            request = request[request["n"] > 0]
        cells = merge_cells(cells, simulate(request, s_sim))
        spent += int(np.sum(request["n"]))
        posterior = fit(cells, s_fit)
        sd = float(statistic(posterior)) if statistic is not None else float("nan")
        rec = DesignRound(index=index, request=request, n_sources=int(np.sum(request["n"])),
                          n_total=spent, max_sd=sd, cpu_s=time.process_time() - t0)
        rounds.append(rec)
        if callback is not None:
            callback(rec)
        if target_sd is not None and sd < target_sd:
            stopped = "target"
            break
        if spent >= budget:
            break
    return DesignResult(cells=cells, posterior=posterior, rounds=tuple(rounds), stopped=stopped)
