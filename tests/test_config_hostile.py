"""Hostile configuration inputs: each is refused fast, in one line naming the file and key.

Part of the hostile-input suite of issue 10 (the run-directory and CLI-value
cases are in test_integrity.py). Every case must fail with a ConfigError (or
exit status 2 from the CLI) whose message names where the problem is, within
a second, without a traceback and without writing anything.
"""
import copy
import time

import numpy as np
import pytest
import yaml

from glaciar.cli import main
from glaciar.config import ConfigError, config_from_dict, load_config
from glaciar.engine.selection import compile_selection

MOFFAT = {"profile": "moffat", "fwhm_arcsec": 0.18}
BASE = {"survey": {"fields": ["f1"], "science": "{field}_{band}.fits", "detection_band": "f160w",
                   "bands": {"f160w": {"filter": "wfc3_ir_f160w", "zeropoint": 25.9,
                                       "psf": MOFFAT},
                             "f125w": {"filter": "wfc3_ir_f125w", "zeropoint": 26.2,
                                       "psf": MOFFAT}}},
        "selection": ["sn_f160w > 5"]}


def base():
    return copy.deepcopy(BASE)


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
    d = base()
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
    d = base()
    mutate(d)
    msg = refused(d, tmp_path)
    assert msg.startswith(f"c.yaml: {where}: ") and what in msg, msg


def test_non_utf8_fields_file(tmp_path):
    (tmp_path / "fields.txt").write_bytes(b"caf\xe9\n")
    d = base()
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
