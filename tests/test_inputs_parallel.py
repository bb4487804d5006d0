"""The input check in a run's process pool (issue 24, point 2): each field's files checked by a
worker, with the serial check's fingerprints, cache, first error and "nothing written"."""
import concurrent.futures as cf
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from astropy.io import fits

from glaciar.cli import main
from glaciar.config import load_config
from glaciar.inputs import InputError, check_inputs

BANDS = ("f160w", "f098m", "f125w", "f606w")


class CountingPool(cf.ProcessPoolExecutor):
    """A process pool that counts the jobs it is given."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.jobs = 0

    def submit(self, fn, /, *args, **kwargs):
        self.jobs += 1
        return super().submit(fn, *args, **kwargs)


@pytest.fixture(scope="module")
def pool():
    with CountingPool(max_workers=2) as p:
        yield p


@pytest.fixture
def two_fields(small_survey, tmp_path):
    """A private copy of the small demo survey with a second field (a copy of the first's files)."""
    root = tmp_path / "survey"
    shutil.copytree(Path(small_survey).parent, root)
    path = root / Path(small_survey).name
    data = yaml.safe_load(path.read_text())
    first = data["survey"]["fields"][0]
    images = root / data["survey"]["image_dir"]
    for f in list(images.glob(f"{first}_*.fits")):
        shutil.copy(f, images / f.name.replace(first, "second", 1))
    data["survey"]["fields"] = [first, "second"]
    data["grid"] = {"z": {"values": [8.0]}, "mag": {"values": [25.0]}}
    data["simulation"] = {"n_galaxies": 4, "n_iterations": 1, "seed": 3}
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path, images, first


def weight_as_rms(images: Path, field: str, band: str) -> None:
    """The field's weight map of ``band`` replaced by its RMS (as the config declares weights)."""
    p = images / f"{field}_{band}_wht.fits"
    w = fits.getdata(p).astype(np.float64)
    with np.errstate(divide="ignore"):
        fits.writeto(p, (1.0 / np.sqrt(w)).astype(np.float32), overwrite=True)


def truncate(images: Path, field: str, band: str) -> None:
    p = images / f"{field}_{band}_drz.fits"
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])


def test_pool_check_is_the_serial_check(two_fields, pool):
    """Same fingerprints and cache entries (verdicts included) as the serial check, from one
    job per field on the pool."""
    path, images, first = two_fields
    cfg = load_config(path)
    serial, pooled = {}, {}
    want = check_inputs(cfg, cache=serial)
    jobs = pool.jobs
    got = check_inputs(cfg, cache=pooled, executor=pool)
    assert pool.jobs - jobs == 2                      # one per field
    assert got == want
    assert pooled == serial
    # every image checked and every noise map's verdict recorded (2 fields x 4 bands)
    assert sum(bool(e.get("checked")) for e in pooled.values()) == 16
    assert sum(bool(e.get("map_type_checked")) for e in pooled.values()) == 8


@pytest.mark.parametrize("damage,named", [
    # a noise map misdeclared in the first field, an unreadable image in the second: every
    # file's own check comes before the noise maps', so the second field's image is named
    ({"rms": (0, "f125w"), "cut": (1, "f098m")}, "second_f098m_drz.fits"),
    # misdeclared maps in both fields: the first field's (the first in input order)
    ({"rms": (0, "f606w"), "rms2": (1, "f160w")}, "{first}_f606w_wht.fits"),
    ({"rms": (1, "f125w")}, "second_f125w_wht.fits"),
], ids=["image-before-map", "first-field-first", "second-field"])
def test_the_first_error_is_the_serial_one(two_fields, pool, damage, named):
    path, images, first = two_fields
    fields = (first, "second")
    for what, (k, band) in damage.items():
        (truncate if what == "cut" else weight_as_rms)(images, fields[k], band)
    cfg = load_config(path)
    with pytest.raises(InputError) as serial:
        check_inputs(cfg)
    with pytest.raises(InputError) as pooled:
        check_inputs(cfg, executor=pool)
    assert str(pooled.value) == str(serial.value)
    assert named.format(first=first) in str(pooled.value)


def test_refused_with_two_workers_writes_nothing(two_fields, tmp_path, capsys):
    """``glaciar simulate --workers 2`` (the fields' files checked in its pool): one line,
    exit 2, no run directory."""
    path, images, first = two_fields
    weight_as_rms(images, "second", "f098m")
    out = tmp_path / "run"
    capsys.readouterr()
    code = main(["simulate", str(path), "--out", str(out), "--quiet", "--workers", "2"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "second_f098m_wht.fits" in err and "set survey.noise_type: rms" in err, err
    assert not out.exists()
