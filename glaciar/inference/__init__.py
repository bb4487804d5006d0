"""Bayesian completeness and selection surfaces: models, fit, sampling, diagnostics, proposals.

Arrays in, results out; no file I/O but one: the selection function's own file,
which :class:`SelectionFunction` reads and writes whole (``read``/``write``; the layout
is a codec on bytes, :mod:`~glaciar.inference.selection_format`), because that is how a
luminosity-function code loads it.  Reading a run directory, the chains, tables and
figures are :mod:`glaciar.pipeline`'s job (``glaciar fit`` is
:func:`glaciar.pipeline.run_fit`); this package never imports it.

- :mod:`~glaciar.inference.models` -- the surfaces C(m, z) and S(z, m), priors, likelihood;
- :mod:`~glaciar.inference.fit` -- aggregation into cells, MAP, :func:`fit_surfaces`,
  :func:`fit_and_choose` (completeness step by PSIS-LOO);
- :mod:`~glaciar.inference.sampling` -- emcee per parameter block, convergence;
- :mod:`~glaciar.inference.diagnostics` -- PPC, PSIS-LOO, redshift-edge check;
- :mod:`~glaciar.inference.selection_function` -- the fitted selection function, V_eff;
- :mod:`~glaciar.inference.selection_format` -- its file's layout, bytes <-> fits;
- :mod:`~glaciar.inference.products` -- value types of its products and the k-correction;
- :mod:`~glaciar.inference.transfer` -- the transfer function p(m_obs | m_in, z) anywhere;
- :mod:`~glaciar.inference.counts` -- expected counts per measured-magnitude bin of an LF;
- :mod:`~glaciar.inference.covariates` -- C given the size, S given beta; re-weighted V_eff;
- :mod:`~glaciar.inference.adaptive` -- where to simulate next, how many, when to stop.
"""
from .adaptive import (allocate_sources, allocate_variance_reduction, candidate_grid,
                       information_gain, max_posterior_sd, plan_round, propose_cells, run_design)
from .fit import (ConvergenceWarning, FitResult, aggregate_cells, find_map, fit_and_choose,
                  fit_surfaces, laplace_covariance)
from .models import COMPLETENESS_SHAPES, Cells, SurfaceModel
from .counts import CountKernel, ExpectedCounts, count_kernel, expected_counts
from .covariates import BetaDistribution, SizeRelation
from .products import EffectiveVolume
from .selection_function import SelectionFunction
from .transfer import TransferFunction, transfer_function

__all__ = ["propose_cells", "allocate_sources", "allocate_variance_reduction", "candidate_grid", "information_gain",
           "max_posterior_sd", "plan_round", "run_design", "ConvergenceWarning", "FitResult", "aggregate_cells", "find_map",
           "fit_and_choose", "fit_surfaces", "laplace_covariance", "COMPLETENESS_SHAPES",
           "Cells", "SurfaceModel", "EffectiveVolume", "SelectionFunction", "TransferFunction",
           "transfer_function", "CountKernel", "ExpectedCounts", "count_kernel", "expected_counts",
           "SizeRelation", "BetaDistribution"]

