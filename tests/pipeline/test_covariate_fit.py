"""glaciar fit --covariates: refusals that cost no sampling (the fit itself: tests/inference/test_covariates.py)."""
import shutil

import pytest

from glaciar import constants as C
from glaciar.cli import main
from glaciar.pipeline.covariate_fit import add_covariates


def test_unknown_covariate_is_refused_before_fitting(small_run, tmp_path, capsys):
    _, run = small_run
    dst = tmp_path / "run"
    shutil.copytree(run, dst, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    assert main(["fit", str(dst), "--covariates", "r_eff,size", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'size'" in err[0] and "r_eff" in err[0]
    assert not (dst / "selection_function.fits").exists()


def test_covariates_need_a_fitted_run(small_run, tmp_path):
    _, run = small_run
    dst = tmp_path / "run"
    shutil.copytree(run, dst, ignore=shutil.ignore_patterns(C.LOCK_NAME, "selection_function.fits"))
    with pytest.raises(ValueError, match="run `glaciar fit` first"):
        add_covariates(dst, "r_eff")
