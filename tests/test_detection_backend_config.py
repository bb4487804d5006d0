"""The detection keys of the CLEAN / backend cross-checks (issue 9 point 6) in the typed config:
CLEAN_STYLE, THRESHOLD_RMS and BACKEND reach DetectionParams, enter the store identity, are
refused with the key's name when wrong, and are refused by name in a SExtractor .sex file
(they are glaciar's keys, not SExtractor's)."""
import copy

import pytest

from glaciar.config import ConfigError, config_from_dict, store_hash
from glaciar.engine.detect import BACKENDS, CLEAN_STYLES, THRESHOLD_RMS, DetectionParams
from glaciar.fieldprep import detection_params

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
