"""The command line: init template, precise errors with exit 2, simulate + report on FITS files."""
import shutil

import numpy as np
import pytest
import yaml
from astropy.table import Table

from glaciar import constants as C
from glaciar.cli import main
from glaciar.config import load_config

from tiny_runs import write_yaml


def test_init_writes_a_loadable_template(tmp_path, capsys):
    path = tmp_path / "g.yaml"
    assert main(["init", str(path)]) == 0
    text = path.read_text()
    assert text.count("#") > 20            # commented
    assert yaml.safe_load(text)["survey"]["detection_band"]
    # Refuses to overwrite without --force, with a one-line error and exit 2.
    assert main(["init", str(path)]) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "Traceback" not in err


def test_bad_config_names_the_key(small_survey, tmp_path, capsys):
    src = yaml.safe_load(small_survey.read_text())
    src["survey"]["bands"]["f160w"]["zeropoint"] = "abc"
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(src))
    assert main(["simulate", str(bad), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "survey.bands.f160w.zeropoint" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_missing_image_names_the_file(small_survey, tmp_path, capsys):
    survey_dir = small_survey.parent
    copy = tmp_path / "s"
    shutil.copytree(survey_dir, copy)
    (copy / "images" / "demo01_f125w_wht.fits").unlink()
    assert main(["simulate", str(copy / small_survey.name), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "demo01_f125w_wht.fits" in err


def test_simulate_and_report(small_survey, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["simulate", str(small_survey), "--out", str(out), "--workers", "1", "--quiet"]) == 0
    cfg = load_config(small_survey)
    t = Table.read(out / C.SUMMARY_DIRNAME / "summary_demo01.ecsv")
    assert len(t) == len(cfg.grid.z_values) * len(cfg.grid.mag_values)
    n = cfg.simulation.n_galaxies * cfg.simulation.n_iterations
    assert (t["n_input"] == n).all()
    np.testing.assert_allclose(t["completeness"], t["n_recovered"] / t["n_input"])
    for col in ("completeness", "selection_total", "selection"):
        assert (out / C.SUMMARY_DIRNAME / f"{col}_demo01.png").stat().st_size > 1000
    # Re-running resumes: nothing left to do.
    capsys.readouterr()
    assert main(["simulate", str(small_survey), "--out", str(out), "--workers", "1", "--quiet"]) == 0
    assert capsys.readouterr().out.startswith("0 tasks run")
    assert main(["report", str(out), "--regions"]) == 0
    regs = list((out / C.SUMMARY_DIRNAME / "regions").glob("*.reg"))
    # One region file per field, a circle per injected source.
    assert len(regs) == len(cfg.survey.fields)
    n_all = Table.read(out / C.SUMMARY_DIRNAME / "summary_all.ecsv")["n_input"].sum()
    assert sum(r.read_text().count("circle(") for r in regs) == int(n_all)


def test_fit_and_next_on_a_run(small_survey, small_run, tmp_path, capsys):
    """`glaciar fit` writes a loadable selection function; `next` proposes cells inside the grid.

    The run is a copy of the session's ``small_run`` (``small_survey`` simulated serially,
    as `glaciar simulate --workers 1` does; test_simulate_and_report runs that command).
    """
    from glaciar import SelectionFunction

    out = shutil.copytree(small_run[1], tmp_path / "run", ignore=shutil.ignore_patterns(C.LOCK_NAME))
    # The default model choice (four steps compared by PSIS-LOO) with short chains: what is
    # checked is the command's products, not convergence (tests/pipeline/test_fit.py).
    assert main(["fit", str(out), "--quiet", "--area-arcmin2", "2.0", "--max-steps", "300"]) == 0
    sf = SelectionFunction.read(out / C.SELECTION_FUNCTION_NAME)
    assert sf.area_arcmin2() == 2.0
    c = sf.completeness(np.array([24.0, 27.5]), np.array([8.0, 8.0]))
    assert 0 <= c[1] < c[0] <= 1
    capsys.readouterr()
    assert main(["next", str(out), "-n", "3"]) == 0
    lines = [l for l in capsys.readouterr().out.splitlines() if not l.startswith("#")]
    assert len(lines) == 3
    cfg = load_config(small_survey)
    for line in lines:
        z, m = map(float, line.split()[:2])
        assert min(cfg.grid.z_values) <= z <= max(cfg.grid.z_values)
        assert min(cfg.grid.mag_values) <= m <= max(cfg.grid.mag_values)


# --------------------------------------------------------------------------
# CLI values: one line, exit 2, nothing written
# --------------------------------------------------------------------------
CLI_CASES = [
    (["simulate", "{cfg}", "--out", "{out}", "--workers", "0"], "--workers: expected an integer >= 1, got '0'"),
    (["simulate", "{cfg}", "--out", "{out}", "--workers", "-3"], "--workers: expected an integer >= 1, got '-3'"),
    (["simulate", "{cfg}", "--out", "{out}", "--seed", "abc"], "--seed: expected an integer >= 0, got 'abc'"),
    (["simulate", "{cfg}", "--out", "{out}", "--seed", "-1"], "--seed: expected an integer >= 0, got '-1'"),
    (["simulate", "{cfg}", "--out", "{out}", "--mode", "fast"], "--mode: invalid choice: 'fast'"),
    (["fit", "{out}", "--area-arcmin2", "-1"], "--area-arcmin2: expected a finite number > 0, got '-1'"),
    (["fit", "{out}", "--area-arcmin2", "nan"], "--area-arcmin2: expected a finite number > 0, got 'nan'"),
    (["fit", "{out}", "--area-arcmin2", "inf"], "--area-arcmin2: expected a finite number > 0, got 'inf'"),
    (["fit", "{out}", "--max-steps", "0"], "--max-steps: expected an integer >= 1, got '0'"),
    (["next", "{out}", "-n", "0"], "-n: expected an integer >= 1, got '0'"),
    (["next", "{out}", "-n", "-1"], "-n: expected an integer >= 1, got '-1'"),
    (["simulate"], "the following arguments are required: config"),
]


@pytest.mark.parametrize("argv, expected", CLI_CASES, ids=[" ".join(c[0][2:]) or c[0][0] for c in CLI_CASES])
def test_bad_cli_values_one_line_exit_2(argv, expected, one_task_run, tmp_path, capsys):
    d, _ = one_task_run
    cfg = write_yaml(d, tmp_path / "c.yaml")
    out = tmp_path / "out"
    argv = [a.format(cfg=cfg, out=out) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [f"glaciar: error: {expected}" if "invalid choice" not in expected
                                else err.splitlines()[0]]
    assert expected in err and "usage" not in err
    assert not out.exists()


def test_out_pointing_to_a_file_is_refused(one_task_run, tmp_path, capsys):
    d, _ = one_task_run
    cfg = write_yaml(d, tmp_path / "c.yaml")
    f = tmp_path / "results.txt"
    f.write_text("keep me")
    assert main(["simulate", str(cfg), "--out", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [f"glaciar simulate: error: --out {f}: exists and is not a directory"]
    assert f.read_text() == "keep me"


def test_user_warnings_are_one_line_each_and_developer_warnings_are_not_shown(
        small_run, tmp_path, capsys, monkeypatch):
    """A garbage-collected open file (ResourceWarning) met during a command is not the
    user's news; the command's own warnings are, once each, as ``warning: ...``."""
    import warnings

    import glaciar.report

    run = tmp_path / "run"
    shutil.copytree(small_run[1], run, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    real = glaciar.report.write_summary_files

    def noisy(*args, **kwargs):
        warnings.warn("unclosed file <_io.TextIOWrapper name=19>", ResourceWarning)
        warnings.warn("a deprecated thing", DeprecationWarning)
        for _ in range(2):
            warnings.warn("the run's own caveat")
        return real(*args, **kwargs)

    monkeypatch.setattr(glaciar.report, "write_summary_files", noisy)
    capsys.readouterr()
    assert main(["report", str(run)]) == 0
    assert capsys.readouterr().err.splitlines() == ["warning: the run's own caveat"]
    # Warnings shown by Python's own machinery (outside the recorded blocks) alike.
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        from glaciar.cli import _show_warning
        _show_warning(ResourceWarning("unclosed"), ResourceWarning, "f.py", 1)
        _show_warning(UserWarning("shown"), UserWarning, "f.py", 1)
    assert capsys.readouterr().err.splitlines() == ["warning: shown"]
