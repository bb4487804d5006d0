"""Hostile noise inputs at the CLI (issue 21, bullets 1 and 2): each is one line, exit 2, nothing written.

Mis-declared noise maps (an RMS map declared as weight and the reverse, maps in the
wrong units) are refused by ``glaciar simulate`` before anything is written, with the
fix; a background no noise model can describe is refused naming the settings to
change. Maps within the factor a map scale handles are accepted (documented).
Every refusal leaves the files around it, and an existing run, unchanged.
"""
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from astropy.io import fits

from glaciar.cli import main
from glaciar.config import load_config
from glaciar.inputs import InputError, check_inputs

from noise_fields import SIGMA, big_galaxy_survey, hff

BANDS = ("f160w", "f098m", "f125w", "f606w")


def snapshot(root: Path) -> dict:
    """Every file under ``root``: (size, mtime_ns, bytes) — what a refusal must not change."""
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns, p.read_bytes())
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def demo(small_survey, tmp_path):
    """A private copy of the session's small demo survey (its images are written into)."""
    root = tmp_path / "survey"
    shutil.copytree(Path(small_survey).parent, root)
    return root / Path(small_survey).name


def write_maps(cfg_path: Path, make, suffix: str, noise_type: str, bands=BANDS, **survey) -> Path:
    """Noise maps ``make(weight)`` as ``{field}_{band}_<suffix>.fits``; a config declaring ``noise_type``."""
    data = yaml.safe_load(cfg_path.read_text())
    images = cfg_path.parent / data["survey"]["image_dir"]
    field = data["survey"]["fields"][0]
    for b in BANDS:
        wht = fits.getdata(images / f"{field}_{b}_wht.fits").astype(np.float64)
        out = make(wht) if b in bands else wht if noise_type == "weight" else 1 / np.sqrt(wht)
        fits.writeto(images / f"{field}_{b}_{suffix}.fits", out.astype(np.float32), overwrite=True)
    data["survey"].update(noise="{field}_{band}_" + suffix + ".fits", noise_type=noise_type, **survey)
    path = cfg_path.with_name(f"{suffix}_{noise_type}.yaml")
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def rms_of(w):
    with np.errstate(divide="ignore"):
        return 1.0 / np.sqrt(w)          # inf where the weight is 0: no data, as in the weight map


def refused_cli(capsys, root: Path, config: Path, out: Path) -> str:
    """``glaciar simulate``: exit 2, one stderr line, nothing under ``root`` changed, ``out`` empty."""
    before = snapshot(root)
    capsys.readouterr()
    code = main(["simulate", str(config), "--out", str(out), "--quiet", "--workers", "1"])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    after = {k: v for k, v in snapshot(root).items()
             if not (root / k).resolve().is_relative_to(out.resolve())}
    assert after == {k: v for k, v in before.items()
                     if not (root / k).resolve().is_relative_to(out.resolve())}
    assert not out.exists() or not any(p.is_file() and p.stat().st_size
                                       for p in out.rglob("*") if p.name != ".lock")
    return err


# (name, how the maps are made from the demo's weights, suffix, declared noise_type, expected)
CASES = [
    ("rms map declared weight", rms_of, "rms", "weight", "set survey.noise_type: rms"),
    ("weight map declared rms", lambda w: w, "wht2", "rms", "set survey.noise_type: weight"),
    ("rms map x1000 declared rms", lambda w: 1000 * rms_of(w), "rmsx", "rms", "units"),
    ("weight map / 1e10 declared weight", lambda w: w / 1e10, "whtx", "weight", "units"),
    ("rms map / 1000 declared rms", lambda w: rms_of(w) / 1000, "rmsd", "rms", "units"),
]


@pytest.mark.parametrize("name,make,suffix,ntype,expected", CASES, ids=[c[0] for c in CASES])
def test_misdeclared_map_is_refused(demo, tmp_path, capsys, name, make, suffix, ntype, expected):
    cfg = write_maps(demo, make, suffix, ntype)
    err = refused_cli(capsys, tmp_path, cfg, tmp_path / "run")
    assert expected in err and "survey.noise (field" in err and f"_{suffix}.fits" in err, err
    assert "implied sigma" in err


def test_one_bad_band_is_named(demo, tmp_path, capsys):
    cfg = write_maps(demo, rms_of, "mix", "weight", bands=("f125w",))
    err = refused_cli(capsys, tmp_path, cfg, tmp_path / "run")
    assert "band 'f125w'" in err and "demo01_f125w_mix.fits" in err and "noise_type: rms" in err


def test_misdeclared_map_leaves_an_existing_run_unchanged(demo, tmp_path, capsys):
    """A finished run, then the same --out with the weight maps declared as RMS: refused, and
    the run's files (tasks, manifest, summaries) are byte for byte as they were."""
    data = yaml.safe_load(demo.read_text())
    data["grid"] = {"z": {"values": [8.0]}, "mag": {"values": [25.0]}}
    data["simulation"] = {"n_galaxies": 4, "n_iterations": 1, "seed": 3}
    good = demo.with_name("one_task.yaml")
    good.write_text(yaml.safe_dump(data, sort_keys=False))
    run = tmp_path / "run"
    assert main(["simulate", str(good), "--out", str(run), "--quiet", "--workers", "1"]) == 0
    data["survey"]["noise_type"] = "rms"
    bad = demo.with_name("one_task_rms.yaml")
    bad.write_text(yaml.safe_dump(data, sort_keys=False))
    before = snapshot(run)
    capsys.readouterr()
    assert main(["simulate", str(bad), "--out", str(run), "--quiet", "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "set survey.noise_type: weight" in err, err
    assert snapshot(run) == before


@pytest.mark.parametrize("factor", [0.5, 2.0, 5.0])
def test_a_map_a_few_times_off_is_accepted(demo, factor):
    """Documented: a map off by a factor the map-scale handles (here 0.5-5) is not refused."""
    cfg = load_config(write_maps(demo, lambda w: factor * rms_of(w), f"rms{factor:g}".replace(".", "p"), "rms"))
    check_inputs(cfg)


def test_map_weight_maps_are_relative(demo):
    """Documented: with WEIGHT_TYPE MAP_WEIGHT the weight map's scale is free (it is rescaled)."""
    path = write_maps(demo, lambda w: w * 1e-8, "rel", "weight")
    data = yaml.safe_load(path.read_text())
    data.setdefault("detection", {})["WEIGHT_TYPE"] = "MAP_WEIGHT"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    check_inputs(load_config(path))
    data["detection"]["WEIGHT_TYPE"] = None           # the same maps read as absolute: refused
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(InputError, match="units"):
        check_inputs(load_config(path))


def test_the_verdict_is_cached_per_file_and_noise_type(demo):
    cfg = load_config(demo)
    cache: dict = {}
    check_inputs(cfg, cache=cache)
    stamps = [e.get("map_type_checked") for e in cache.values() if e.get("map_type_checked")]
    assert len(stamps) == len(BANDS) and all(s[0] == "weight" for s in stamps)


def test_background_no_model_describes_is_refused(tmp_path, capsys):
    """The synthetic egg-crate background of tests/engine/test_noise.py: simulate exits 2 in one line
    naming the field, band, r(N) and the settings to change; nothing written."""
    root = tmp_path / "syn"
    data = big_galaxy_survey(root, amp=0.0, n=192, back_size=64)
    sci = fits.getdata(root / "img" / "f_b.fits").astype(np.float32)
    y, x = np.mgrid[:192, :192]
    sci += (3.0 * SIGMA * np.sin(2 * np.pi * x / 96)
            * np.sin(2 * np.pi * y / 96)).astype(np.float32)
    fits.writeto(root / "img" / "f_b.fits", sci, overwrite=True)
    cfg = root / "syn.yaml"
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    err = refused_cli(capsys, tmp_path, cfg, tmp_path / "run")
    assert "field 'f', band 'b'" in err and "r(N) = " in err and "detection.BACK_SIZE" in err
    assert "noise.correlated: 'off'" in err


def test_big_galaxy_warns_once_and_prints_the_factors(tmp_path, capsys):
    """Documented behaviour, not a refusal: the mesh's residuals around a large galaxy are
    said in one warning line, and the simulate summary prints the factors used."""
    root = tmp_path / "syn"
    data = big_galaxy_survey(root)
    cfg = root / "syn.yaml"
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    capsys.readouterr()
    assert main(["simulate", str(cfg), "--out", str(tmp_path / "run"), "--quiet", "--workers", "1"]) == 0
    out, err = capsys.readouterr()
    warned = [line for line in err.splitlines() if "background mesh" in line]
    assert len(warned) == 1 and "BACK_SIZE 64" in warned[0] and "field 'f', band 'b'" in warned[0]
    line = [s for s in out.splitlines() if s.startswith("noise f b:")]
    assert len(line) == 1 and "map scale 1" in line[0] and "applied" in line[0]
    assert "about local backgrounds" in line[0]


@pytest.mark.skipif(not (hff.DATA / "abell_2744_dwarf_galaxy_f105w_rms.fits.gz").is_file(),
                    reason=f"HFF A2744 cutouts not present at {hff.DATA}")
def test_hff_rms_map_declared_weight_is_refused(tmp_path, capsys):
    """The issue's case: before, it ran and gave C = 0 everywhere."""
    data = hff.hff_config(hff.DATA, 64)
    data["survey"]["noise_type"] = "weight"
    cfg = tmp_path / "hff.yaml"
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    err = refused_cli(capsys, tmp_path, cfg, tmp_path / "run")
    assert "_rms.fits.gz: survey.noise_type is weight but the map looks like an RMS map" in err
    assert err.endswith("set survey.noise_type: rms")
