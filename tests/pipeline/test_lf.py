"""`glaciar lf` on the command line: its exit paths, and how it meets `glaciar catalog`.

The run is a copy of the session's ``small_run`` (a real store and manifest: the identity a
catalogue must match).  Catalogues of other configurations are made by ``glaciar catalog``
itself, from a configuration with another setting (``classification.min_sn``) and from a
survey with other images (the same settings, another image seed).  The selection function
put into the copy is the analytic one of ``tests/analytic_sf.py`` (``lf_sf``: 4 draws, a
transfer matrix; stamped with the run's ``config_hash``), so that a fit takes seconds; the
candidates of the success paths are drawn from its forward model and written with the run's
identity, as ``benchmarks/lf_speed.py`` writes them.

Every refusal is exit status 2 with one line on stderr that names the cause, and writes
nothing under ``RUN/lf``.
"""
import json
import shutil

import numpy as np
import pandas as pd
import pytest
import yaml

from glaciar import constants as C
from glaciar.cli import main
from glaciar.lf import default_window, schechter
from glaciar.pipeline.catalog import catalog_identity, read_catalog, write_catalog
from glaciar.rundir import read_manifest
from analytic_sf import TRUE, lf_sf, mock_candidates


def _cli(capsys, *argv):
    """(exit status, stdout, stderr) of ``glaciar *argv``."""
    capsys.readouterr()
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _refused(code, err, *needles):
    assert code == 2, err
    line = err.strip()
    assert "\n" not in line and "Traceback" not in line, err
    for n in needles:
        assert n in line, (n, line)


@pytest.fixture(scope="module")
def lf_run(small_run, tmp_path_factory):
    """A copy of ``small_run`` with its own catalogue (``glaciar catalog RUN``) and the analytic
    selection function of tests/analytic_sf.py; shared by this module's tests, which copy it again
    when they write into it."""
    _, run = small_run
    dst = tmp_path_factory.mktemp("lf_cli") / "run"
    shutil.copytree(run, dst, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    assert main(["catalog", str(dst), "--quiet"]) == 0             # -> RUN/catalog.parquet
    manifest = read_manifest(dst)
    sf = lf_sf()
    sf.meta["config_hash"] = manifest["config_hash"]
    sf.write(dst / C.SELECTION_FUNCTION_NAME)
    return dst


@pytest.fixture
def run(lf_run, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(lf_run, dst, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    return dst


@pytest.fixture(scope="module")
def other_catalogs(small_survey, tmp_path_factory):
    """``glaciar catalog`` of (a) the run's own configuration file, (b) the same with another
    min_sn, (c) a survey of the same settings with other images: {name: path}."""
    from glaciar.demo import build_demo_survey

    base = tmp_path_factory.mktemp("other_catalogs")
    cfg = yaml.safe_load(small_survey.read_text())
    # (b): the same images (the configuration beside them), another S/N threshold
    other = dict(cfg, classification={**cfg.get("classification", {}),
                                      "min_sn": float(cfg.get("classification", {})
                                                      .get("min_sn", 3.0)) + 1.0})
    survey_copy = base / "survey"
    shutil.copytree(small_survey.parent, survey_copy)
    (survey_copy / "min_sn.yaml").write_text(yaml.safe_dump(other, sort_keys=False))
    # (c): the small survey's settings (image seed aside), other images
    images = build_demo_survey(base / "images", shape=(320, 320), seed=12, n_galaxies=12,
                               n_iterations=2, z_values=(8.0, 10.4), mag_values=(24.0, 27.5))
    out = {}
    for name, config in (("same", small_survey), ("settings", survey_copy / "min_sn.yaml"),
                         ("inputs", images)):
        out[name] = base / f"{name}.parquet"
        assert main(["catalog", str(config), "--out", str(out[name]), "--quiet"]) == 0
    return out


def _candidates(run, path, *, n_seed=21, drop=()):
    """Selected candidates from the forward model of the run's selection function, written with
    the run's identity (as ``glaciar catalog`` records it); their number."""
    manifest = read_manifest(run)
    det = manifest["detection_band"]
    sf = lf_sf()
    m = mock_candidates(sf, lambda M: schechter(M, **TRUE), default_window(sf), seed=n_seed)
    col = C.band_column(C.OBS_MAG_QUANTITY, det)
    table = pd.DataFrame({"field": manifest["fields"][0], "id": np.arange(len(m)),
                          "x": np.zeros(len(m)), "y": np.zeros(len(m)),
                          "selected": np.ones(len(m), bool), col: m})
    table = table.drop(columns=list(drop))
    meta = {**catalog_identity(manifest["store_hash"], manifest["inputs"], manifest["fields"], det),
            "obs_mag_column": col}
    write_catalog(table, path, meta)
    return len(m)


# ------------------------------------------------------------------------ identity
@pytest.mark.parametrize("which, what", [("settings", "other measurement settings"),
                                         ("inputs", "other input files")])
def test_catalogue_of_another_configuration_is_refused(run, other_catalogs, capsys, which, what):
    code, out, err = _cli(capsys, "lf", run, "--catalog", other_catalogs[which], "--quiet")
    _refused(code, err, what, str(other_catalogs[which]), "glaciar catalog")
    assert not (run / "lf").exists()


def test_catalogue_of_the_runs_configuration_file_is_accepted(run, other_catalogs, capsys):
    # `glaciar catalog CONFIG` (the file the run was made from, not the run's stored
    # config.yaml) records the same identity: accepted.  The 320^2 demo field at the demo's
    # depth holds no J125-dropout, so the fit stops at that, naming it.
    for cat in (other_catalogs["same"], run / "catalog.parquet"):
        t, _ = read_catalog(cat)
        assert len(t) and int(t[C.COL_SELECTED].sum()) == 0
    for cat in (other_catalogs["same"], run / "catalog.parquet"):
        code, out, err = _cli(capsys, "lf", run, "--catalog", cat, "--quiet")
        _refused(code, err, "no selected candidate", "mag_auto_f160w")
    code, out, err = _cli(capsys, "lf", run, "--quiet")             # default: RUN/catalog.parquet
    _refused(code, err, "no selected candidate", str(run / "catalog.parquet"))
    assert not (run / "lf").exists()


# ------------------------------------------------------------------------ columns
@pytest.mark.parametrize("column", ["mag_auto_f160w", "selected"])
def test_catalogue_without_a_needed_column(run, tmp_path, capsys, column):
    cat = tmp_path / "cat.parquet"
    _candidates(run, cat, drop=[column])
    code, out, err = _cli(capsys, "lf", run, "--catalog", cat, "--quiet")
    _refused(code, err, "missing column", column, "detection band of the run is f160w")
    assert not (run / "lf").exists()


# ------------------------------------------------------------------------ --fix
@pytest.mark.parametrize("model, allowed", [
    ("schechter", "allowed: log_phi_star, M_star, alpha"),
    ("dpl", "allowed: log_phi_star, M_star, alpha, beta"),
    ("stepwise", "allowed: log_phi_0, log_phi_1, ..."),
])
def test_fix_of_an_unknown_parameter_names_the_allowed_ones(run, tmp_path, capsys, model, allowed):
    cat = tmp_path / "cat.parquet"
    _candidates(run, cat)
    code, out, err = _cli(capsys, "lf", run, "--catalog", cat, "--model", model,
                          "--fix", "alpha2=1", "--quiet")
    _refused(code, err, "'alpha2'", allowed)
    assert not (run / "lf").exists()


def test_fix_on_stepwise(run, tmp_path, capsys):
    cat = tmp_path / "cat.parquet"
    _candidates(run, cat)
    # A step the model's bins do not have: refused once the bins are known, naming them.
    code, out, err = _cli(capsys, "lf", run, "--catalog", cat, "--model", "stepwise",
                          "--fix", "log_phi_99=-4", "--quiet")
    _refused(code, err, "'log_phi_99'", "allowed: log_phi_0, log_phi_1")
    assert not (run / "lf").exists()
    # A parametric model's parameter is not a step.
    code, out, err = _cli(capsys, "lf", run, "--catalog", cat, "--model", "stepwise",
                          "--fix", "alpha=-2", "--quiet")
    _refused(code, err, "'alpha'", "log_phi_0")
    assert not (run / "lf").exists()
    # One step held: fitted with the others free, and recorded as fixed.
    code, out, err = _cli(capsys, "lf", run, "--catalog", cat, "--model", "stepwise",
                          "--fix", "log_phi_0=-4.5", "--quiet")
    assert code == 0, err
    summary = json.loads((run / "lf" / "summary.json").read_text())
    assert summary["model"] == "stepwise" and summary["fixed"] == {"log_phi_0": -4.5}
    assert summary["parameters"]["log_phi_0"] == {"median": -4.5, "lo68": -4.5, "hi68": -4.5}
    free = [p for k, p in summary["parameters"].items() if k != "log_phi_0"]
    assert free and all(p["hi68"] > p["lo68"] for p in free)


# ------------------------------------------------------------------------ success
def test_lf_through_the_cli(run, tmp_path, capsys):
    cat = tmp_path / "cat.parquet"
    n = _candidates(run, cat)
    code, out, err = _cli(capsys, "lf", run, "--catalog", cat, "--model", "schechter",
                          "--fix", f"M_star={TRUE['M_star']}", "--seed", 3, "--quiet")
    assert code == 0, err
    summary = json.loads((run / "lf" / "summary.json").read_text())
    assert summary["catalog_identity"] == "store_hash"
    assert summary["n_candidates"] + summary["n_outside_window"] == n
    assert summary["fixed"] == {"M_star": TRUE["M_star"]}
    lines = out.strip().splitlines()
    assert lines[0] == f"schechter: {summary['n_candidates']} candidates"
    assert lines[-1] == f"wrote {run / 'lf'}"
    for name in ("log_phi_star", "M_star", "alpha"):
        p = summary["parameters"][name]
        assert any(line.split()[0] == name and f"{p['median']:.3f}" in line for line in lines[1:-1])
        if name != "M_star":                  # the input within 3 half-widths of the 68 % interval
            assert abs(p["median"] - TRUE[name]) < 1.5 * (p["hi68"] - p["lo68"]), (name, p)
    for f in ("summary.json", "counts.ecsv", "binned_phi.ecsv", "lf.png"):
        assert (run / "lf" / f).is_file()
