"""Hostile configuration inputs at the command line (issue 21, bullet 9, and more).

Each case runs ``glaciar simulate`` in this process on a copy of the small demo
survey's configuration with one bad input, and checks: exit status 2, exactly
one line on stderr (astropy's warnings from worker processes included: the
file descriptor is captured), the expected words in it, and nothing written:
no run directory, and the survey's and the test directory's files unchanged.

The second half checks what is now accepted: YAML 1.1 words of the
enumerations, and GLACiAR's own ``SExtractor_files/parameters.sex`` with its
bare ``GAIN`` line.
"""
from __future__ import annotations

import os

import pytest
import yaml

from glaciar.cli import main

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
    from test_glaciar_compat import PARAMS, _write_glaciar_images

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
