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
"""
from .fit import MODEL_CHOICES, FitWarning, run_fit
from .summary import format_summary

__all__ = ["run_fit", "FitWarning", "format_summary", "MODEL_CHOICES"]
