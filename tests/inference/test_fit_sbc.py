"""Simulation-based calibration of the fitted depth-aware surfaces (the real emcee posterior).

Every data set is a depth-aware survey: each source has a local depth d drawn
uniformly over DEPTH_REF -+ 0.75 mag (a 1.5 mag span, as between a shallow and
a deep field), parameters are drawn from the prior of the depth-aware model
(``SurfaceModel.for_data(..., depth_ref=DEPTH_REF)``), the flags from
C(m, z | d) and S(z, m | d) of those parameters, the cells aggregated with
``depth_ref`` (exactly: ``mag_resolution=None``), and the surfaces refitted by
:func:`fit_surfaces` (MAP, Laplace, pilot, emcee on the exact binomial
likelihood).  Over many data sets the central 68 % and 95 % credible intervals
of C and S at fixed (z, m, depth) points must contain the truth at their
nominal rates (within 5 and 3 percentage points).  Exact SBC: with truths
drawn from the prior, coverage averaged over data sets is nominal for a
correct sampler.

Points: a 3 x 3 grid in z (the middle of the window and both halves) and m
(bright, around the prior's m50 and faint) at two depths (0.6 mag shallower
and deeper than the reference), 18 points, so the depth shift enters the
evaluated surfaces.

Two sizes.  The default test (``test_depth_aware_sbc_coverage_small``) fits the
first 64 data sets and holds the coverages to 8 points at 68 % and 5 at 95 %; the
full test (``test_depth_aware_sbc_coverage``, marked ``slow``: ``pytest -m slow
tests/inference/test_fit_sbc.py``, or ``python benchmarks/sbc.py``) fits 220 and holds
them to 5 and 3 points.  The small set is the full one's first 64 (each data set is
seeded by its index), so the two differ only in how many data sets they average.

Size and error: the points of one data set share its truth and posterior, so
the Monte Carlo standard error of a coverage is estimated from the spread of
the per-data-set coverages (cluster standard error).  With 220 data sets it is
about 2.0 points for C and S at 68 %, 0.9 and 0.8 at 95 %; with 64 it is 3.7 and
3.5 at 68 %, 2.1 and 1.5 at 95 %.  Each test asserts that every tolerance is at
least 2 standard errors.  Each also checks it has the power to see a
miscalibration: intervals shrunk by 25 % must fail the 68 % tolerance (their
coverage is 0.49-0.52 for C and S with 220 sets, 0.50-0.52 with 64, against
limits of 0.63 and 0.60).  Measured coverages (68 % / 95 %): 220 sets, C 0.670 /
0.944, S 0.667 / 0.951; 64 sets, C 0.656 / 0.926, S 0.668 / 0.951.  (Over 800 data
sets the coverages were 0.685 +- 0.010 and 0.944 +- 0.005 for C, 0.668 +- 0.011 and
0.945 +- 0.005 for S.)

Speed: each data set is seeded on its own (``SeedSequence([2024, k])`` for the
depths, truth, flags and the sampler), so the result does not depend on how
the sets are spread over worker processes; 2 processes by default
(``GLACIAR_SBC_WORKERS``; ``GLACIAR_SBC_SETS`` sets the number of data sets of
the full test, default 220).  Each fit is the production :func:`fit_surfaces` with 64
walkers, the chains capped at 120 steps (tau of the slowest parameter ~5-11
steps on these 280-source data sets, ~600 effective draws per block) and, by
default, the pilot cut to the first two stages of ``PILOT_STAGES`` (50 + 150
steps).  On these small, often prior-dominated data sets the full staged pilot
usually runs on to its 400-, 1000- and 2500-step stages and costs ~4 times the
rest of the fit.  The pilot only shapes the independence
proposal; the chain proper is a valid MCMC with any proposal, and a less
adapted one only raises tau, so the short pilot, like the short chains, makes
the test stricter on mixing than the chains `glaciar fit` runs.
``GLACIAR_SBC_PILOT=full`` runs the production pilot (200 sets: coverage
0.660 / 0.946 for C, 0.681 / 0.952 for S).  About 0.37 s of CPU per data set with
emcee's stock moves and ``emcee.autocorr`` (measured: 23 s for the 64 sets, 82 s for
the 220), so ~12 s wall for the small test and ~45 s for the full one on 2 free cores.
glaciar's former private override of emcee's red-blue moves and autocorrelation time
gave the same chains (the same coverages) for ~20 % less CPU on data sets this small
(220 sets: 76 s against 92 s; ``benchmarks/fit.py``).
"""
import multiprocessing
import os
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from unittest import mock

import numpy as np
import pandas as pd
import pytest

import glaciar.inference.sampling as sampling
from glaciar.inference import SurfaceModel, aggregate_cells, fit_surfaces
from glaciar.inference.fit import ConvergenceWarning

N_SETS = int(os.environ.get("GLACIAR_SBC_SETS", 220))      # the full (slow) test
N_SETS_SMALL = 64                                           # the default test
N_WORKERS = int(os.environ.get("GLACIAR_SBC_WORKERS", 2))
# "short": the pilot's first two stages only (see the module docstring); "full": production.
PILOT = os.environ.get("GLACIAR_SBC_PILOT", "short")
if PILOT not in ("short", "full"):
    raise ValueError(f"GLACIAR_SBC_PILOT must be 'short' or 'full', not {PILOT!r}")
SEED = 2024
Z = np.array([6.0, 6.5, 7.0, 7.5, 8.0, 8.5, 9.0])
M = np.arange(25.0, 29.51, 0.5)
DEPTH_REF = 28.0
DEPTH_HALF_SPAN = 0.75      # local depths uniform over DEPTH_REF -+ this [mag]
# 3 (z) x 3 (m) x 2 (depth) points: bright, around the 50 % magnitude and faint,
# at the selection edges and in the middle of the window, shallow and deep.
PTS_Z, PTS_M, PTS_D = (a.ravel() for a in np.meshgrid(
    [6.5, 7.5, 8.5], [26.5, 27.5, 28.5], [DEPTH_REF - 0.6, DEPTH_REF + 0.6], indexing="ij"))
N_PER_CELL = 4
WALKERS, STEPS = 64, 120
LEVELS = (0.68, 0.95)
TOL = {0.68: 0.05, 0.95: 0.03}           # the full test's tolerances (220 sets)
TOL_SMALL = {0.68: 0.08, 0.95: 0.05}     # the default test's (64 sets)
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
    zs = np.repeat(Z, len(M) * N_PER_CELL)
    ms = np.tile(np.repeat(M, N_PER_CELL), len(Z))
    ds = DEPTH_REF + rng.uniform(-DEPTH_HALF_SPAN, DEPTH_HALF_SPAN, zs.size)
    mdl = SurfaceModel.for_data(zs, ms - (ds - DEPTH_REF), depth_ref=DEPTH_REF)
    th = mdl.sample_prior(1, rng)[0]
    rec = rng.random(zs.size) < mdl.completeness(th, ms, zs, depth=ds)
    sel = rec & (rng.random(zs.size) < mdl.selection_given_recovered(th, zs, ms, depth=ds))
    cells = aggregate_cells(pd.DataFrame({"z": zs, "mag_input": ms, "depth_local": ds,
                                          "recovered": rec, "selected": sel}),
                            None, depth_ref=DEPTH_REF)
    # The fitted model is the one the pipeline would build from these cells.
    assert SurfaceModel.for_data(cells.z, cells.mag, depth_ref=DEPTH_REF) == mdl
    stages = sampling.PILOT_STAGES if PILOT == "full" else sampling.PILOT_STAGES[:2]
    with warnings.catch_warnings(), mock.patch.object(sampling, "PILOT_STAGES", stages):
        warnings.simplefilter("ignore", ConvergenceWarning)
        res = fit_surfaces(cells, mdl, seed=[SEED, k], max_steps=STEPS, n_walkers=WALKERS)
    d = res.draws()

    def surfaces(theta):
        return np.stack([mdl.completeness(theta, PTS_M, PTS_Z, depth=PTS_D),
                         mdl.selection_given_recovered(theta, PTS_Z, PTS_M, depth=PTS_D)])

    return surfaces(th), surfaces(d)


def _hits(truth, vals, p, shrink=1.0):
    lo, med, hi = np.quantile(vals, [0.5 - p / 2, 0.5, 0.5 + p / 2], axis=1)
    # Shrink towards the median as lo + (1 - shrink)(med - lo), which is lo itself at
    # shrink = 1: the form med - shrink (med - lo) rounds lo to 0 where lo << med (a C
    # of 1e-30 beside a median of 1e-5) and wrongly counts every truth below as covered.
    lo, hi = lo + (1.0 - shrink) * (med - lo), hi - (1.0 - shrink) * (hi - med)
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


def check_sbc(n_sets, tol, workers=N_WORKERS):
    """Run the SBC on data sets 0..n_sets-1 and assert coverage within ``tol`` (by level).

    Returns the summary lines (also printed).
    """
    t0 = time.perf_counter()
    hits, shrunk = run_sbc(n_sets, workers)
    per_set = hits.mean(axis=-1)                               # (n_sets, 2, 2)
    cov = per_set.mean(axis=0)
    mcse = per_set.std(axis=0, ddof=1) / np.sqrt(len(per_set))
    lines = [f"SBC (depth-aware): {n_sets} data sets x {len(PTS_Z)} points, {PILOT} pilot, "
             f"{time.perf_counter() - t0:.1f} s"]
    for i, name in enumerate("CS"):
        for j, p in enumerate(LEVELS):
            lines.append(f"  {name} {p:.0%}: coverage {cov[i, j]:.3f} +- {mcse[i, j]:.3f} (MC s.e.), "
                         f"tolerance {tol[p]:.2f}")
    shrunk_cov = shrunk.mean(axis=(0, 2))
    lines.append(f"  intervals shrunk by {1 - SHRINK:.0%}: 68 % coverage C {shrunk_cov[0]:.3f}, "
                 f"S {shrunk_cov[1]:.3f} (must be < {LEVELS[0] - tol[LEVELS[0]]:.2f})")
    print("\n".join(lines))
    for i, name in enumerate("CS"):
        for j, p in enumerate(LEVELS):
            assert abs(cov[i, j] - p) <= tol[p], f"{name} {p:.0%} interval covers {cov[i, j]:.1%}"
            # Enough data sets that the tolerance is >= 2 Monte Carlo standard errors.
            assert mcse[i, j] <= tol[p] / 2, f"{name} {p:.0%}: MC error {mcse[i, j]:.3f} too large"
    # Power: a 25 % too narrow 68 % interval is caught by the same tolerance.
    assert np.all(shrunk_cov < LEVELS[0] - tol[LEVELS[0]])
    return lines


def test_depth_aware_sbc_coverage_small():
    """64 data sets: coverage within 8 points at 68 %, 5 at 95 % (the full test: 5 and 3)."""
    check_sbc(N_SETS_SMALL, TOL_SMALL)


@pytest.mark.slow
def test_depth_aware_sbc_coverage():
    """220 data sets (GLACIAR_SBC_SETS): within 5 points at 68 %, 3 at 95 %."""
    check_sbc(N_SETS, TOL)
