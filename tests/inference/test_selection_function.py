"""Area bookkeeping of the exported selection function (per-field areas from the run manifest)."""
import numpy as np
import pytest

from glaciar.inference import SelectionFunction, SurfaceModel


def _sf(field, area):
    mdl = SurfaceModel.for_data(np.array([8.0, 9.0, 10.0]), np.array([25.0, 26.0, 27.0]))
    th = mdl.sample_prior(4, np.random.default_rng(0))
    return SelectionFunction(mdl, th, meta={"area_arcmin2": area}, field=field)


def test_area_from_per_field_mapping():
    areas = {"a": 1.5, "b": 2.25}
    assert _sf("a", areas).area_arcmin2() == 1.5
    assert _sf("all", areas).area_arcmin2() == 3.75
    assert _sf("all", 4.0).area_arcmin2() == 4.0
    assert _sf("all", None).area_arcmin2() is None


def test_area_prefers_the_per_field_entry():
    mdl = SurfaceModel.for_data(np.array([8.0, 9.0]), np.array([25.0, 26.0]))
    th = mdl.sample_prior(2, np.random.default_rng(1))
    meta = {"area_arcmin2": 4.0, "area_arcmin2_field": {"a": 1.0, "b": 3.0}}
    assert SelectionFunction(mdl, th, meta=meta, field="b").area_arcmin2() == 3.0
    assert SelectionFunction(mdl, th, meta=meta, field="all").area_arcmin2() == 4.0


def test_effective_volume_scales_with_field_area():
    areas = {"a": 1.0, "b": 3.0}
    va = _sf("a", areas).effective_volume(np.array([26.0]))
    vb = _sf("b", areas).effective_volume(np.array([26.0]))
    # Same surfaces, areas 1 and 3: volumes in the same ratio.
    np.testing.assert_allclose(vb.median / va.median, 3.0, rtol=1e-12)


def test_file_header_area_is_total(tmp_path):
    from astropy.io import fits

    path = tmp_path / "sf.fits"
    _sf("a", {"a": 1.0, "b": 3.0}).write(path)
    assert fits.getheader(path)["AREA"] == pytest.approx(4.0)
