"""glaciar.pipeline's names are imported on first use: taking a run's lock
(glaciar.pipeline.fitdir, as `glaciar simulate` and `glaciar report` do) does not import
the inference (emcee, h5py)."""
from __future__ import annotations

import subprocess
import sys

import pytest


def test_fitdir_does_not_import_the_inference():
    code = ("import sys, glaciar.pipeline.fitdir; "
            "print(sorted(m for m in ('emcee', 'h5py', 'glaciar.inference', 'glaciar.pipeline.fit') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_public_names_still_import():
    import glaciar.pipeline as pipeline
    from glaciar.pipeline import MODEL_CHOICES, FitWarning, format_summary, run_fit
    from glaciar.pipeline.fit import run_fit as fit_run_fit
    from glaciar.pipeline.summary import format_summary as summary_format

    assert run_fit is fit_run_fit and format_summary is summary_format
    assert issubclass(FitWarning, Warning) and len(MODEL_CHOICES) > 0
    assert set(pipeline.__all__) <= set(dir(pipeline))
    with pytest.raises(AttributeError):
        pipeline.no_such_name
