"""Bayesian completeness and selection surfaces: models, fit, adaptive proposals, export."""
from .adaptive import propose_cells
from .fit import (ConvergenceWarning, FitResult, aggregate_cells, find_map, fit_surfaces,
                  laplace_covariance, ppc_table, run_fit)
from .models import COMPLETENESS_SHAPES, Cells, SurfaceModel
from .selection_function import EffectiveVolume, SelectionFunction

__all__ = ["propose_cells", "ConvergenceWarning", "FitResult", "aggregate_cells", "find_map",
           "fit_surfaces", "laplace_covariance", "ppc_table", "run_fit", "COMPLETENESS_SHAPES",
           "Cells", "SurfaceModel", "EffectiveVolume", "SelectionFunction"]
