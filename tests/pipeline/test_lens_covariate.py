"""glaciar fit and the magnification covariate (glaciar.pipeline.lens_covariate).

A lensed run's fit gets it (the lensed demo: docs/lensing.md); an unlensed run's fit never
reads the magnification column nor fits it, so its file is the one of a fit without it.
"""
import io
import shutil
import warnings

from astropy.io import fits

from glaciar import constants as C
from glaciar.inference import SelectionFunction
from glaciar.inference.sampling import SamplerSettings
from glaciar.pipeline import run_fit
import glaciar.pipeline.fit as fit_module


def test_unlensed_fit_never_fits_the_magnification(small_run, tmp_path, monkeypatch):
    _, run = small_run
    dst = tmp_path / "run"
    shutil.copytree(run, dst, ignore=shutil.ignore_patterns(C.LOCK_NAME, "selection_function.fits",
                                                            "fit"))

    def refuse(*a, **k):
        raise AssertionError("the magnification covariate was fitted for an unlensed run")
    monkeypatch.setattr(fit_module, "fit_magnification", refuse)
    monkeypatch.setattr(fit_module, "magnification_rows", refuse)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = run_fit(dst, model="logistic", plots=False, write=False,
                      sampler=SamplerSettings(max_steps=40, seed=1, progress=False))
    assert [sf.covariates for sf in got] == [{}]
    with fits.open(io.BytesIO(SelectionFunction.to_bytes(got, got[0].meta))) as h:
        names = [x.name for x in h]
    assert "LENS" not in names and not any(n.startswith("CV_") for n in names)
