"""Filter curves: built-ins, file formats, AB magnitudes against synphot."""
import warnings

import numpy as np
import pytest

from glaciar.constants import C_ANGSTROM_PER_S
from glaciar.galaxy.filters import (Filter, ab_magnitude, builtin_filter_names, get_filter,
                                    read_filter_file)

HST_JWST = ["wfc3_ir_f098m", "wfc3_ir_f160w", "wfc3_uvis_f606w", "acs_wfc_f435w",
            "acs_wfc_f850lp", "nircam_f090w", "nircam_f200w", "nircam_f444w"]


def _spectra():
    wave = np.geomspace(1500.0, 60000.0, 30000)
    power_law = 3e-18 * (wave / 1e4) ** -1.3
    # Planck law, T = 8000 K, arbitrary scale [erg/s/cm^2/A]
    blackbody = 1e5 / wave**5 / np.expm1(1.438777e8 / (wave * 8000.0))
    return wave, {"power_law": power_law, "blackbody": blackbody}


@pytest.mark.parametrize("name", HST_JWST)
def test_ab_magnitude_matches_synphot(name):
    """Photon-counting AB magnitude equals synphot's effstim to 1e-3 mag.

    synphot extrapolates a tabulated bandpass beyond its last sample by
    default; our convention is zero throughput outside the table, so synphot
    is given the same integration wavelengths (union of the filter's and the
    spectrum's samples inside the filter range).
    """
    import astropy.units as u
    from synphot import Observation, SourceSpectrum, SpectralElement
    from synphot.models import Empirical1D

    filt = get_filter(name)
    bp = SpectralElement(Empirical1D, points=filt.wave_angstrom * u.AA,
                         lookup_table=filt.throughput)
    wave, spectra = _spectra()
    inside = (wave > filt.wave_angstrom[0]) & (wave < filt.wave_angstrom[-1])
    grid = np.union1d(filt.wave_angstrom, wave[inside]) * u.AA
    for flam in spectra.values():
        sp = SourceSpectrum(Empirical1D, points=wave * u.AA,
                            lookup_table=flam * u.Unit("erg / (s cm2 AA)"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref = Observation(sp, bp, force="taper").effstim(u.ABmag, wavelengths=grid).value
        assert abs(ab_magnitude(wave, flam, filt) - ref) < 1e-3
    assert abs(filt.pivot_wavelength_angstrom - bp.pivot().to_value(u.AA)) < 1e-6 * bp.pivot().value


def test_flat_fnu_same_magnitude_in_every_band():
    """f_nu = const = 10^(-0.4 (m + 48.6)) has AB magnitude m in any band."""
    wave = np.geomspace(1000.0, 60000.0, 200000)
    m_true = 23.7
    fnu = 10 ** (-0.4 * (m_true + 48.60))
    flam = fnu * C_ANGSTROM_PER_S / wave**2
    for name in builtin_filter_names():
        if name == "wfc3_uvis_f600lp":
            continue
        assert abs(ab_magnitude(wave, flam, name) - m_true) < 1e-4, name


def test_zero_flux_is_inf_without_warning():
    wave = np.linspace(1000, 60000, 1000)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert ab_magnitude(wave, np.zeros_like(wave), "f160w") == np.inf
        # spectrum entirely outside the band
        w_blue = np.linspace(1000, 5000, 100)
        assert ab_magnitude(w_blue, np.ones_like(w_blue), "f160w") == np.inf


def test_aliases_and_ambiguity():
    assert get_filter("F160W") is get_filter("wfc3_ir_f160w")
    assert get_filter("f444w") is get_filter("nircam_f444w")
    assert get_filter("f435w").name == "acs_wfc_f435w"
    for short, choices in [("f606w", {"wfc3_uvis_f606w", "acs_wfc_f606w"}),
                           ("F814W", {"wfc3_uvis_f814w", "acs_wfc_f814w"})]:
        with pytest.raises(ValueError, match="ambiguous") as err:
            get_filter(short)
        assert all(c in str(err.value) for c in choices)
    with pytest.raises(ValueError, match="unknown filter"):
        get_filter("f999w")


def test_builtin_set_and_pivots():
    """Every advertised band loads (except F600LP) with a sensible pivot."""
    expected_pivot = {"wfc3_ir_f160w": 15369, "wfc3_ir_f125w": 12486, "wfc3_uvis_f606w": 5887,
                      "acs_wfc_f814w": 8060, "nircam_f444w": 44017, "nircam_f090w": 9024}
    for name in builtin_filter_names():
        if name == "wfc3_uvis_f600lp":
            continue
        f = get_filter(name)
        # band number: micron x 100 for WFC3/IR and NIRCam, nm for UVIS and ACS
        scale = 100 if name.startswith(("wfc3_ir", "nircam")) else 10
        band = int(name.rsplit("_f", 1)[1][:3]) * scale
        assert 0.75 * band < f.pivot_wavelength_angstrom < 1.15 * band, name
    for name, pivot in expected_pivot.items():
        assert abs(get_filter(name).pivot_wavelength_angstrom - pivot) < 2, name


def test_f600lp_not_shipped_error():
    with pytest.raises(ValueError, match="path of a throughput file"):
        get_filter("wfc3_uvis_f600lp")
    with pytest.raises(ValueError, match="path of a throughput file"):
        get_filter("f600lp")


def test_glaciar_tab_formats(tmp_path):
    """GLACiAR's .tab files load as they are: with a '# col2 col3' header,
    bare two columns, and f140w.IR.tab's leading row counter."""
    wave = np.arange(1700.0, 1710.0)
    thr = np.array([0, 0, 0.1, 0.3, 0.5, 0.52, 0.4, 0.2, 0.05, 0.0])
    p1 = tmp_path / "f160w.tab"
    p1.write_text("# col2     col3  \n" + "".join(f"  {w:.1f}   {t:.6E}   \n" for w, t in zip(wave, thr)))
    p2 = tmp_path / "f105w.tab"
    p2.write_text("".join(f"{w:.0f}.\t{t}\n" for w, t in zip(wave, thr)))
    p3 = tmp_path / "f140w.IR.tab"
    p3.write_text("".join(f"{i + 1:5d}  {w:14.0f}.  {t:14.6E}\n" for i, (w, t) in enumerate(zip(wave, thr))))
    for p, name in [(p1, "f160w"), (p2, "f105w"), (p3, "f140w.IR")]:
        f = get_filter(str(p))
        assert f.name == name
        np.testing.assert_array_equal(f.wave_angstrom, wave)
        np.testing.assert_allclose(f.throughput, thr, rtol=1e-12)


def test_csv_with_header_and_par(tmp_path):
    p = tmp_path / "band.csv"
    p.write_text("# from somewhere\nWAVELENGTH,THROUGHPUT\n5000,0\n5100,0.5\n5200,0\n")
    f = read_filter_file(p)
    np.testing.assert_array_equal(f.throughput, [0, 0.5, 0])
    assert get_filter(p) is f          # cached per unchanged file


def test_fits_round_trip(tmp_path):
    from astropy.table import Table

    wave_nm = np.linspace(600.0, 700.0, 51)
    thr = np.exp(-0.5 * ((wave_nm - 650.0) / 15.0) ** 2)
    t = Table({"WAVELENGTH": wave_nm, "THROUGHPUT": thr})
    t["WAVELENGTH"].unit = "nm"
    path = tmp_path / "gauss.fits"
    t.write(path)
    f = read_filter_file(path)
    np.testing.assert_allclose(f.wave_angstrom, wave_nm * 10.0, rtol=1e-14)
    np.testing.assert_allclose(f.throughput, thr, rtol=1e-14)
    # no unit -> Angstrom, other column names -> first two columns
    t2 = Table({"lam": wave_nm * 10.0, "resp": thr})
    t2.write(tmp_path / "plain.fits")
    f2 = get_filter(str(tmp_path / "plain.fits"))
    np.testing.assert_allclose(f2.wave_angstrom, wave_nm * 10.0)


def test_bad_files_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.tab"):
        get_filter(str(tmp_path / "missing.tab"))
    p = tmp_path / "neg.dat"
    p.write_text("5000 0\n5100 -0.1\n5200 0\n")
    with pytest.raises(ValueError, match="neg.dat.*>= 0"):
        read_filter_file(p)
    p = tmp_path / "order.dat"
    p.write_text("5000 0\n5200 0.5\n5100 0\n")
    with pytest.raises(ValueError, match="order.dat.*increasing"):
        read_filter_file(p)
    p = tmp_path / "micron.dat"
    p.write_text("1.5 0\n1.6 0.5\n1.7 0\n")
    with pytest.raises(ValueError, match="micron.dat.*Angstrom"):
        read_filter_file(p)
    p = tmp_path / "junk.dat"
    p.write_text("5000 0\n5100 abc\n")
    with pytest.raises(ValueError, match="junk.dat, line 2"):
        read_filter_file(p)


def test_filter_validation():
    with pytest.raises(ValueError, match="increasing"):
        Filter("x", [2, 1, 3], [0, 1, 0])
    with pytest.raises(ValueError, match="zero everywhere"):
        Filter("x", [1, 2, 3], [0, 0, 0])
    f = Filter("x", [1000.0, 2000.0, 3000.0], [0.0, 1.0, 0.0])
    with pytest.raises(ValueError):
        f.throughput[0] = 1.0        # read-only arrays
