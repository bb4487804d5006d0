"""A GLACiAR user's parameters.yaml and file layout run as they are."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import Table

from glaciar import constants as C
from glaciar.cli import main
from glaciar.config import ConfigError, check_files, config_from_dict, config_to_dict, load_config
from glaciar.demo import DEMO_BANDS, make_demo_images
from glaciar.engine.selection import DEFAULT_JDROPOUT

PARAMS = """\
n_galaxies: 6
n_iterations: 1
mag_bins: 2
min_mag: 24.0
max_mag: 27.0
z_bins: 1
min_z: 8.0
max_z: 8.0
n_bands: 4
lambda_detection: 15369.14
detection_band: f160w
bands: [f160w, f098m, f125w, f606w]
zeropoints: [25.946, 25.667, 26.230, 26.08]
gain_values: [2800, 4200, 2600, 3200]
list_of_fields: fields.txt
R_eff: 1.075
beta_mean: -2.0
beta_sd: 0.0
size_pix: 0.08
path_to_images: images/
image_name: borg_
types_galaxies: 2
sersic_indices: [1, 4]
fraction_type_galaxies: [0.5, 0.5]
ibins: 1
ebins: 1
min_sn: 8.0
dropouts: yes
de_Vacouleur: No
"""


def _write_glaciar_images(tmp_path, suffix):
    """A 200^2 demo field in GLACiAR's naming: <image_name><field>_<band><suffix>, _rms<suffix>."""
    imgs = make_demo_images((200, 200), seed=5)
    (tmp_path / "images").mkdir()
    hdr = fits.Header({"CTYPE1": "RA---TAN", "CTYPE2": "DEC--TAN", "CD1_1": -0.08 / 3600,
                       "CD2_2": 0.08 / 3600, "CD1_2": 0.0, "CD2_1": 0.0, "CRPIX1": 100.0,
                       "CRPIX2": 100.0, "CRVAL1": 150.0, "CRVAL2": 2.0})
    for band in DEMO_BANDS:
        w = imgs["weight"][band]
        rms = np.where(w > 0, 1 / np.sqrt(np.where(w > 0, w, 1)), 0).astype(np.float32)
        stem = tmp_path / "images" / f"borg_0440-5244_{band}"
        fits.PrimaryHDU(imgs["science"][band], hdr).writeto(f"{stem}{suffix}")
        fits.PrimaryHDU(rms, hdr).writeto(f"{stem}_rms{suffix}")


def test_glaciar_parameters_file_runs(tmp_path, capsys):
    _write_glaciar_images(tmp_path, ".fits")
    (tmp_path / "fields.txt").write_text("0440-5244  some comment\n")
    (tmp_path / "parameters.yaml").write_text(PARAMS)
    out = tmp_path / "run"
    rc = main(["simulate", str(tmp_path / "parameters.yaml"), "--out", str(out), "--workers", "1", "--quiet"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "warning:" in captured.err            # the mapping's caveats are shown
    t = Table.read(out / C.SUMMARY_DIRNAME / "summary_0440-5244.ecsv")
    # GLACiAR bins: min + k (max - min) / (bins - 1)
    np.testing.assert_allclose(sorted(set(t["mag"])), [24.0, 27.0])
    np.testing.assert_allclose(t["z"], 8.0)
    assert (t["n_input"] == 6).all()


def test_glaciar_gzipped_layout_with_headerless_psfs_runs(tmp_path, capsys):
    """GLACiAR as users have it: .fits.gz images and PSFs in Files/ with no pixel scale.

    Also checks that R_eff reaches the sources as GLACiAR means it: pixels at z = 6
    (hand computation through astropy's Planck18 distances, independent of glaciar's code).
    """
    from astropy import units as u
    from astropy.cosmology import Planck18

    from glaciar.engine.context import R_EFF_LOG_STEP
    from glaciar.store import read_results

    _write_glaciar_images(tmp_path, ".fits.gz")
    (tmp_path / "Files").mkdir()
    yy, xx = np.mgrid[-8:9, -8:9]
    for band in DEMO_BANDS:
        # A PSF at the image scale with a bare header (no PIXSCALE, no WCS), as GLACiAR ships.
        psf = np.exp(-(xx ** 2 + yy ** 2) / (2 * 0.95 ** 2)).astype(np.float32)
        fits.PrimaryHDU(psf).writeto(tmp_path / "Files" / f"psf_{band}.fits")
    (tmp_path / "fields.txt").write_text("0440-5244  some comment\n")
    (tmp_path / "parameters.yaml").write_text(PARAMS.replace("R_eff: 1.075", "R_eff: 2.4"))
    out = tmp_path / "run"
    rc = main(["simulate", str(tmp_path / "parameters.yaml"), "--out", str(out), "--workers", "1",
               "--quiet"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    # R_eff = 2.4 px at z = 6 and 0.08"/px: theta = 0.192"; proper size theta x D_A(z = 6).
    arcsec = np.pi / 180 / 3600
    r6 = 2.4 * 0.08 * arcsec * Planck18.angular_diameter_distance(6.0).to(u.kpc).value
    assert '0.192"' in captured.err and f"{r6:.4g} proper kpc" in captured.err, captured.err
    rows = read_results(out)
    assert len(rows) == 12
    # glaciar's size law r(z) = r6 (7 / (1+z)) in proper kpc, then theta = r / D_A(z)
    r8 = r6 * 7 / 9
    np.testing.assert_allclose(rows["r_eff_kpc"], r8, rtol=1e-9)
    theta8 = r8 / Planck18.angular_diameter_distance(8.0).to(u.kpc).value / arcsec
    # r_e in pixels is rounded to a log grid of step R_EFF_LOG_STEP
    assert np.all(np.abs(np.log(rows["r_eff_arcsec"] / theta8)) <= R_EFF_LOG_STEP / 2 + 1e-12)


# ------------------------------------------------------------------------------
# GLACiAR parameters.yaml
# ------------------------------------------------------------------------------
GLACIAR_PARAMETERS = """\
n_galaxies: 100
n_iterations: 3
mag_bins: 21
min_mag: 24.0
max_mag: 28.0
z_bins: 13
min_z: 9.6
max_z: 12.0
n_bands: 4
lambda_detection: 15369.14
detection_band: f160w
bands:
- f160w
- f098m
- f125w
- f606w
zeropoints:
- 25.9463
- 25.6674
- 26.2303
- 26.0691
gain_values:
- 2008.803039
- 4208.810304
- 2205.871521
- 4698
list_of_fields: ../list.txt
R_eff: 1.075
beta_mean: -2.0
beta_sd: 0.0
size_pix: 0.08
path_to_images: ../
image_name: hlsp_borg_hst_wfc3_par
types_galaxies: 2
sersic_indices:
- 1
- 4
fraction_type_galaxies:
- 0.5
- 0.5
ibins: 1
ebins: 2
min_sn: 8.0
dropouts: yes
de_Vacouleur: yes
"""


@pytest.fixture
def glaciar_dir(tmp_path):
    (tmp_path / "GLACiAR").mkdir()
    (tmp_path / "list.txt").write_text("0440-5244 0.0\n0240-1857 0.0\n")
    p = tmp_path / "GLACiAR" / "parameters.yaml"
    p.write_text(GLACIAR_PARAMETERS)
    return p


def test_glaciar_parameters_file(glaciar_dir, tmp_path):
    cfg = load_config(glaciar_dir)
    s = cfg.survey
    assert s.fields == ("0440-5244", "0240-1857")
    assert s.band_names == ("f160w", "f098m", "f125w", "f606w") and s.detection_band == "f160w"
    # <path_to_images><image_name><field>_<band>.fits and ..._rms.fits, paths relative to the file
    assert s.image_dir / s.science.format(field="0440-5244", band="f125w") == \
        tmp_path / "hlsp_borg_hst_wfc3_par0440-5244_f125w.fits"
    assert s.noise.format(field="x", band="f098m") == "hlsp_borg_hst_wfc3_parx_f098m_rms.fits"
    assert s.noise_type == "rms" and s.pixel_scale_arcsec == 0.08
    assert [b.zeropoint for b in s.bands] == [25.9463, 25.6674, 26.2303, 26.0691]
    assert [b.gain for b in s.bands] == [2008.803039, 4208.810304, 2205.871521, 4698.0]
    assert [b.filter for b in s.bands] == ["wfc3_ir_f160w", "wfc3_ir_f098m", "wfc3_ir_f125w",
                                          "wfc3_uvis_f606w"]
    assert all(b.psf["profile"] == "moffat" for b in s.bands)
    # Bin centres min + k (max - min) / (bins - 1).
    np.testing.assert_allclose(cfg.grid.z_values, 9.6 + np.arange(13) * 2.4 / 12, atol=1e-9)
    np.testing.assert_allclose(cfg.grid.mag_values, 24.0 + np.arange(21) * 4.0 / 20, atol=1e-9)
    assert (cfg.simulation.n_galaxies, cfg.simulation.n_iterations) == (100, 3)
    src = cfg.source
    # R_eff is GLACiAR's size in pixels at z = 6: 1.075 px x 0.08"/px, as a proper size through
    # Planck18's angular-diameter distance at z = 6 (hand computation: theta [rad] x D_A).
    from astropy import units as u
    from astropy.cosmology import Planck18
    theta_rad = 1.075 * 0.08 / 3600 * np.pi / 180
    r_kpc = theta_rad * Planck18.angular_diameter_distance(6.0).to(u.kpc).value
    assert abs(src.r_eff_kpc_z6 / r_kpc - 1) < 1e-9 and 0.49 < r_kpc < 0.51
    note = next(w for w in cfg.warnings if w.startswith("R_eff"))
    assert f'{1.075 * 0.08:.4g}"' in note and f"{r_kpc:.4g} proper kpc" in note, note
    assert src.beta_mean == -2.0 and src.beta_sd == 0.0
    assert src.sersic_indices == (1.0, 4.0) and src.sersic_fractions == (0.5, 0.5)
    assert src.ellipticity_bins == 2 and src.position_angle_bins == 1
    assert src.round_de_vaucouleurs is True
    assert src.beta_per == "iteration" and src.igm == "sharp"
    assert cfg.classification.min_sn == 8.0
    assert cfg.selection == DEFAULT_JDROPOUT
    assert cfg.detection.phot_apertures == (2.0, 4.0, 6.0, 8.0, 10.0)
    text = "\n".join(cfg.warnings)
    for needle in ("R_eff", "kpc", "f606w", "ebins", "Moffat", "beta_per"):
        assert needle in text, needle
    # The mapped config is a normal config: it round-trips.
    assert config_from_dict(config_to_dict(cfg), tmp_path) == cfg


def test_glaciar_variants(glaciar_dir, tmp_path):
    gdir = glaciar_dir.parent
    data = yaml.safe_load(GLACIAR_PARAMETERS)
    # Quoted YAML 1.1 words; the appendix spelling of the index key; no dropouts.
    data.update(de_Vacouleur="No", dropouts="No", ibins=4, z_bins=15, min_z=9.0, max_z=11.9)
    data["sersic_indexes"] = data.pop("sersic_indices")
    (gdir / "Files").mkdir()
    (gdir / "Files" / "psf_f160w.fits").write_text("x")
    (gdir / "SExtractor_files").mkdir()
    (gdir / "SExtractor_files" / "parameters.sex").write_text("DETECT_THRESH 0.9\n")
    cfg = config_from_dict(data, gdir, "parameters.yaml")
    assert cfg.source.round_de_vaucouleurs is False and cfg.selection == ()
    assert cfg.source.position_angle_bins == 4
    np.testing.assert_allclose(cfg.grid.z_values, np.linspace(9.0, 11.9, 15), atol=1e-9)
    assert any("z_bins" in w and "0.2" in w for w in cfg.warnings)
    assert any("ibins" in w and "180" in w for w in cfg.warnings)
    assert cfg.survey.band("f160w").psf == str(gdir / "Files" / "psf_f160w.fits")
    # not FITS: no scale is guessed (the run's input check names the file)
    assert cfg.survey.band("f160w").psf_pixel_scale_arcsec is None
    assert any("psf_f160w" in w and "not readable" in w for w in cfg.warnings)
    assert cfg.detection.detect_thresh == 0.9
    assert cfg.detection.sex_file == str(gdir / "SExtractor_files" / "parameters.sex")
    # Non-standard band order: the J-dropout cuts follow GLACiAR's positional [H, Y, J, V].
    data.update(dropouts=True, min_sn=5)
    cfg = config_from_dict(data, gdir, "parameters.yaml")
    assert cfg.selection == ("sn_f160w >= 5", "sn_f606w < 1.5", "sn_f098m < 1.5",
                             "maglim_f125w - mag_f160w > 1.5")


def _glaciar_fits(path, data, header=None):
    from astropy.io import fits

    path.parent.mkdir(parents=True, exist_ok=True)
    fits.PrimaryHDU(np.asarray(data, dtype=np.float32), header).writeto(path)


def test_glaciar_psf_scale_from_size_pix(glaciar_dir):
    """A PSF without a header scale is at size_pix; a header scale, where there is one, wins."""
    from astropy.io import fits

    from glaciar.galaxy.psf import prepare_psf

    gdir = glaciar_dir.parent
    data = yaml.safe_load(GLACIAR_PARAMETERS)
    data["size_pix"] = 0.06
    yy, xx = np.mgrid[-7:8, -7:8]
    psf = np.exp(-(xx ** 2 + yy ** 2) / (2 * 1.5 ** 2))
    _glaciar_fits(gdir / "Files" / "psf_f160w.fits", psf)                   # no scale at all
    _glaciar_fits(gdir / "Files" / "psf_f125w.fits.gz", psf, fits.Header({"PIXSCALE": 0.13}))
    cfg = config_from_dict(data, gdir, "parameters.yaml")
    h, j = cfg.survey.band("f160w"), cfg.survey.band("f125w")
    assert h.psf == str(gdir / "Files" / "psf_f160w.fits") and h.psf_pixel_scale_arcsec == 0.06
    assert j.psf == str(gdir / "Files" / "psf_f125w.fits.gz") and j.psf_pixel_scale_arcsec is None
    assert any("psf_f160w" in w and "size_pix = 0.06" in w for w in cfg.warnings)
    assert any("psf_f125w" in w and "header pixel scale 0.13" in w for w in cfg.warnings)
    # At its own (image) scale the header-less PSF is used as written: odd, centred, sum 1.
    got = prepare_psf(h.psf, 0.06, psf_pixel_scale_arcsec=h.psf_pixel_scale_arcsec)
    np.testing.assert_allclose(got, psf / psf.sum(), rtol=1e-6)
    with pytest.raises(ValueError, match="psf_pixel_scale_arcsec"):       # as before, alone
        prepare_psf(h.psf, 0.06)


def test_glaciar_gzipped_images(glaciar_dir, tmp_path):
    """Images found as <path_to_images><image_name><field>_<band>.fits.gz are read gzipped."""
    gdir = glaciar_dir.parent
    stem = tmp_path / "hlsp_borg_hst_wfc3_par"
    bands = ("f160w", "f098m", "f125w", "f606w")
    for field in ("0440-5244", "0240-1857"):
        for b in bands:
            _glaciar_fits(Path(f"{stem}{field}_{b}.fits.gz"), np.ones((4, 4)))
            _glaciar_fits(Path(f"{stem}{field}_{b}_rms.fits.gz"), np.ones((4, 4)))
    cfg = load_config(glaciar_dir)
    s = cfg.survey
    assert s.image_dir / s.science.format(field="0440-5244", band="f125w") == \
        Path(f"{stem}0440-5244_f125w.fits.gz")
    assert s.noise.format(field="x", band="f098m") == "hlsp_borg_hst_wfc3_parx_f098m_rms.fits.gz"
    assert check_files(cfg) is None                          # every file named is there
    # A mixed layout: the majority naming, and a warning with the count left out.
    Path(f"{stem}0240-1857_f606w.fits.gz").unlink()
    _glaciar_fits(Path(f"{stem}0240-1857_f606w.fits"), np.ones((4, 4)))
    cfg = load_config(glaciar_dir)
    assert cfg.survey.science.endswith(".fits.gz")
    assert any("1 file(s) are .fits and 7 .fits.gz" in w and "1 file(s) not found" in w
               for w in cfg.warnings), cfg.warnings


def test_glaciar_size_pix_missing(glaciar_dir, tmp_path):
    """Without size_pix: the detection image's header scale, else GLACiAR's default 0.08"/px."""
    from astropy import units as u
    from astropy.cosmology import Planck18
    from astropy.io import fits

    gdir = glaciar_dir.parent
    data = yaml.safe_load(GLACIAR_PARAMETERS)
    data["size_pix"] = None          # GLACiAR: present and empty -> the default
    cfg = config_from_dict(data, gdir, "parameters.yaml")
    assert cfg.survey.pixel_scale_arcsec == 0.08
    assert any(w.startswith("size_pix") and "0.08" in w for w in cfg.warnings)
    hdr = fits.Header({"CTYPE1": "RA---TAN", "CTYPE2": "DEC--TAN", "CD1_1": -0.06 / 3600,
                       "CD2_2": 0.06 / 3600, "CD1_2": 0.0, "CD2_1": 0.0})
    _glaciar_fits(tmp_path / "hlsp_borg_hst_wfc3_par0440-5244_f160w.fits", np.ones((4, 4)), hdr)
    cfg = config_from_dict(data, gdir, "parameters.yaml")
    assert cfg.survey.pixel_scale_arcsec is None               # the survey reads the same WCS
    d_a = Planck18.angular_diameter_distance(6.0).to(u.kpc).value
    expected = 1.075 * 0.06 / 3600 * np.pi / 180 * d_a
    assert abs(cfg.source.r_eff_kpc_z6 / expected - 1) < 1e-6


@pytest.mark.parametrize("change, pattern", [
    ({"n_galaxy": 5}, r"n_galaxy: unknown key 'n_galaxy'; did you mean 'n_galaxies'\?"),
    ({"path_to_images": None}, r"path_to_images: missing required GLACiAR key"),
    ({"ebins": 0}, r"ebins: must be >= 1"),
    ({"n_bands": 3}, r"n_bands: is 3 but bands lists 4"),
    ({"detection_band": "f140w"}, r"detection_band: 'f140w' is not in bands"),
    ({"beta_sd": -1}, r"source\.beta_sd: must be >= 0.*from GLACiAR key 'beta_sd'"),
    ({"zeropoints": ["abc", 1, 2, 3]},
     r"survey\.bands\.f160w\.zeropoint: expected a number, got 'abc' \(from GLACiAR key 'zeropoints\[0\]'\)"),
    ({"fraction_type_galaxies": [0.5, 0.6]}, r"sersic_fractions: must sum to 1.*fraction_type_galaxies"),
    ({"survey": {}}, None),
])
def test_glaciar_errors(glaciar_dir, change, pattern):
    data = yaml.safe_load(GLACIAR_PARAMETERS)
    data.update(change)
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, glaciar_dir.parent, "parameters.yaml")
    msg = str(info.value)
    assert msg.startswith("parameters.yaml: ")
    if pattern:
        assert re.search(pattern, msg), msg


# ------------------------------------------------------------------------------
# GLACiAR's own SExtractor file through the command line (issue 21, bullet 9)
# ------------------------------------------------------------------------------
# GLACiAR's SExtractor template as its repository ships it: values GLACiAR fills per
# band before each call are left empty (GAIN, MAG_ZEROPOINT, WEIGHT_IMAGE, ...).
GLACIAR_SEX = """\
CATALOG_TYPE     ASCII_HEAD
PARAMETERS_NAME  SExtractor_files/default3.param
DETECT_TYPE      CCD
DETECT_MINAREA   9
DETECT_THRESH    0.7
ANALYSIS_THRESH  0.7
FILTER           Y
FILTER_NAME      SExtractor_files/gauss_2.0_5x5.conv
DEBLEND_NTHRESH  32
DEBLEND_MINCONT  0.005
CLEAN            Y
CLEAN_PARAM      1.0
MASK_TYPE        CORRECT
PHOT_APERTURES   2,4,6,8,10
PHOT_AUTOPARAMS  1.5, 3.5
PHOT_PETROPARAMS 2.0, 3.5
SATUR_LEVEL      50000.0
MAG_ZEROPOINT
MAG_GAMMA        4.0
GAIN
PIXEL_SCALE      0.08
SEEING_FWHM      0.2
STARNNW_NAME     SExtractor_files/default.nnw
BACK_SIZE        64
BACK_FILTERSIZE  3
BACKPHOTO_TYPE   GLOBAL
CHECKIMAGE_TYPE
CHECKIMAGE_NAME
MEMORY_OBJSTACK  3000
MEMORY_PIXSTACK  300000
MEMORY_BUFSIZE   1024
VERBOSE_TYPE     NORMAL
WRITE_XML        N
XML_NAME         sex.xml
WEIGHT_IMAGE
CATALOG_NAME
WEIGHT_TYPE MAP_RMS, MAP_RMS
WEIGHT_GAIN N,N
"""


def test_glaciar_own_parameters_sex_runs_with_the_per_band_gain(tmp_path, capsys):
    from glaciar import constants as C
    from glaciar.config import load_config
    from glaciar.store import read_results

    _write_glaciar_images(tmp_path, ".fits")
    (tmp_path / "fields.txt").write_text("0440-5244\n")
    (tmp_path / "parameters.yaml").write_text(PARAMS)
    (tmp_path / "SExtractor_files").mkdir()
    (tmp_path / "SExtractor_files" / "parameters.sex").write_text(GLACIAR_SEX)
    out = tmp_path / "run"
    rc = main(["simulate", str(tmp_path / "parameters.yaml"), "--out", str(out), "--workers", "1",
               "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "GAIN without a value" in err and "survey.bands.<band>.gain" in err
    stored = load_config(out / C.RUN_CONFIG_NAME)
    assert [b.gain for b in stored.survey.bands] == [2800, 4200, 2600, 3200]
    assert stored.detection.weight_type == "map_rms" and stored.detection.weight_gain is False
    assert stored.detection.phot_apertures == (2.0, 4.0, 6.0, 8.0, 10.0)
    assert len(read_results(out)) == 12
