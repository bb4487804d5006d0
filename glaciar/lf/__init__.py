"""Luminosity functions on top of the selection function: models, Poisson likelihood, sampling.

The observed candidates' measured magnitudes are compared, bin by bin, with the counts a
luminosity function phi(M_UV) predicts through the selection probability P = C S and the
photometric transfer function (:meth:`glaciar.inference.SelectionFunction.expected_counts`),
marginalised over the selection function's posterior draws.

- :mod:`~glaciar.lf.models` -- :func:`schechter`, :func:`double_power_law`, :func:`stepwise`,
  their priors, :func:`parse_fix`;
- :mod:`~glaciar.lf.fit` -- :func:`fit_lf` (-> :class:`LFResult`), :func:`expected_counts`.

Arrays in, results out; no file I/O (``glaciar lf`` is :func:`glaciar.pipeline.lf.run_lf`).
"""
from .fit import LFPosterior, LFResult, default_window, expected_counts, fit_lf
from .models import (MODELS, PRIORS, LFModel, double_power_law, get_model, parse_fix, schechter,
                     stepwise)

__all__ = ["fit_lf", "LFResult", "LFPosterior", "expected_counts", "default_window", "schechter",
           "double_power_law", "stepwise", "LFModel", "get_model", "parse_fix", "MODELS", "PRIORS"]
