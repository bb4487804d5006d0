"""Configuration: defaults, validation errors, round trips, hashing, .sex files, GLACiAR files."""
import copy
import json
import re
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml

from glaciar.config import (ConfigError, check_files, config_from_dict, config_hash,
                            config_to_dict, load_config, missing_files, template_yaml)
from glaciar.engine.selection import DEFAULT_JDROPOUT

REPO = Path(__file__).resolve().parents[1]

MOFFAT = {"profile": "moffat", "fwhm_arcsec": 0.18}
BASE = {
    "survey": {
        "fields": ["f1", "f2"],
        "image_dir": "images",
        "science": "{field}_{band}_drz.fits",
        "noise": "{field}_{band}_wht.fits",
        "detection_band": "f160w",
        "bands": {
            "f160w": {"filter": "wfc3_ir_f160w", "zeropoint": 25.946, "psf": MOFFAT},
            "f098m": {"filter": "wfc3_ir_f098m", "zeropoint": 25.667, "psf": MOFFAT},
            "f125w": {"filter": "wfc3_ir_f125w", "zeropoint": 26.230, "psf": MOFFAT},
            "f606w": {"filter": "wfc3_uvis_f606w", "zeropoint": 26.069, "psf": MOFFAT},
        },
    },
}


def base():
    return copy.deepcopy(BASE)


def load(data, tmp_path, name="config.yaml"):
    return config_from_dict(data, tmp_path, name)


def error_of(data, tmp_path):
    with pytest.raises(ConfigError) as info:
        load(data, tmp_path)
    return str(info.value)


# ---------------------------------------------------------------------------
# Defaults and the template
# ---------------------------------------------------------------------------
def test_paper_defaults(tmp_path):
    cfg = load(base(), tmp_path)
    # Carrasco et al. 2018, appendix: 100 galaxies, 100 iterations, m 24.1-27.9 in 20 bins,
    # R_e 1.075 kpc, beta -2.2 +- 0.4, n = 1 and 4 at 50 % each, ibins = ebins = 1, S/N 8.
    assert (cfg.simulation.n_galaxies, cfg.simulation.n_iterations) == (100, 100)
    np.testing.assert_allclose(cfg.grid.mag_values, 24.1 + 0.2 * np.arange(20), atol=1e-9)
    np.testing.assert_allclose(cfg.grid.z_values, 9.0 + 0.2 * np.arange(15), atol=1e-9)
    src = cfg.source
    assert src.r_eff_kpc_z6 == 1.075 and (src.beta_mean, src.beta_sd) == (-2.2, 0.4)
    assert src.sersic_indices == (1.0, 4.0) and src.sersic_fractions == (0.5, 0.5)
    assert src.ellipticity_bins == 1 and src.position_angle_bins == 1
    assert src.round_de_vaucouleurs is False
    assert cfg.classification.min_sn == 8.0 and cfg.classification.search_box == 3
    assert cfg.classification.max_overlap_fraction == 0.25
    assert cfg.detection.detect_thresh == 0.7 and cfg.detection.detect_minarea == 9
    # With the BoRG bands present the default selection is the paper's J-dropout.
    assert cfg.selection == DEFAULT_JDROPOUT
    assert cfg.survey.image_dir == (tmp_path / "images").resolve()
    assert cfg.survey.noise_type == "weight" and cfg.warnings == ()


def test_default_selection_needs_its_bands(tmp_path):
    d = base()
    del d["survey"]["bands"]["f606w"]
    cfg = load(d, tmp_path)
    assert cfg.selection == ()
    assert any("J-dropout" in w for w in cfg.warnings)
    d["selection"] = ["sn_f160w > 5"]
    assert load(d, tmp_path).selection == ("sn_f160w > 5",)


def test_template_is_valid_and_documents_defaults(tmp_path):
    text = template_yaml()
    assert text.lstrip().startswith("#")
    data = yaml.safe_load(text)
    cfg = load(data, tmp_path, "template.yaml")
    defaults = load(base(), tmp_path)
    # The template writes the defaults out explicitly.
    assert cfg.source == defaults.source
    assert cfg.detection == defaults.detection
    assert cfg.classification == defaults.classification
    assert cfg.simulation == defaults.simulation and cfg.grid == defaults.grid
    assert cfg.selection == DEFAULT_JDROPOUT


# The shipped configs/ examples are tested in tests/test_configs.py.


# ---------------------------------------------------------------------------
# Grid
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("spec, expected", [
    ({"min": 24.1, "max": 27.9, "step": 0.2}, 24.1 + 0.2 * np.arange(20)),
    ({"min": 24.0, "max": 25.0001, "step": 0.2}, 24.0 + 0.2 * np.arange(6)),   # within step/1000
    ({"min": 24.0, "max": 24.95, "step": 0.2}, 24.0 + 0.2 * np.arange(5)),     # 25.0 excluded
    ({"min": 9.0, "max": 11.9, "n_bins": 15}, np.linspace(9.0, 11.9, 15)),
    ({"values": [7.0, 8.5, 10.0]}, [7.0, 8.5, 10.0]),
    ({"min": 26.0, "max": 26.0, "step": 0.5}, [26.0]),
])
def test_grid_axes(tmp_path, spec, expected):
    d = base()
    d["grid"] = {"mag": spec}
    got = load(d, tmp_path).grid.mag_values
    np.testing.assert_allclose(got, expected, atol=1e-9)
    assert len(got) == len(expected)


def test_grid_values_are_clean_decimals(tmp_path):
    d = base()
    d["grid"] = {"z": {"min": 9.0, "max": 11.0, "step": 0.2}}
    assert load(d, tmp_path).grid.z_values[3] == 9.6      # not 9.600000000000001


# ---------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------
def test_error_names_file_and_key(tmp_path):
    d = base()
    d["survey"]["bands"]["f160w"]["zeropoint"] = "abc"
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == f"{path}: survey.bands.f160w.zeropoint: expected a number, got 'abc'"


@pytest.mark.parametrize("mutate, pattern", [
    (lambda d: d["survey"]["bands"]["f160w"].update(zeropiont=1),
     r"survey\.bands\.f160w\.zeropiont: unknown key 'zeropiont'; did you mean 'zeropoint'\?"),
    (lambda d: d.update(simulaton={}), r"simulaton: unknown key.*did you mean 'simulation'"),
    (lambda d: d.update(source={"beta_means": -2}), r"source\.beta_means.*did you mean 'beta_mean'"),
    (lambda d: d.update(n_galaxies=5), r"n_galaxies: unknown key.*simulation\.n_galaxies"),
    (lambda d: d.update(simulation={"n_galaxies": 0}), r"simulation\.n_galaxies: must be >= 1, got 0"),
    (lambda d: d.update(simulation={"n_iterations": 2.5}), r"simulation\.n_iterations: expected an integer"),
    (lambda d: d.update(simulation={"seed": True}), r"simulation\.seed: expected an integer, got True"),
    (lambda d: d.update(source={"sersic_fractions": [0.5, 0.4]}), r"sersic_fractions: must sum to 1"),
    (lambda d: d.update(source={"sersic_fractions": [1.0]}), r"sersic_fractions: has 1 value.*has 2"),
    (lambda d: d.update(source={"beta_sd": -0.1}), r"source\.beta_sd: must be >= 0"),
    (lambda d: d.update(source={"igm": "inoue"}), r"source\.igm: expected one of.*did you mean 'inoue14'"),
    (lambda d: d.update(source={"cosmology": "Planck19"}), r"source\.cosmology: unknown astropy"),
    (lambda d: d.update(detection={"DETECT_THRESH": 0}), r"detection\.DETECT_THRESH: must be > 0"),
    (lambda d: d.update(detection={"detect_tresh": 1}), r"did you mean 'DETECT_THRESH'"),
    (lambda d: d.update(detection={"PHOT_AUTOPARAMS": [2.5]}), r"PHOT_AUTOPARAMS: expected at least 2"),
    (lambda d: d.update(classification={"search_box": 4}), r"search_box: must be odd"),
    (lambda d: d.update(classification={"sn_aperture_index": 2}), r"sn_aperture_index.*2 aperture"),
    (lambda d: d.update(classification={"max_overlap_fraction": 1.5}), r"must be <= 1"),
    (lambda d: d.update(grid={"z": {"min": 11, "max": 9, "step": 0.2}}), r"grid\.z: min \(11\) > max \(9\)"),
    (lambda d: d.update(grid={"z": {"min": 9, "max": 11}}), r"grid\.z: give exactly one of step"),
    (lambda d: d.update(grid={"z": {"min": -1, "max": 1, "step": 0.5}}), r"grid\.z\.min: must be >= 0"),
    (lambda d: d.update(grid={"mag": {"values": [25, 24]}}), r"strictly increasing"),
    (lambda d: d.update(grid={"mag": {"min": 24, "max": 28, "step": 0}}), r"grid\.mag\.step: must be > 0"),
    (lambda d: d["survey"].pop("science"), r"survey\.science: missing required key"),
    (lambda d: d["survey"].pop("fields"), r"survey\.fields: missing required key"),
    (lambda d: d["survey"]["bands"]["f125w"].pop("filter"), r"bands\.f125w\.filter: missing required"),
    (lambda d: d["survey"]["bands"]["f125w"].pop("psf"), r"bands\.f125w\.psf: missing required"),
    (lambda d: d["survey"]["bands"]["f125w"].update(psf={"profile": "airy", "fwhm_arcsec": 0.1}),
     r"bands\.f125w\.psf\.fwhm_arcsec: unknown key"),
    (lambda d: d["survey"].update(detection_band="f150w"),
     r"survey\.detection_band: 'f150w' is not one of the bands.*did you mean 'f160w'"),
    (lambda d: d["survey"].update(noise_type="variance"), r"survey\.noise_type: expected one of weight, rms"),
    (lambda d: d["survey"].update(fields=[1, 2]), r"survey\.fields\[0\]: expected a field name.*quote"),
    (lambda d: d["survey"].update(science="{field}_{filt}.fits"), r"only the placeholders"),
    (lambda d: d["survey"].update(science="{field}.fits"), r"has no \{band\} but there are 4 bands"),
    (lambda d: d["survey"]["bands"]["f160w"].update(psf={"profile": "moffat"}),
     r"bands\.f160w\.psf\.fwhm_arcsec: missing required key"),
    (lambda d: d["survey"]["bands"]["f160w"].update(psf={"profile": "moffat", "fwhm_arcsec": 0.2,
                                                         "obscuration": 0.3}),
     r"psf\.obscuration: unknown key"),
    (lambda d: d["survey"]["bands"]["f160w"].update(filter="wfc3_ir_f999w"), r"bands\.f160w\.filter: "),
    (lambda d: d.update(selection=["sn_f160w >= 8", 1.5]), r"selection\[1\]: expected an expression string"),
    (lambda d: d.update(selection=["sn_f150w >= 8"]), r"selection\[0\].*unknown column 'sn_f150w'.*'sn_f160w'"),
    (lambda d: d.update(selection=["open('x')"]), r"selection\[0\].*call of 'open'"),
    (lambda d: d.update(output={"regions": "maybe"}), r"output\.regions: expected true/false"),
])
def test_validation_errors(tmp_path, mutate, pattern):
    d = base()
    mutate(d)
    msg = error_of(d, tmp_path)
    assert msg.startswith("config.yaml: ")
    assert re.search(pattern, msg), msg


def test_yaml_level_errors(tmp_path):
    p = tmp_path / "dup.yaml"
    p.write_text("survey:\n  fields: [a]\nsurvey:\n  fields: [b]\n")
    with pytest.raises(ConfigError, match=r"line 3.*duplicate key 'survey'"):
        load_config(p)
    p.write_text("survey: [a, b\n")
    with pytest.raises(ConfigError, match=r"invalid YAML"):
        load_config(p)
    p.write_text("")
    with pytest.raises(ConfigError, match="empty"):
        load_config(p)
    with pytest.raises(FileNotFoundError):
        load_config(tmp_path / "nope.yaml")


def test_numeric_strings_and_yaml11_words(tmp_path):
    d = base()
    d["detection"] = {"DEBLEND_MINCONT": "1e-3", "CLEAN": "N", "filter": "yes"}  # PyYAML: 1e-3 is a str
    d["source"] = {"round_de_vaucouleurs": "Yes"}
    cfg = load(d, tmp_path)
    assert cfg.detection.deblend_mincont == 1e-3
    assert cfg.detection.clean is False and cfg.detection.filter is True
    assert cfg.source.round_de_vaucouleurs is True


# ---------------------------------------------------------------------------
# Round trip and hash
# ---------------------------------------------------------------------------
def test_round_trip(tmp_path):
    d = base()
    d["survey"]["bands"]["f160w"]["psf"] = "psf/psf_f160w.fits"
    d["survey"]["bands"]["f125w"]["psf"] = {"profile": "moffat", "fwhm_arcsec": 0.17}
    d["survey"]["bands"]["f098m"]["filter"] = "curves/f098m.tab"
    d["survey"]["bands"]["f098m"]["gain"] = 2000
    d["grid"] = {"z": {"min": 9, "max": 10, "n_bins": 3}, "mag": {"values": [25, 26]}}
    d["selection"] = ["sn_f160w >= 5", "(source_flags & 1) == 0"]
    cfg = load(d, tmp_path)
    out = config_to_dict(cfg)
    json.dumps(out)                                   # JSON-serialisable
    again = config_from_dict(yaml.safe_load(yaml.safe_dump(out, sort_keys=False)), tmp_path / "elsewhere")
    assert again == cfg
    assert config_to_dict(again) == out
    assert cfg.survey.band("f160w").psf == str((tmp_path / "psf/psf_f160w.fits").resolve())
    assert cfg.survey.band("f098m").filter == str((tmp_path / "curves/f098m.tab").resolve())
    assert cfg.survey.band("f125w").psf == {"profile": "moffat", "fwhm_arcsec": 0.17, "beta": 2.5}
    rel = config_to_dict(cfg, relative_to=tmp_path)
    assert rel["survey"]["image_dir"] == "images"
    assert config_from_dict(rel, tmp_path) == cfg


def test_hash(tmp_path):
    cfg = load(base(), tmp_path)
    h = config_hash(cfg)
    assert len(h) == 64 and h == config_hash(load(base(), tmp_path))
    # Output options do not change the science; seeds, thresholds and selections do.
    d = base()
    d["output"] = {"regions": True}
    assert config_hash(load(d, tmp_path)) == h
    for key, value in (("simulation", {"seed": 1}), ("detection", {"DETECT_THRESH": 0.8}),
                       ("selection", ["sn_f160w >= 8"]), ("source", {"igm": "sharp"})):
        d = base()
        d[key] = value
        assert config_hash(load(d, tmp_path)) != h, key
    # A project moved as a whole (relative paths unchanged) keeps its hash.
    (tmp_path / "moved").mkdir()
    assert config_hash(load(base(), tmp_path / "moved")) == h
    # Key order in the file does not matter.
    d = base()
    d["survey"] = dict(reversed(list(d["survey"].items())))
    assert config_hash(load(d, tmp_path)) == h


def test_store_hash_ignores_only_what_adds_tasks(tmp_path):
    from glaciar.config import store_hash

    h = store_hash(load(base(), tmp_path))
    # More fields, grid values or iterations only add tasks: same store identity.
    for key, value in (("grid", {"z": {"values": [9.0, 9.4]}, "mag": {"values": [25.0]}}),
                       ("simulation", {"n_iterations": 7})):
        d = base()
        d[key] = value
        cfg = load(d, tmp_path)
        assert store_hash(cfg) == h, key
        assert config_hash(cfg) != config_hash(load(base(), tmp_path)), key
    # Everything that changes a task's rows changes it.
    for key, value in (("simulation", {"seed": 1}), ("detection", {"DETECT_THRESH": 0.8}),
                       ("selection", ["sn_f160w >= 8"]), ("source", {"igm": "sharp"}),
                       ("grid", {"magnitude_type": "absolute"})):
        d = base()
        d[key] = value
        assert store_hash(load(d, tmp_path)) != h, key


# ---------------------------------------------------------------------------
# Files: fields file, check_files, SExtractor .sex files
# ---------------------------------------------------------------------------
def test_fields_file(tmp_path):
    (tmp_path / "fields.txt").write_text("# name  area\nborg_0440-5244  4.1\n\n  borg_0240-1857 x\n")
    d = base()
    del d["survey"]["fields"]
    d["survey"]["fields_file"] = "fields.txt"
    assert load(d, tmp_path).survey.fields == ("borg_0440-5244", "borg_0240-1857")
    d["survey"]["fields_file"] = "missing.txt"
    assert "survey.fields_file: file not found" in error_of(d, tmp_path)
    d["survey"]["fields"] = ["a"]
    assert "either fields or fields_file" in error_of(d, tmp_path)


def test_check_files(tmp_path):
    d = base()
    d["survey"]["bands"]["f160w"]["psf"] = "psf_f160w.fits"
    d["survey"]["bands"]["f098m"]["filter"] = "f098m.tab"
    d["detection"] = {"FILTER_NAME": "kernels/my.conv"}
    cfg = load(d, tmp_path)
    missing = missing_files(cfg)
    # 2 fields x 4 bands x (science + noise) + PSF + filter curve + .conv
    assert len(missing) == 19
    assert "survey.science (field 'f2', band 'f606w'): " \
           f"{(tmp_path / 'images' / 'f2_f606w_drz.fits').resolve()}" in missing
    assert any(m.startswith("survey.bands.f160w.psf: ") for m in missing)
    assert any(m.startswith("survey.bands.f098m.filter: ") for m in missing)
    assert any(m.startswith("detection.FILTER_NAME: ") for m in missing)
    with pytest.raises(FileNotFoundError, match="19 input file"):
        check_files(cfg)
    (tmp_path / "images").mkdir()
    for m in missing:
        p = Path(m.split(": ", 1)[1])
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("x")
    assert missing_files(cfg) == []
    check_files(cfg)


def test_sex_file_merge(tmp_path):
    sexdir = tmp_path / "sex"
    sexdir.mkdir()
    (sexdir / "my.conv").write_text("CONV NORM\n1 2 1\n2 4 2\n1 2 1\n")
    (sexdir / "default.sex").write_text(textwrap.dedent("""\
        # SExtractor config
        CATALOG_NAME     test.cat       # ignored
        DETECT_MINAREA   5
        DETECT_THRESH    1.5,25.0       # sigma first
        FILTER           Y
        FILTER_NAME      my.conv
        DEBLEND_NTHRESH  64
        CLEAN            N
        PHOT_APERTURES   2,4,6          # diameters
        PHOT_AUTOPARAMS  2.5, 3.5
        BACK_SIZE        128
        """))
    d = base()
    d["detection"] = {"sex_file": "sex/default.sex", "DEBLEND_NTHRESH": 16}
    det = load(d, tmp_path).detection
    assert det.sex_file == str((sexdir / "default.sex").resolve())
    assert det.detect_minarea == 5 and det.detect_thresh == 1.5      # from the .sex file
    assert det.deblend_nthresh == 16                                     # explicit key wins
    assert det.clean is False and det.phot_apertures == (2.0, 4.0, 6.0)
    assert det.phot_autoparams == (2.5, 3.5) and det.back_size == 128
    assert det.filter_name == str((sexdir / "my.conv").resolve())       # next to the .sex
    assert det.deblend_mincont == 0.005                                  # default kept
    (sexdir / "abs.sex").write_text("THRESH_TYPE ABSOLUTE\nDETECT_THRESH 0.01\n")
    d["detection"] = {"sex_file": "sex/abs.sex"}
    assert "THRESH_TYPE: only RELATIVE" in error_of(d, tmp_path)
    d["detection"] = {"sex_file": "sex/none.sex"}
    assert "detection.sex_file: file not found" in error_of(d, tmp_path)


# ---------------------------------------------------------------------------
# GLACiAR parameters.yaml
# ---------------------------------------------------------------------------
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


# ---------------------------------------------------------------------------
# SExtractor keys -> the engine's DetectionParams (one reader, one validator)
# ---------------------------------------------------------------------------
def test_sex_file_reader_and_detection_params(tmp_path):
    from glaciar.config import read_sex_file
    from glaciar.engine.detect import DetectionParams
    from glaciar.fieldprep import detection_params

    (tmp_path / "my.conv").write_text("CONV NORM\n0 1 0\n1 4 1\n0 1 0\n")
    sex = tmp_path / "det.sex"
    sex.write_text("# comment\nDETECT_THRESH   1.5   # sigma\nDETECT_MINAREA 5\n"
                   "PHOT_APERTURES 2,4,6\nFILTER_NAME my.conv\nCATALOG_NAME out.cat\nCLEAN N\n")
    raw = read_sex_file(sex)
    assert raw["DETECT_THRESH"] == "1.5" and raw["PHOT_APERTURES"] == ["2", "4", "6"]
    d = base()
    d["detection"] = {"sex_file": "det.sex", "DETECT_MINAREA": 12}
    p = detection_params(load(d, tmp_path))
    assert p.detect_thresh == 1.5 and p.detect_minarea == 12          # explicit key wins
    assert p.phot_apertures == (2.0, 4.0, 6.0) and p.clean is False
    np.testing.assert_array_equal(p.filter_kernel, [[0, 1, 0], [1, 4, 1], [0, 1, 0]])
    d["detection"] = {"FILTER": False}
    q = detection_params(load(d, tmp_path))
    assert q.filter_kernel is None and q.filter_halfwidth == 0
    d["detection"] = {"FILTER_NAME": "gauss_3.0_7x7"}
    assert detection_params(load(d, tmp_path)).filter_halfwidth == 3
    # The config's defaults are the engine's defaults (one place).
    assert detection_params(load(base(), tmp_path)) == DetectionParams()


@pytest.mark.parametrize("key,value,expected", [
    ("DETECT_THRESH", "abc", "expected a number"), ("DETECT_MINAREA", 2.5, "expected an integer"),
    ("CLEAN", "maybe", "expected true/false"), ("PHOT_APERTURES", [1, "x"], "expected a number"),
    ("DEBLEND_MINCONT", 2.0, "must be <= 1"), ("FILTER_NAME", "nofilter", "unknown built-in filter"),
    ("FILTER_TYPE", "gauss", "expected one of conv, matched")])
def test_detection_errors_name_the_key(tmp_path, key, value, expected):
    d = base()
    d["detection"] = {key: value}
    msg = error_of(d, tmp_path)
    assert msg.startswith(f"config.yaml: detection.{key}") and expected in msg, msg


def test_sex_file_values_are_checked_and_named(tmp_path):
    (tmp_path / "bad.sex").write_text("DETECT_MINAREA 2.5\n")
    d = base()
    d["detection"] = {"sex_file": "bad.sex"}
    msg = error_of(d, tmp_path)
    assert "detection.DETECT_MINAREA: expected an integer" in msg
    assert str((tmp_path / "bad.sex").resolve()) in msg        # where the value came from


def test_missing_filter_file_is_reported(tmp_path):
    d = base()
    d["detection"] = {"FILTER_NAME": "nope.conv"}
    assert any(m.startswith("detection.FILTER_NAME: ") and m.endswith("nope.conv")
               for m in missing_files(load(d, tmp_path)))



# ---------------------------------------------------------------------------
# One source of truth: the template, the documented schema and the engine defaults
# ---------------------------------------------------------------------------
def test_documented_schema_is_generated_from_the_models():
    from glaciar.config import schema_yaml

    committed = (REPO / "docs" / "config-schema.yaml").read_text()
    assert committed == schema_yaml(), (
        "docs/config-schema.yaml is stale; regenerate it with "
        "python -c \"import glaciar.config as c; print(c.schema_yaml(), end='')\" "
        "> docs/config-schema.yaml")


def test_template_and_schema_cover_every_key():
    from glaciar.config import schema_yaml
    from glaciar.config.models import SECTIONS
    from glaciar.config.survey_models import BandConfig

    template = yaml.safe_load(template_yaml())
    schema = yaml.safe_load(schema_yaml())
    for section, info in SECTIONS.items():
        assert section in template and section in schema
        model = info.annotation
        if not hasattr(model, "user_keys"):
            continue
        for key in model.user_keys():
            assert key in schema[section]["keys"], (section, key)
            if (section, key) != ("survey", "fields_file"):     # an alternative to fields
                assert key in template[section], (section, key)
    first_band = next(iter(template["survey"]["bands"].values()))
    assert set(first_band) == set(BandConfig.user_keys())


def test_config_defaults_are_the_engine_defaults(tmp_path):
    from glaciar.engine.classify import ClassificationParams
    from glaciar.galaxy.population import SourceModel

    cfg = load(base(), tmp_path)
    assert SourceModel(**cfg.source.model_dump()) == SourceModel()
    assert ClassificationParams(**cfg.classification.model_dump()) == ClassificationParams()


# ---------------------------------------------------------------------------
# Every SExtractor key honoured or refused (issue 9, point 2)
# ---------------------------------------------------------------------------
SEX_DEFAULTS = """\
CATALOG_NAME     test.cat
CATALOG_TYPE     ASCII_HEAD
PARAMETERS_NAME  default.param
DETECT_TYPE      CCD
DETECT_MINAREA   3
DETECT_THRESH    1.5
ANALYSIS_THRESH  1.5
FILTER           Y
FILTER_NAME      gauss_2.0_5x5.conv
DEBLEND_NTHRESH  32
DEBLEND_MINCONT  0.005
CLEAN            Y
CLEAN_PARAM      1.0
MASK_TYPE        CORRECT
WEIGHT_TYPE      NONE
WEIGHT_IMAGE     weight.fits
FLAG_IMAGE       flag.fits
FLAG_TYPE        OR
PHOT_APERTURES   5
PHOT_AUTOPARAMS  2.5, 3.5
PHOT_PETROPARAMS 2.0, 3.5
PHOT_AUTOAPERS   0.0,0.0
SATUR_LEVEL      50000.0
SATUR_KEY        SATURATE
MAG_ZEROPOINT    0.0
GAIN             0.0
GAIN_KEY         GAIN
PIXEL_SCALE      1.0
SEEING_FWHM      1.2
BACK_TYPE        AUTO
BACK_VALUE       0.0
BACK_SIZE        64
BACK_FILTERSIZE  3
BACKPHOTO_TYPE   GLOBAL
CHECKIMAGE_TYPE  NONE
MEMORY_OBJSTACK  3000
VERBOSE_TYPE     NORMAL
"""


def test_sextractor_default_file_is_accepted(tmp_path):
    (tmp_path / "default.sex").write_text(SEX_DEFAULTS)
    d = base()
    d["detection"] = {"sex_file": "default.sex"}
    cfg = load(d, tmp_path)
    det = cfg.detection
    assert (det.detect_thresh, det.detect_minarea, det.phot_apertures) == (1.5, 3, (5.0,))
    assert det.filter_name == "gauss_2.0_5x5" and det.weight_type is None
    assert any("WEIGHT_TYPE NONE" in w for w in cfg.warnings)


@pytest.mark.parametrize("line, needle", [
    ("BACK_TYPE MANUAL", "BACK_TYPE MANUAL: not supported"),
    ("GAIN 2.5", "GAIN 2.5: not supported"),
    ("INTERP_TYPE ALL", "INTERP_TYPE ALL: not supported"),
    ("DETECT_TYPE PHOTO", "DETECT_TYPE PHOTO"),
    ("FANCY_NEW_KEY 3", "FANCY_NEW_KEY: SExtractor key not supported"),
    ("WEIGHT_TYPE MAP_WEIGHT,MAP_RMS", "different types for detection and measurement"),
])
def test_sextractor_keys_that_would_change_the_answer_are_refused(tmp_path, line, needle):
    (tmp_path / "x.sex").write_text(SEX_DEFAULTS.replace("WEIGHT_TYPE      NONE\n", "") + line + "\n")
    d = base()
    d["detection"] = {"sex_file": "x.sex"}
    msg = error_of(d, tmp_path)
    assert msg.startswith("config.yaml: detection.sex_file: ") and needle in msg, msg
    assert str(tmp_path / "x.sex") in msg


def test_weight_type_from_sex_and_consistency(tmp_path):
    (tmp_path / "w.sex").write_text("WEIGHT_TYPE MAP_WEIGHT,MAP_WEIGHT\nWEIGHT_GAIN Y\n")
    d = base()
    d["detection"] = {"sex_file": "w.sex"}
    cfg = load(d, tmp_path)
    assert cfg.detection.weight_type == "map_weight" and cfg.detection.weight_gain is True
    d["survey"]["noise_type"] = "rms"
    assert "detection.WEIGHT_TYPE: MAP_WEIGHT needs survey.noise_type: weight" in error_of(d, tmp_path)
    d = base()
    d["detection"] = {"WEIGHT_GAIN": True}
    d["survey"]["bands"]["f160w"]["gain"] = 2000.0
    assert "detection.WEIGHT_GAIN: WEIGHT_GAIN Y" in error_of(d, tmp_path)
    d = base()
    del d["survey"]["noise"]
    d["detection"] = {"WEIGHT_TYPE": "MAP_WEIGHT"}
    assert "needs a noise map" in error_of(d, tmp_path)
