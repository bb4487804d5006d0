"""Simulation-based calibration of the fitted surfaces (the real emcee posterior).

Parameters are drawn from the prior, flags from the surfaces they define, and
the surfaces refitted by :func:`fit_surfaces` (MAP, Laplace, pilot, emcee on
the exact binomial likelihood); over many data sets the central 68 % and 95 %
credible intervals of C and S at fixed points must contain the truth at their
nominal rates (within 5 and 3 percentage points).  Exact SBC: with truths
drawn from the prior, coverage averaged over data sets is nominal for a
correct sampler.

Size and error: 300 data sets x 9 points (a 3 x 3 grid in z and m) = 2700
intervals per quantity and level.  The points of one data set share its
truth and posterior, so the Monte Carlo standard error of a coverage is
estimated from the spread of the per-data-set coverages (cluster standard
error): about 1.9 points for C at 68 %, 1.6 for S at 68 %, 0.9 and 0.7 at
95 % -- the tolerances are 2.6-4.3 standard errors wide, and the test asserts
that they are at least 2.  It also checks it has the power to see a
miscalibration: intervals shrunk by 25 % must fail the 68 % tolerance.

Speed: each data set is seeded on its own (``SeedSequence([2024, k])`` for
the flags and the sampler), so the result does not depend on how the sets
are spread over worker processes; 2 processes by default
(``GLACIAR_SBC_WORKERS``; ``GLACIAR_SBC_SETS`` sets the number of data sets).
Each fit is the production :func:`fit_surfaces` with 96 walkers and the
chains capped at 120 steps after the 50-step pilot (tau of the slowest
parameter ~5-15 steps on these 280-source data sets, >= 1000 effective draws
per block): shorter than the 50-tau rule of a production fit, so a stricter
test of the sampler than the chains `glaciar fit` runs.
About 0.3 s of CPU per data set, ~45 s on 2 free cores.
"""
import multiprocessing
import os
import time
import warnings
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pandas as pd

from glaciar.inference import SurfaceModel, aggregate_cells, fit_surfaces
from glaciar.inference.fit import ConvergenceWarning

N_SETS = int(os.environ.get("GLACIAR_SBC_SETS", 300))
N_WORKERS = int(os.environ.get("GLACIAR_SBC_WORKERS", 2))
SEED = 2024
Z = np.array([6.0, 6.5, 7.0, 7.5, 8.0, 8.5, 9.0])
M = np.arange(25.0, 29.51, 0.5)
# A 3 x 3 grid of (z, m) points: bright, at the 50 % magnitude and faint, at the
# selection edges and in the middle of the window.
PTS_Z, PTS_M = (a.ravel() for a in np.meshgrid([6.5, 7.5, 8.5], [26.5, 27.5, 28.5]))
N_PER_CELL = 4
WALKERS, STEPS = 96, 120
LEVELS = (0.68, 0.95)
SHRINK = 0.75          # interval half-width factor of the power check


def one_set(k):
    """Fit data set ``k``; return (truth, posterior draws) of C and S at the points.

    Returns
    -------
    truth : ndarray (2, n_points)
        C and S of the true parameters.
    vals : ndarray (2, n_draws, n_points)
        C and S of the posterior draws.
    """
    rng = np.random.default_rng(np.random.SeedSequence([SEED, k]))
    mdl = SurfaceModel.for_data(Z, M)
    zs = np.repeat(Z, len(M) * N_PER_CELL)
    ms = np.tile(np.repeat(M, N_PER_CELL), len(Z))
    th = mdl.sample_prior(1, rng)[0]
    rec = rng.random(zs.size) < mdl.completeness(th, ms, zs)
    sel = rec & (rng.random(zs.size) < mdl.selection(th, zs, ms))
    cells = aggregate_cells(pd.DataFrame({"z": zs, "mag_input": ms, "recovered": rec,
                                          "selected": sel}), None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        res = fit_surfaces(cells, mdl, seed=[SEED, k], max_steps=STEPS, n_walkers=WALKERS)
    d = res.draws()
    truth = np.stack([mdl.completeness(th, PTS_M, PTS_Z), mdl.selection(th, PTS_Z, PTS_M)])
    vals = np.stack([mdl.completeness(d, PTS_M, PTS_Z), mdl.selection(d, PTS_Z, PTS_M)])
    return truth, vals


def _hits(truth, vals, p, shrink=1.0):
    lo, med, hi = np.quantile(vals, [0.5 - p / 2, 0.5, 0.5 + p / 2], axis=1)
    lo, hi = med - shrink * (med - lo), med + shrink * (hi - med)
    return (lo <= truth) & (truth <= hi)                       # (2, n_points)


def run_sbc(n_sets, workers=N_WORKERS):
    """Per-data-set hits, shape (n_sets, 2 quantities, 2 levels, n_points), and the power check."""
    if workers > 1 and "fork" in multiprocessing.get_all_start_methods():
        # fork: the workers inherit this module without re-importing the test tree.
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as ex:
            out = list(ex.map(one_set, range(n_sets), chunksize=4))
    else:
        out = [one_set(k) for k in range(n_sets)]
    hits = np.array([[_hits(t, v, p) for p in LEVELS] for t, v in out]).transpose(0, 2, 1, 3)
    shrunk = np.array([_hits(t, v, LEVELS[0], SHRINK) for t, v in out])
    return hits, shrunk


def test_sbc_coverage():
    t0 = time.perf_counter()
    hits, shrunk = run_sbc(N_SETS)
    per_set = hits.mean(axis=-1)                               # (n_sets, 2, 2)
    cov = per_set.mean(axis=0)
    mcse = per_set.std(axis=0, ddof=1) / np.sqrt(len(per_set))
    lines = [f"SBC: {N_SETS} data sets x {len(PTS_Z)} points, {time.perf_counter() - t0:.1f} s"]
    for i, name in enumerate("CS"):
        for j, p in enumerate(LEVELS):
            lines.append(f"  {name} {p:.0%}: coverage {cov[i, j]:.3f} +- {mcse[i, j]:.3f} (MC s.e.)")
    print("\n".join(lines))
    for i, name in enumerate("CS"):
        for j, p in enumerate(LEVELS):
            tol = 0.05 if p == 0.68 else 0.03
            assert abs(cov[i, j] - p) <= tol, f"{name} {p:.0%} interval covers {cov[i, j]:.1%}"
            # Enough data sets that the tolerance is >= 2 Monte Carlo standard errors.
            assert mcse[i, j] <= tol / 2, f"{name} {p:.0%}: MC error {mcse[i, j]:.3f} too large"
    # Power: a 25 % too narrow 68 % interval is caught by the same tolerance.
    assert np.all(shrunk.mean(axis=(0, 2)) < LEVELS[0] - 0.05)
