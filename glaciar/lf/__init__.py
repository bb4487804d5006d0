"""Luminosity functions on top of the selection function: models, Poisson likelihood, sampling.

The observed candidates' measured magnitudes are compared, bin by bin, with the counts a
luminosity function phi(M_UV) predicts through the selection probability P = C S and the
photometric transfer function (:meth:`glaciar.inference.SelectionFunction.expected_counts`),
marginalised over the selection function's posterior draws.

- :mod:`~glaciar.lf.models` -- :func:`schechter`, :func:`double_power_law`, :func:`stepwise`,
  their priors, :func:`parse_fix`;
- :mod:`~glaciar.lf.fit` -- :func:`fit_lf` (-> :class:`LFResult`), :func:`expected_counts`.

Arrays in, results out; no file I/O (``glaciar lf`` is :func:`glaciar.pipeline.lf.run_lf`).
The module itself is callable, as the public API's ``glaciar.lf``:
``glaciar.lf(run_dir, catalog, model="schechter", fix=..., muv_range=..., z_range=...)`` runs
``glaciar lf`` and returns the :class:`LFResult` (``.parameters``, ``.counts``,
``.binned_phi``; ``.path`` is ``RUN_DIR/lf``).
"""
import sys as _sys
import types as _types

from .fit import LFPosterior, LFResult, default_window, expected_counts, fit_lf
from .models import (MODELS, PRIORS, LFModel, double_power_law, get_model, parse_fix, schechter,
                     stepwise)

__all__ = ["fit_lf", "LFResult", "LFPosterior", "expected_counts", "default_window", "schechter",
           "double_power_law", "stepwise", "LFModel", "get_model", "parse_fix", "MODELS", "PRIORS"]


class _CallableModule(_types.ModuleType):
    """``glaciar.lf`` is both this package and the public API's ``glaciar lf`` (a package and a
    function of one name cannot both be attributes of ``glaciar``)."""

    def __call__(self, run_dir, catalog=None, *, model: str = "schechter", fix=None, muv_range=None,
                 z_range=None, seed: int = 0, progress: bool = False) -> "LFResult":
        """Fit a luminosity function to a run's candidates and write ``RUN_DIR/lf/``
        (:func:`glaciar.pipeline.lf.run_lf`); returns the :class:`LFResult`."""
        from ..pipeline.lf import run_lf

        return run_lf(run_dir, catalog, model=model, fix=fix, muv_range=muv_range, z_range=z_range,
                      seed=seed, progress=progress, return_result=True)


_sys.modules[__name__].__class__ = _CallableModule
