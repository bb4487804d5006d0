"""glaciar export --format jollof: written, then read back the way jollof's driver reads it.

jollof (bd-j/jollof, jof.py and lf.py) reads each axis and image with
``np.asarray(fits.getdata(path, EXTNAME), dtype=np.float32)`` and interpolates with
``RegularGridInterpolator((axis1, axis2), image, bounds_error=False, fill_value=0)``:
DET_COMP on (MAB, LOGRHALF [log10 arcsec]), SEL_COMP on (Z, MUV).  That reading is
re-implemented here (jollof is not imported) and compared with the selection function.
"""
import numpy as np
import pytest
from astropy.io import fits
from scipy.interpolate import RegularGridInterpolator

from analytic_sf import lf_sf
from glaciar.cli import main
from glaciar.inference.covariates import CovariateNodes
from glaciar.inference.products import beta_nodes, kcorrection


def sized_sf():
    """lf_sf with a size covariate: m50 moves by -1.5 mag per dex of r_e over 3 nodes."""
    sf = lf_sf(n_draws=4)
    i = sf.model.param_names.index("m50_0")
    x = np.array([-1.4, -1.0, -0.6])
    draws = np.stack([sf.draws.copy() for _ in x])
    draws[:, :, i] += (-1.5 * (x - x[1]))[:, None]
    sf.covariates = {"r_eff": CovariateNodes(
        name="r_eff", centres=x, edges=np.array([-1.6, -1.2, -0.8, -0.4]), draws=draws,
        n_sources=np.array([100] * 3), n_cells=np.array([10] * 3), n_extreme=np.zeros(3, int),
        adequate=np.ones(3, bool))}
    return sf


def jollof_read(path, image, ax1, ax2):
    g1 = np.asarray(fits.getdata(path, ax1), dtype=np.float32)
    g2 = np.asarray(fits.getdata(path, ax2), dtype=np.float32)
    comp = np.asarray(fits.getdata(path, image), dtype=np.float32)
    return g1, g2, RegularGridInterpolator((g1, g2), comp, bounds_error=False, fill_value=0.0)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("export")
    sf = sized_sf()
    sf.write(tmp / "selection_function.fits")
    assert main(["export", str(tmp), "--format", "jollof", "--out", str(tmp / "jollof")]) == 0
    return sf, tmp / "jollof"


def test_det_comp_read_as_jollof_matches_completeness_at_the_nodes(exported):
    sf, out = exported
    mab, lrh, comp = jollof_read(out / "detection_completeness.fits", "DET_COMP", "MAB", "LOGRHALF")
    assert mab[0] == pytest.approx(24.0) and mab[-1] == pytest.approx(30.0)
    assert lrh[0] == pytest.approx(-1.6) and lrh[-1] == pytest.approx(-0.4)
    zd = np.asarray(sf.z_grid if sf.z_grid is not None else np.linspace(6.0, 8.0, 41))
    m64 = np.asarray(fits.getdata(out / "detection_completeness.fits", "MAB")["MAB"], float)
    x64 = np.asarray(fits.getdata(out / "detection_completeness.fits", "LOGRHALF")["LOGRHALF"], float)
    for j in (0, 7, 24):
        for i in (0, 25, 36, 60):
            c = sf.completeness(np.full(len(zd), m64[i]), zd, r_eff_arcsec=10.0 ** x64[j],
                                draws=True)
            want = np.median(np.mean(c, axis=1))
            assert comp((mab[i], lrh[j])) == pytest.approx(want, abs=2e-5)   # float32 axes
    # bigger sources are less complete at fixed magnitude, as the covariate says
    assert comp((27.6, -1.5)) > comp((27.6, -0.5)) + 0.3


def test_sel_comp_read_as_jollof_matches_selection_at_the_nodes(exported):
    sf, out = exported
    z, muv, comp = jollof_read(out / "selection_completeness.fits", "SEL_COMP", "Z", "MUV")
    bn, bw = beta_nodes(sf.sed.beta_mean, sf.sed.beta_sd, 5)
    for iz in (0, 20, 40):
        k = kcorrection([float(z[iz])], bn, sf.sed.detection_filter, igm=sf.sed.igm,
                        cosmology=sf.sed.cosmology)[0]
        for iM in (0, 10, len(muv) - 1):
            s = sum(w * sf.selection_given_recovered(float(z[iz]), float(muv[iM]) + kb, draws=True,
                                                     outside="extrapolate")
                    for kb, w in zip(k, bw))
            assert comp((z[iz], muv[iM])) == pytest.approx(np.median(s), abs=2e-5)


def test_export_needs_a_size_fit(tmp_path):
    lf_sf().write(tmp_path / "plain.fits")
    assert main(["export", str(tmp_path / "plain.fits"), "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()
