"""Reading, writing and identifying configurations (glaciar.config.io).

YAML-level errors, numeric strings and YAML 1.1 words, round trips, the hashes, fields files
and the check of the files a configuration names.
"""
from __future__ import annotations

import copy
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from glaciar.cli import main
from glaciar.config import (ConfigError, check_files, config_from_dict, config_hash, config_to_dict,
                            load_config, missing_files)
from glaciar.engine.selection import compile_selection

from config_dicts import MOFFAT, base, error_of, load


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


# ------------------------------------------------------------------------------
# Hostile configuration inputs: each is refused fast, in one line naming the file and key.
#
# Part of the hostile-input suite of issue 10 (the run-directory and CLI-value
# cases are in tests/test_rundir.py and tests/test_cli.py). Every case must fail with a ConfigError (or
# exit status 2 from the CLI) whose message names where the problem is, within
# a second, without a traceback and without writing anything.
# ------------------------------------------------------------------------------
HOSTILE_BASE = {"survey": {"fields": ["f1"], "science": "{field}_{band}.fits", "detection_band": "f160w",
                   "bands": {"f160w": {"filter": "wfc3_ir_f160w", "zeropoint": 25.9,
                                       "psf": MOFFAT},
                             "f125w": {"filter": "wfc3_ir_f125w", "zeropoint": 26.2,
                                       "psf": MOFFAT}}},
        "selection": ["sn_f160w > 5"]}


def hostile_base():
    return copy.deepcopy(HOSTILE_BASE)


def refused(data, tmp_path) -> str:
    t0 = time.perf_counter()
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, tmp_path, "c.yaml")
    assert time.perf_counter() - t0 < 5.0
    msg = str(info.value)
    assert msg.startswith("c.yaml: ") and "\n" not in msg and len(msg) < 400, msg
    return msg


def refused_file(path) -> str:
    t0 = time.perf_counter()
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert time.perf_counter() - t0 < 5.0
    msg = str(info.value)
    assert msg.startswith(str(path)) and "\n" not in msg and len(msg) < 400, msg
    return msg


# --- the YAML itself -------------------------------------------------------
def test_alias_bomb_is_refused_before_expansion(tmp_path):
    lines = ['a: &a ["x","x","x","x","x","x","x","x","x"]']
    for i in range(1, 12):      # 9**12 leaves if expanded
        prev, cur = chr(ord("a") + i - 1), chr(ord("a") + i)
        lines.append(f"{cur}: &{cur} [" + ",".join([f"*{prev}"] * 9) + "]")
    p = tmp_path / "bomb.yaml"
    p.write_text("\n".join(lines) + "\n")
    assert "alias" in refused_file(p)


def test_deep_nesting_is_refused(tmp_path):
    p = tmp_path / "deep.yaml"
    p.write_text("survey: " + "[" * 5000 + "]" * 5000 + "\n")
    assert "nested" in refused_file(p)


def test_non_utf8_config_names_the_file(tmp_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes("survey:\n  fields: [caf\xe9]\n".encode("latin-1"))
    assert "not UTF-8" in refused_file(p)


def test_oversized_config_is_refused(tmp_path):
    p = tmp_path / "big.yaml"
    p.write_text("# " + "x" * 2_000_000 + "\n")
    assert "bytes" in refused_file(p)


def test_top_level_not_a_mapping(tmp_path):
    assert "expected a mapping" in refused([1, 2, 3], tmp_path)


def test_non_string_keys(tmp_path):
    d = hostile_base()
    d[1] = "x"
    assert "unknown key 1" in refused(d, tmp_path)


# --- values ----------------------------------------------------------------
@pytest.mark.parametrize("mutate, where, what", [
    (lambda d: d.update(simulation={"n_iterations": 2e8}), "simulation.n_iterations",
     "tasks, more than"),
    (lambda d: d.update(simulation={"seed": -1}), "simulation.seed", ">= 0"),
    (lambda d: d.update(simulation={"seed": 2 ** 64}), "simulation.seed", "< 9223372036854775808"),
    (lambda d: d.update(simulation={"n_galaxies": "many"}), "simulation.n_galaxies",
     "expected an integer"),
    (lambda d: d.update(source={"ellipticity_bins": 21}), "source.ellipticity_bins", "<= 20"),
    (lambda d: d.update(grid={"z": {"min": 0, "max": 10, "step": 1e-6}}), "grid.z", "step too small"),
    (lambda d: d.update(grid={"mag": {"min": 20, "max": 30, "n_bins": 10 ** 7}}), "grid.mag.n_bins",
     "<= 10000"),
    (lambda d: d["survey"]["bands"]["f160w"].update(zeropoint=float("nan")),
     "survey.bands.f160w.zeropoint", "finite"),
    (lambda d: d["survey"]["bands"]["f160w"].update(zeropoint=float("inf")),
     "survey.bands.f160w.zeropoint", "finite"),
    (lambda d: d["survey"]["bands"]["f160w"].update(zeropoint=[1.0] * 100_000),
     "survey.bands.f160w.zeropoint", "expected a number"),
    (lambda d: d["survey"]["bands"]["f160w"].update(psf=["a.fits"]), "survey.bands.f160w.psf",
     "expected a FITS path or a mapping"),
    (lambda d: d["survey"]["bands"].update({"f 1": {}}), "survey.bands.f 1", "band names"),
    (lambda d: d["survey"].update(science="{0}.fits"), "survey.science", "placeholders"),
    (lambda d: d["survey"].update(fields=["a"] * 3), "survey.fields", "duplicate"),
    (lambda d: d.update(selection="x" * 10_000), "selection[0]", "at most 1000 characters"),
    (lambda d: d.update(selection=["(" * 300 + "sn_f160w" + ")" * 300 + " > 1"]), "selection[0]",
     "nested"),
    (lambda d: d.update(selection=["-" * 500 + "sn_f160w > 1"]), "selection[0]", "nested"),
    (lambda d: d.update(selection=["sn_f160w > 1"] * 101), "selection", "at most 100"),
    (lambda d: d.update(selection=["(source_flags & 18446744073709551616) == 0"]), "selection[0]",
     "outside the 64-bit range"),
    (lambda d: d.update(selection=["__import__('os')"]), "selection[0]", ""),
    # issue 21: beyond float range, refused in one line (was an OverflowError traceback)
    (lambda d: d.update(selection=["sn_f160w > " + "9" * 800]), "selection[0]",
     "(800 characters) is outside the 64-bit range"),
    (lambda d: d.update(selection=["sn_f160w < 1e400"]), "selection[0]",
     "1e400 is beyond the float range"),
    (lambda d: d["survey"].update(noise_type=True), "survey.noise_type",
     "YAML reads unquoted on/yes/true as true: quote the word"),
])
def test_hostile_values(tmp_path, mutate, where, what):
    d = hostile_base()
    mutate(d)
    msg = refused(d, tmp_path)
    assert msg.startswith(f"c.yaml: {where}: ") and what in msg, msg


def test_non_utf8_fields_file(tmp_path):
    (tmp_path / "fields.txt").write_bytes(b"caf\xe9\n")
    d = hostile_base()
    del d["survey"]["fields"]
    d["survey"]["fields_file"] = "fields.txt"
    assert "survey.fields_file" in refused(d, tmp_path) 


def test_integer_arithmetic_does_not_wrap():
    # numpy int64 arithmetic would make 2 ** 64 == 0 and this False.
    sel = compile_selection(["2 ** 64 > 0", "a * 4611686018427387904 > 0"])
    assert sel({"a": np.array([3, 1])}).tolist() == [True, True]


def test_cli_refuses_a_bomb_in_one_line_and_writes_nothing(tmp_path, capsys):
    lines = ['a: &a ["x","x","x","x","x","x","x","x","x"]']
    for i in range(1, 12):
        prev, cur = chr(ord("a") + i - 1), chr(ord("a") + i)
        lines.append(f"{cur}: &{cur} [" + ",".join([f"*{prev}"] * 9) + "]")
    p = tmp_path / "bomb.yaml"
    p.write_text("\n".join(lines) + "\n")
    out = tmp_path / "run"
    assert main(["simulate", str(p), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "alias" in err and "Traceback" not in err
    assert not out.exists()


# ------------------------------------------------------------------------------
# Hostile configuration inputs at the command line (issue 21, bullet 9, and more).
#
# Each case runs ``glaciar simulate`` in this process on a copy of the small demo
# survey's configuration with one bad input, and checks: exit status 2, exactly
# one line on stderr (astropy's warnings from worker processes included: the
# file descriptor is captured), the expected words in it, and nothing written:
# no run directory, and the survey's and the test directory's files unchanged.
#
# The second half checks what is now accepted: YAML 1.1 words of the
# enumerations, and GLACiAR's own ``SExtractor_files/parameters.sex`` with its
# bare ``GAIN`` line.
# ------------------------------------------------------------------------------
NOT_FITS_LINES = "\n".join(str(i) for i in range(2000)) + "\n"
FAKE_FITS_HEADER = "SIMPLE  = T\nBITPIX = -32\nNAXIS = 2\nEND\n"


def _snapshot(*dirs) -> dict:
    out = {}
    for d in dirs:
        for root, _, files in os.walk(d):
            for f in files:
                st = os.stat(os.path.join(root, f))
                out[os.path.join(root, f)] = (st.st_size, st.st_mtime_ns)
    return out


def _base(small_survey) -> dict:
    """The small survey's configuration with absolute paths (so it can live elsewhere)."""
    d = yaml.safe_load(small_survey.read_text())
    d["survey"]["image_dir"] = str(small_survey.parent / d["survey"]["image_dir"])
    for b in d["survey"]["bands"].values():
        b["psf"] = str(small_survey.parent / b["psf"])
    return d


def _text_file(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def _spoiled_images(d, tmp_path, name, how):
    """Point the config at a copy of its images in which ``name`` is spoiled by ``how``."""
    import shutil

    src = d["survey"]["image_dir"]
    dst = tmp_path / "images"
    shutil.copytree(src, dst)
    data = (dst / name).read_bytes()
    (dst / name).write_bytes(how(data))
    d["survey"]["image_dir"] = str(dst)


def _sex(tmp_path, lines):
    return {"sex_file": _text_file(tmp_path, "bad.sex", "DETECT_THRESH 0.7\n" + lines + "\n")}


# (id, how the config is spoiled (dict, tmp_path) -> YAML text or None, words in the error)
CASES = [
    ("selection-800-digit-integer",
     lambda d, t: d.update(selection=["sn_f160w > " + "9" * 800]),
     ["selection[0]", "800 characters", "64-bit"]),
    ("selection-negative-800-digit-integer",
     lambda d, t: d.update(selection=["sn_f160w > -" + "9" * 800]), ["selection[0]", "64-bit"]),
    ("selection-1e400", lambda d, t: d.update(selection=["sn_f160w > 1e400"]),
     ["selection[0]", "1e400", "float range"]),
    ("selection-huge-flag-mask",
     lambda d, t: d.update(selection=["(source_flags & " + "7" * 60 + ") == 0"]),
     ["selection[0]", "64-bit"]),
    ("psf-text-file-named-fits",
     lambda d, t: d["survey"]["bands"]["f160w"].update(psf=_text_file(t, "psf.fits",
                                                                      NOT_FITS_LINES)),
     ["survey.bands.f160w.psf", "psf.fits"]),
    ("psf-fake-fits-header",
     lambda d, t: d["survey"]["bands"]["f125w"].update(psf=_text_file(t, "psf2.fits",
                                                                      FAKE_FITS_HEADER)),
     ["survey.bands.f125w.psf", "corrupt", "astropy warned"]),
    ("psf-empty-file",
     lambda d, t: d["survey"]["bands"]["f160w"].update(psf=_text_file(t, "empty.fits", "")),
     ["survey.bands.f160w.psf", "empty.fits"]),
    ("noise-type-boolean", lambda d, t: d["survey"].update(noise_type=False),
     ["survey.noise_type", "quote the word"]),
    ("science-boolean", lambda d, t: d["survey"].update(science=False),
     ["survey.science", "quote the word"]),
    ("detection-band-boolean", lambda d, t: d["survey"].update(detection_band=True),
     ["survey.detection_band", "quote the word"]),
    ("igm-boolean", lambda d, t: d.setdefault("source", {}).update(igm=False),
     ["source.igm", "quote the word"]),
    ("filter-boolean", lambda d, t: d["survey"]["bands"]["f160w"].update(filter=False),
     ["survey.bands.f160w.filter", "quote the word"]),
    ("cosmology-boolean", lambda d, t: d.setdefault("source", {}).update(cosmology=False),
     ["source.cosmology", "quote the word"]),
    ("filter-name-boolean", lambda d, t: d["detection"].update(FILTER_NAME=False),
     ["detection.FILTER_NAME", "quote the word"]),
    ("sex-file-boolean", lambda d, t: d["detection"].update(sex_file=True),
     ["detection.sex_file", "quote the word"]),
    ("sex-gain-with-a-value", lambda d, t: d.update(detection=_sex(t, "GAIN 3.5")),
     ["bad.sex", "GAIN 3.5"]),
    ("sex-weight-gain-differs", lambda d, t: d.update(detection=_sex(t, "WEIGHT_GAIN Y,N")),
     ["bad.sex", "WEIGHT_GAIN"]),
    ("sex-absolute-threshold", lambda d, t: d.update(detection=_sex(t, "THRESH_TYPE ABSOLUTE")),
     ["bad.sex", "THRESH_TYPE"]),
    ("science-image-truncated",
     lambda d, t: _spoiled_images(d, t, "demo01_f160w_drz.fits", lambda b: b[:2880]),
     ["survey.science (field 'demo01', band 'f160w')", "truncated"]),
    ("noise-map-truncated",
     lambda d, t: _spoiled_images(d, t, "demo01_f125w_wht.fits", lambda b: b[:2 * 2880]),
     ["survey.noise (field 'demo01', band 'f125w')", "truncated"]),
    ("science-image-is-text",
     lambda d, t: _spoiled_images(d, t, "demo01_f098m_drz.fits",
                                  lambda b: FAKE_FITS_HEADER.encode()),
     ["survey.science (field 'demo01', band 'f098m')"]),
    # Absurd numbers: before, tracebacks (OverflowError), a run, or a task file name
    # too long to write; now refused at the key by a plausibility bound.
    ("pixel-scale-1e300", lambda d, t: d["survey"].update(pixel_scale_arcsec=1e300),
     ["survey.pixel_scale_arcsec", "< 10"]),
    ("redshift-1e300", lambda d, t: d["grid"].update(z={"values": [1e300]}),
     ["grid.z.values[0]", "<= 50"]),
    ("magnitude-1e300", lambda d, t: d["grid"].update(mag={"values": [1e300]}),
     ["grid.mag.values[0]", "<= 100"]),
    ("cell-magnitude-1e300", lambda d, t: d["grid"].update(cells=[{"z": 8.0, "mag": -1e300}]),
     ["grid.cells[0].mag", ">= -100"]),
    ("box-redshift-1e300",
     lambda d, t: d["grid"].update(box={"z": [8.0, 1e300], "mag": [24, 27], "n_points": 4}),
     ["grid.box.z[1]", "<= 50"]),
    ("zeropoint-1e300", lambda d, t: d["survey"]["bands"]["f160w"].update(zeropoint=1e300),
     ["survey.bands.f160w.zeropoint", "<= 100"]),
    ("r-eff-1e300", lambda d, t: d["source"].update(r_eff_kpc_z6=1e300),
     ["source.r_eff_kpc_z6", "<= 100"]),
    ("aperture-1e300", lambda d, t: d["detection"].update(PHOT_APERTURES=[4.0, 1e300]),
     ["detection.PHOT_APERTURES[1]", "<= 10000"]),
    ("detect-thresh-1e300", lambda d, t: d["detection"].update(DETECT_THRESH=1e300),
     ["detection.DETECT_THRESH", "<= 10000"]),
    ("psf-fwhm-1e-300",
     lambda d, t: d["survey"]["bands"]["f160w"].update(psf={"profile": "moffat",
                                                            "fwhm_arcsec": 1e-300}),
     ["survey.bands.f160w.psf.fwhm_arcsec", ">= 0.001"]),
    ("noise-correlated-yes-is-not-a-choice",
     lambda d, t: d.update(noise={"correlated": "maybe"}), ["noise.correlated", "maybe"]),
]


# Damaged images are met first by the set-up that measures the fields while the inputs
# are checked in a worker process (two or more workers): astropy warned there before.
PARALLEL_SETUP = {"science-image-truncated", "noise-map-truncated", "psf-fake-fits-header"}


@pytest.mark.parametrize("spoil, words, workers",
                         [(*c[1:], "2" if c[0] in PARALLEL_SETUP else "1") for c in CASES],
                         ids=[c[0] for c in CASES])
def test_hostile_config_is_one_line_exit_2_and_writes_nothing(small_survey, tmp_path, capfd,
                                                              spoil, words, workers):
    d = _base(small_survey)
    spoil(d, tmp_path)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))
    before = _snapshot(small_survey.parent, tmp_path)
    out = tmp_path / "run"
    capfd.readouterr()
    code = main(["simulate", str(cfg), "--out", str(out), "--workers", workers, "--quiet"])
    err = capfd.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("glaciar simulate: error:"), err
    assert "Traceback" not in err and all(w in err for w in words), err
    assert not out.exists()
    assert _snapshot(small_survey.parent, tmp_path) == before


@pytest.mark.parametrize("spoil, extra, words", [
    (lambda d, t: d.update(selection=["sn_f160w > " + "9" * 800]), [], ["64-bit"]),
    (lambda d, t: d["survey"]["bands"]["f160w"].update(psf=_text_file(t, "p.fits",
                                                                      FAKE_FITS_HEADER)),
     [], ["survey.bands.f160w.psf", "astropy warned"]),
    (lambda d, t: _spoiled_images(d, t, "demo01_f160w_drz.fits", lambda b: b[:2880]), [],
     ["truncated"]),
    (lambda d, t: None, ["--adaptive", "--budget", "40"], ["--budget 40", "48"]),
], ids=["selection-overflow", "psf-fake-header", "truncated-image", "budget-below-corners"])
def test_hostile_input_leaves_an_existing_run_as_it_was(small_survey, small_run, tmp_path, capfd,
                                                        spoil, extra, words):
    import hashlib
    import shutil

    from glaciar import constants as C

    run = tmp_path / "run"
    shutil.copytree(small_run[1], run, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    d = _base(small_survey)
    spoil(d, tmp_path)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(d, sort_keys=False))

    def contents():
        return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in run.rglob("*")
                if p.is_file()}

    before, stat_before = contents(), _snapshot(run)
    capfd.readouterr()
    code = main(["simulate", str(cfg), "--out", str(run), "--workers", "2", "--quiet", *extra])
    err = capfd.readouterr().err
    assert code == 2 and err.count("\n") == 1 and all(w in err for w in words), err
    assert contents() == before and _snapshot(run) == stat_before


# ---------------------------------------------------------------------------
# accepted now
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("text, value", [("off", "off"), ("no", "off"), ("false", "off"),
                                         ("on", "on"), ("yes", "on"), ("'auto'", "auto")])
def test_yaml_1_1_words_of_an_enumeration_are_read_as_written(small_survey, tmp_path, text,
                                                              value):
    from glaciar.config import load_config

    d = _base(small_survey)
    d.pop("noise", None)
    body = yaml.safe_dump(d, sort_keys=False) + f"noise: {{correlated: {text}}}\n"
    p = tmp_path / "c.yaml"
    p.write_text(body)
    assert load_config(p).noise.correlated == value
