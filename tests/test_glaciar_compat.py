"""A GLACiAR user's parameters.yaml and file layout run as they are."""
import numpy as np
from astropy.io import fits
from astropy.table import Table

from glaciar import constants as C
from glaciar.cli import main
from glaciar.demo import DEMO_BANDS, make_demo_images

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
