"""Hostile cases of `glaciar fit`, `report` and `next` (issue 21, bullets 3 and 8).

Each case: exit status 2, one line on stderr naming the run, nothing outside the
run directory touched, nothing already in it changed (the lock file aside, which
a refused command may create and never removes).  The runs are hand-made
(:func:`test_degenerate_fit.make_run`); no case samples.
"""
import numpy as np
import pytest

from glaciar import constants as C
from glaciar.cli import main
from glaciar.rundir import RunLock

from test_degenerate_fit import make_run

FAST = ["--quiet", "--model", "logistic", "--max-steps", "50"]


def _snapshot(root):
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(root.rglob("*")) if p.name != C.LOCK_NAME}


def _locked(run):
    make_run(run)
    (run / "fit").mkdir()
    (run / "fit" / "summary.json").write_text("{}")
    (run / C.SELECTION_FUNCTION_NAME).write_bytes(b"previous fit")
    (run / C.RUN_CONFIG_NAME).write_text("previous config")
    return RunLock(run).acquire()          # as `glaciar simulate` holds it while it writes


def _none_recovered(run):
    make_run(run, recovered=lambda d: np.zeros(len(d), bool))


def _none_recovered_with_selection(run):
    make_run(run, selection=["sn_f160w > 5"], recovered=lambda d: np.zeros(len(d), bool))


def _none_selected(run):
    make_run(run, selection=["sn_f160w > 5"], selected=lambda d: np.zeros(len(d), bool))


def _field_none_recovered(run):
    make_run(run, recovered=lambda d: (d["field"] == "f1").to_numpy() & (d["mag"] < 27).to_numpy())


def _field_none_selected(run):
    make_run(run, selection=["sn_f160w > 5"], selected=lambda d: (d["field"] == "f1").to_numpy())


def _flags_disagree(run):
    make_run(run, selection=[], selected=lambda d: (d["mag"] < 26).to_numpy())


def _missing(run):
    pass


def _a_file(run):
    run.write_text("not a run")


def _no_fit_yet(run):
    make_run(run)
    (run / C.RUN_CONFIG_NAME).write_text("survey: {}")


CASES = [
    # (id, set-up, command after "glaciar", words the one line must hold)
    ("fit-while-simulate-writes", _locked, ["fit"], ["being written", "pid"]),
    ("report-while-simulate-writes", _locked, ["report"], ["being written", "pid"]),
    ("report-html-while-simulate-writes", _locked, ["report", "--html"], ["being written"]),
    ("next-while-simulate-writes", _locked, ["next", "-n", "2"], ["being written"]),
    ("fit-nothing-recovered", _none_recovered, ["fit"], ["none of the", "recovered"]),
    ("fit-nothing-recovered-with-selection", _none_recovered_with_selection, ["fit"],
     ["none of the", "recovered"]),
    ("fit-nothing-selected", _none_selected, ["fit"], ["passes the selection"]),
    ("fit-field-nothing-recovered", _field_none_recovered, ["fit"], ["'f2'", "recovered"]),
    ("fit-per-field-nothing-selected", _field_none_selected, ["fit", "--per-field"],
     ["'f2'", "selection"]),
    ("fit-detection-only-flags-disagree", _flags_disagree, ["fit"], ["differ from 'recovered'"]),
    ("fit-no-such-run", _missing, ["fit"], ["no such run directory"]),
    ("fit-run-is-a-file", _a_file, ["fit"], ["no such run directory"]),
    ("report-no-such-run", _missing, ["report"], ["no such run directory"]),
    ("next-no-such-run", _missing, ["next"], ["no such run directory"]),
    ("next-before-any-fit", _no_fit_yet, ["next"], [C.SELECTION_FUNCTION_NAME]),
]


@pytest.mark.parametrize("setup,command,words", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_refused_in_one_line(tmp_path, capsys, setup, command, words):
    run = tmp_path / "run"
    if setup not in (_missing, _a_file):
        run.mkdir()
    lock = setup(run)
    before = _snapshot(tmp_path)
    capsys.readouterr()
    try:
        args = [command[0], str(run)] + command[1:] + (FAST if command[0] == "fit" else [])
        rc = main(args)
    finally:
        if lock is not None:
            lock.release()
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"glaciar {command[0]}: error: ") and str(run) in err, err
    for w in words:
        assert w in err, (w, err)
    assert _snapshot(tmp_path) == before


def test_leftovers_that_are_symlinks_are_unlinked_not_followed(tmp_path, capsys):
    """A killed fit's stage or old fit/ pointing outside the run: only the links go."""
    run = tmp_path / "run"
    run.mkdir()
    _none_recovered(run)
    outside = tmp_path / "outside"
    (outside / "fit").mkdir(parents=True)
    (outside / "fit" / "keep.npy").write_bytes(b"data")
    (outside / C.SELECTION_FUNCTION_NAME).write_bytes(b"data")
    for name in (".fit.new", ".fit.commit", ".fit.old"):
        (run / name).symlink_to(outside, target_is_directory=True)
    before = _snapshot(outside)
    assert main(["fit", str(run)] + FAST) == 2
    assert _snapshot(outside) == before
    assert not any((run / n).is_symlink() for n in (".fit.new", ".fit.commit", ".fit.old"))
    assert not (run / "fit").exists() and not (run / C.SELECTION_FUNCTION_NAME).exists()
