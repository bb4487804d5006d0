"""The edges of the inference: read a run, fit, write the selection-function file, figures, summary.

:mod:`glaciar.inference` takes arrays and returns results; everything that
touches a file for the fit is here:

- :mod:`~glaciar.pipeline.fit` -- :func:`run_fit`, what ``glaciar fit`` calls;
- :mod:`~glaciar.pipeline.inputs` -- the flag columns and the manifest's areas of a run;
- :mod:`~glaciar.pipeline.chains` -- saved chains, so that a re-run resumes them;
- :mod:`~glaciar.pipeline.selection_file` -- what the fit adds to the selection-function
  file for LF codes (the injections' SED, V_eff(M_UV), transfer matrices; the file's
  layout is :mod:`glaciar.inference.selection_format`);
- :mod:`~glaciar.pipeline.figures` -- C and S with credible bands (Figures);
- :mod:`~glaciar.pipeline.summary` -- the summary and the lines ``glaciar fit`` prints;
- :mod:`~glaciar.pipeline.covariate_fit` -- ``glaciar fit --covariates``: size / beta bins added;
- :mod:`~glaciar.pipeline.export` -- ``glaciar export``: other codes' layouts (jollof).

The names below are imported on first use: ``glaciar simulate`` and ``glaciar report``
take the run's lock from :mod:`~glaciar.pipeline.fitdir`, which must not cost them the
inference's imports (emcee, h5py, scipy.stats: ~0.5 s and ~40 MB).
"""
from __future__ import annotations

import importlib

__all__ = ["run_fit", "FitWarning", "format_summary", "MODEL_CHOICES"]

#: Where each public name lives (imported by :func:`__getattr__` when first asked for).
_LAZY = {"run_fit": ".fit", "FitWarning": ".fit", "MODEL_CHOICES": ".fit",
         "format_summary": ".summary"}


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name], __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
