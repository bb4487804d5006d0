"""Configuration: defaults, validation errors, round trips, hashing, .sex files, GLACiAR files."""
import copy
import re

import numpy as np
import pytest
import yaml

from glaciar.config import ConfigError, config_from_dict, load_config, missing_files, store_hash
from glaciar.engine.detect import BACKENDS, CLEAN_STYLES, DetectionParams, THRESHOLD_RMS
from glaciar.engine.selection import DEFAULT_JDROPOUT
from glaciar.fieldprep import detection_params

from config_dicts import base, error_of, load


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


# The shipped configs/ examples are tested in tests/config/test_io_examples.py.


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


def test_missing_filter_file_is_reported(tmp_path):
    d = base()
    d["detection"] = {"FILTER_NAME": "nope.conv"}
    assert any(m.startswith("detection.FILTER_NAME: ") and m.endswith("nope.conv")
               for m in missing_files(load(d, tmp_path)))


def test_config_defaults_are_the_engine_defaults(tmp_path):
    from glaciar.engine.classify import ClassificationParams
    from glaciar.galaxy.population import SourceModel

    cfg = load(base(), tmp_path)
    assert SourceModel(**cfg.source.model_dump()) == SourceModel()
    assert ClassificationParams(**cfg.classification.model_dump()) == ClassificationParams()


# ------------------------------------------------------------------------------
# The detection keys of the CLEAN / backend cross-checks (issue 9 point 6) in the typed config:
# CLEAN_STYLE, THRESHOLD_RMS and BACKEND reach DetectionParams, enter the store identity, are
# refused with the key's name when wrong, and are refused by name in a SExtractor .sex file
# (they are glaciar's keys, not SExtractor's).
# ------------------------------------------------------------------------------
MOFFAT = {"profile": "moffat", "fwhm_arcsec": 0.18}
BASE = {"survey": {
    "fields": ["f1"], "image_dir": "images", "science": "{field}_{band}_drz.fits",
    "noise": "{field}_{band}_wht.fits", "detection_band": "f160w",
    "bands": {"f160w": {"filter": "wfc3_ir_f160w", "zeropoint": 25.946, "psf": MOFFAT},
              "f098m": {"filter": "wfc3_ir_f098m", "zeropoint": 25.667, "psf": MOFFAT},
              "f125w": {"filter": "wfc3_ir_f125w", "zeropoint": 26.230, "psf": MOFFAT},
              "f606w": {"filter": "wfc3_uvis_f606w", "zeropoint": 26.069, "psf": MOFFAT}}}}


def _cfg(tmp_path, detection=None):
    d = copy.deepcopy(BASE)
    if detection is not None:
        d["detection"] = detection
    return config_from_dict(d, tmp_path, "config.yaml")


def test_defaults_are_the_engines(tmp_path):
    p = detection_params(_cfg(tmp_path))
    assert (p.clean_style, p.threshold_rms, p.backend) == (CLEAN_STYLES[0], THRESHOLD_RMS[0], BACKENDS[0])
    assert p == DetectionParams()


@pytest.mark.parametrize("key,attr,values", [("CLEAN_STYLE", "clean_style", CLEAN_STYLES),
                                             ("THRESHOLD_RMS", "threshold_rms", THRESHOLD_RMS),
                                             ("BACKEND", "backend", BACKENDS)])
def test_each_value_reaches_the_engine_and_the_store_identity(tmp_path, key, attr, values):
    hashes = set()
    for v in values:
        cfg = _cfg(tmp_path, {key: v.upper()})          # SExtractor-style upper case accepted
        assert getattr(detection_params(cfg), attr) == v
        hashes.add(store_hash(cfg))
    assert len(hashes) == len(values)                  # another value: another store


@pytest.mark.parametrize("key", ["CLEAN_STYLE", "THRESHOLD_RMS", "BACKEND"])
def test_bad_value_names_the_key(tmp_path, key):
    with pytest.raises(ConfigError) as info:
        _cfg(tmp_path, {key: "swarp"})
    msg = str(info.value)
    assert msg.startswith(f"config.yaml: detection.{key}") and "expected one of" in msg, msg
    assert "\n" not in msg.strip()


@pytest.mark.parametrize("key", ["CLEAN_STYLE", "THRESHOLD_RMS", "BACKEND"])
def test_glaciar_keys_in_a_sex_file_are_refused_by_name(tmp_path, key):
    (tmp_path / "det.sex").write_text(f"DETECT_THRESH 1.5\nCLEAN Y\n{key} sep\n")
    with pytest.raises(ConfigError) as info:
        _cfg(tmp_path, {"sex_file": "det.sex"})
    msg = str(info.value)
    assert f"{key}: glaciar's own key" in msg and f"detection.{key}" in msg, msg


def test_sex_clean_keys_map_onto_clean_and_clean_param(tmp_path):
    (tmp_path / "det.sex").write_text("CLEAN N\nCLEAN_PARAM 2.5\n")
    p = detection_params(_cfg(tmp_path, {"sex_file": "det.sex", "CLEAN_STYLE": "sextractor"}))
    assert (p.clean, p.clean_param, p.clean_style) == (False, 2.5, "sextractor")
