"""Bayesian completeness and selection surfaces: models, fit, diagnostics, proposals, export.

Everything here takes arrays (or tables) and returns results; reading a run
directory and writing files is :mod:`glaciar.pipeline`'s job
(:func:`run_fit` is re-exported from there for convenience).
"""
from .adaptive import propose_cells
from .fit import (ConvergenceWarning, FitResult, aggregate_cells, find_map, fit_and_choose,
                  fit_surfaces,
                  laplace_covariance)
from .models import COMPLETENESS_SHAPES, Cells, SurfaceModel
from .selection_function import EffectiveVolume, SelectionFunction

__all__ = ["propose_cells", "ConvergenceWarning", "FitResult", "aggregate_cells", "find_map",
           "fit_and_choose", "fit_surfaces", "laplace_covariance", "run_fit", "COMPLETENESS_SHAPES",
           "Cells", "SurfaceModel", "EffectiveVolume", "SelectionFunction"]


def __getattr__(name):
    # run_fit lives at the I/O edge (glaciar.pipeline), which imports this package.
    if name == "run_fit":
        from ..pipeline import run_fit
        return run_fit
    raise AttributeError(f"module 'glaciar.inference' has no attribute {name!r}")
