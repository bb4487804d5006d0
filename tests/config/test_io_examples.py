"""The shipped example configurations (configs/): each loads with no warning, names
exactly the files its comments say the user supplies (by relative paths), and holds
the set-up it claims.

No image needs to exist: each file is copied into an empty temporary directory and
loaded there, so ``missing_files`` lists every input file, which must be exactly the
expected ones.  ``demo.yaml`` is also run against the files ``glaciar.demo`` writes.
"""
import inspect
import math
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from glaciar.config import load_config, missing_files
from glaciar.engine.selection import DEFAULT_JDROPOUT, compile_selection

REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"
SHIPPED = ("demo.yaml", "demo_lensed.yaml", "borg_jdropout.yaml", "jwst_nircam_z10.yaml")

DEMO_BANDS = ("f160w", "f098m", "f125w", "f606w")
BORG_BANDS = ("f160w", "f098m", "f125w", "f606w")
NIRCAM_BANDS = ("f090w", "f115w", "f150w", "f200w", "f277w", "f356w", "f444w")
#: Relative input files each config names (relative to the config's own directory).
EXPECTED_FILES = {
    "demo.yaml": (
        [f"../glaciar-demo/survey/images/demo01_{b}_{k}.fits" for b in DEMO_BANDS
         for k in ("drz", "wht")]
        + [f"../glaciar-demo/survey/psf/psf_{b}.fits" for b in DEMO_BANDS]),
    "demo_lensed.yaml": (
        [f"../glaciar-demo/survey/images/demo01_{b}_{k}.fits" for b in DEMO_BANDS
         for k in ("drz", "wht")]
        + [f"../glaciar-demo/survey/psf/psf_{b}.fits" for b in DEMO_BANDS]),
    "borg_jdropout.yaml": [f"borg/hlsp_borg_hst_wfc3_0440-5244_{b}_v2.0_{k}.fits"
                           for b in BORG_BANDS for k in ("drz", "wht")],
    "jwst_nircam_z10.yaml": (
        [f"images/field1_{b}_{k}.fits" for b in NIRCAM_BANDS for k in ("sci", "wht")]
        + [f"psf/nircam_{b}_psf.fits" for b in NIRCAM_BANDS]),
}


def _load_copy(name, where):
    """Copy configs/<name> into ``where`` and load it there; fail on any warning."""
    where.mkdir(parents=True, exist_ok=True)
    path = where / name
    shutil.copyfile(CONFIGS / name, path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cfg = load_config(path)
    assert cfg.warnings == ()
    return cfg


def test_configs_directory_holds_the_documented_examples():
    assert sorted(p.name for p in CONFIGS.iterdir() if p.suffix in (".yaml", ".yml")) \
        == sorted(SHIPPED)


@pytest.mark.parametrize("name", SHIPPED)
def test_config_loads_without_warnings(name):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cfg = load_config(CONFIGS / name)
    assert cfg.warnings == ()
    assert cfg.survey.detection_band in cfg.survey.band_names
    assert cfg.selection                                    # an explicit, non-empty selection
    columns = set(compile_selection(cfg.selection).columns)
    assert all(c.rsplit("_", 1)[-1] in cfg.survey.band_names for c in columns)


@pytest.mark.parametrize("name", SHIPPED)
def test_config_paths_are_relative(name):
    raw = yaml.safe_load((CONFIGS / name).read_text(encoding="utf-8"))
    s = raw["survey"]
    paths = [s["image_dir"], s["science"], s["noise"]]
    for b in s["bands"].values():
        paths.append(b["filter"])
        if isinstance(b["psf"], str):
            paths.append(b["psf"])
    for p in paths:
        assert not Path(p).is_absolute() and not p.startswith("~"), p


@pytest.mark.parametrize("name", SHIPPED)
def test_missing_files_are_exactly_the_users_inputs(name, tmp_path):
    where = tmp_path / "configs"
    cfg = _load_copy(name, where)
    got = {}
    for msg in missing_files(cfg):
        key, _, path = msg.rpartition(": ")
        got[Path(path)] = key
    expected = {(where / rel).resolve() for rel in EXPECTED_FILES[name]}
    assert {p.resolve() for p in got} == expected
    assert len(got) == len(EXPECTED_FILES[name])
    for path, key in got.items():
        kind = ("survey.bands" if "psf" in path.name else
                "survey.noise" if path.stem.endswith("_wht") else "survey.science")
        assert key.startswith(kind), (key, path)


# ---------------------------------------------------------------------------
# demo.yaml: the configuration glaciar.demo writes, pointing at its files
# ---------------------------------------------------------------------------
def test_demo_config_is_the_one_glaciar_demo_writes(small_survey, tmp_path):
    """configs/demo.yaml = what build_demo_survey writes with its defaults (`glaciar demo`),
    with the paths pointing from configs/ into glaciar-demo/survey/.

    ``small_survey`` (conftest; a small image and its own grid, sizes and seed) shares
    every other key with the default demo, so it is compared on those, and the grid and
    simulation keys against build_demo_survey's defaults.
    """
    from glaciar.demo import build_demo_survey

    ours = yaml.safe_load((CONFIGS / "demo.yaml").read_text(encoding="utf-8"))
    theirs = yaml.safe_load(small_survey.read_text(encoding="utf-8"))
    prefix = "../glaciar-demo/survey/"
    assert ours["survey"]["image_dir"] == prefix + theirs["survey"]["image_dir"]
    for b, spec in theirs["survey"]["bands"].items():
        assert ours["survey"]["bands"][b]["psf"] == prefix + spec["psf"]
        spec["psf"] = ours["survey"]["bands"][b]["psf"]
    theirs["survey"]["image_dir"] = ours["survey"]["image_dir"]
    defaults = {k: p.default for k, p in inspect.signature(build_demo_survey).parameters.items()}
    assert ours.pop("grid") == {"z": {"values": [round(float(v), 6) for v in defaults["z_values"]]},
                                "mag": {"values": [round(float(v), 6)
                                                   for v in defaults["mag_values"]]},
                                "magnitude_type": "apparent"}
    assert ours.pop("simulation") == {"n_galaxies": defaults["n_galaxies"],
                                      "n_iterations": defaults["n_iterations"],
                                      "seed": defaults["seed"]}
    del theirs["grid"], theirs["simulation"]
    assert ours == theirs

    # Next to the demo's files (as after `glaciar demo --out glaciar-demo` in the
    # repository's root) nothing is missing.
    (tmp_path / "glaciar-demo").mkdir()
    (tmp_path / "glaciar-demo" / "survey").symlink_to(small_survey.parent, target_is_directory=True)
    cfg = _load_copy("demo.yaml", tmp_path / "configs")
    assert missing_files(cfg) == []


# ---------------------------------------------------------------------------
# borg_jdropout.yaml: the paper's set-up (Carrasco et al. 2018, Sect. 3)
# ---------------------------------------------------------------------------
def test_borg_config_is_the_papers_setup():
    cfg = load_config(CONFIGS / "borg_jdropout.yaml")
    s = cfg.survey
    assert s.band_names == BORG_BANDS and s.detection_band == "f160w"
    assert [s.band(b).filter for b in BORG_BANDS] == [
        "wfc3_ir_f160w", "wfc3_ir_f098m", "wfc3_ir_f125w", "wfc3_uvis_f606w"]
    assert s.pixel_scale_arcsec == 0.08
    np.testing.assert_allclose(cfg.grid.z_values, np.linspace(9.6, 12.0, 13), atol=1e-9)
    np.testing.assert_allclose(cfg.grid.mag_values, np.linspace(24.0, 28.0, 21), atol=1e-9)
    assert cfg.grid.magnitude_type == "apparent"
    assert (cfg.simulation.n_galaxies, cfg.simulation.n_iterations) == (100, 100)
    src = cfg.source
    assert src.r_eff_kpc_z6 == 1.075 and src.size_evolution == -1.0
    assert (src.beta_mean, src.beta_sd) == (-2.2, 0.4)
    assert tuple(src.sersic_indices) == (1.0, 4.0) and tuple(src.sersic_fractions) == (0.5, 0.5)
    assert cfg.classification.min_sn == 8.0 and cfg.classification.sn_definition == "iso"
    # Bernard et al. (2016) J125-dropouts, as the paper lists them.
    assert cfg.selection == DEFAULT_JDROPOUT
    assert set(cfg.selection) == {"sn_f160w >= 8", "sn_f606w < 1.5", "sn_f098m < 1.5",
                                  "maglim_f125w - mag_f160w > 1.5"}


# ---------------------------------------------------------------------------
# jwst_nircam_z10.yaml: NIRCam F115W dropouts
# ---------------------------------------------------------------------------
def _noiseless_rows(cfg, z, m_uv=-20.0, one_sigma_mag=31.0, beta=-2.2):
    """Photometry columns of a noiseless source (1 sigma = ``one_sigma_mag`` in every band)."""
    from glaciar.galaxy import sed
    from glaciar.galaxy.filters import get_filter

    bands = cfg.survey.band_names
    filters = [get_filter(cfg.survey.band(b).filter) for b in bands]
    mags = sed.band_magnitudes(z, np.array([beta]), filters, M_uv=np.array([m_uv]),
                               cosmology="Planck18", igm="inoue14")[0]
    rows = {}
    for b, m in zip(bands, mags):
        zp = cfg.survey.band(b).zeropoint
        sigma = 10 ** (-0.4 * (one_sigma_mag - zp))
        flux = 10 ** (-0.4 * (m - zp)) if np.isfinite(m) else 0.0
        rows[f"sn_{b}"] = [flux / sigma]
        rows[f"mag_{b}"] = [zp - 2.5 * math.log10(flux) if flux > 0 else np.nan]
        rows[f"maglim_{b}"] = [zp - 2.5 * math.log10(max(flux, sigma))]
    return rows


def test_jwst_config_is_a_nircam_f115w_dropout_setup():
    cfg = load_config(CONFIGS / "jwst_nircam_z10.yaml")
    s = cfg.survey
    assert s.band_names == NIRCAM_BANDS
    assert [s.band(b).filter for b in NIRCAM_BANDS] == [f"nircam_{b}" for b in NIRCAM_BANDS]
    assert s.detection_image.coadd == ("f277w", "f356w", "f444w")
    assert s.detection_band in s.detection_image.coadd
    # The documented unit: MJy/sr on the 0.03"/px grid the config declares.
    assert s.pixel_scale_arcsec == 0.03
    pix_sr = (s.pixel_scale_arcsec / (180 / math.pi * 3600)) ** 2
    zp = -2.5 * math.log10(1e6 * pix_sr / 3631.0)
    for b in NIRCAM_BANDS:
        assert s.band(b).zeropoint == pytest.approx(zp, abs=1e-4)
        assert s.band(b).psf_pixel_scale_arcsec == s.pixel_scale_arcsec
    # Non-detection blueward of the break and the F115W - F150W break colour are cut on.
    assert "sn_f090w < 2" in cfg.selection
    assert any("maglim_f115w - mag_f150w >" in e for e in cfg.selection)


@pytest.mark.parametrize("z, selected", [(7.5, False), (8.0, False), (9.5, True), (10.0, True),
                                         (10.5, True), (11.0, True), (12.5, False), (13.0, False)])
def test_jwst_selection_selects_f115w_dropouts(z, selected):
    """Noiseless M_UV = -20 sources (S/N ~ 20 in F277W): z ~ 10 in, z <= 8 and >= 12.5 out."""
    cfg = load_config(CONFIGS / "jwst_nircam_z10.yaml")
    sel = compile_selection(cfg.selection)
    assert bool(sel(_noiseless_rows(cfg, z))[0]) is selected


def test_jwst_grid_brackets_the_dropout_window():
    """Both edges of the window lie inside the z grid: its ends are not selected."""
    cfg = load_config(CONFIGS / "jwst_nircam_z10.yaml")
    sel = compile_selection(cfg.selection)
    z = cfg.grid.z_values
    picked = [bool(sel(_noiseless_rows(cfg, zi))[0]) for zi in z]
    assert not picked[0] and not picked[-1] and any(picked)
