"""Issue 21, bullets 3, 4 and 8: degenerate outcomes are not fits, honest fit output,
one consistent reader/writer of a run's fit.

The runs here are hand-made (a known logistic completeness, one task file per z),
a few hundred sources, fitted with one model and short chains: the fixture fit
costs ~5 s and is shared by the module.
"""
import json
import shutil
import time
import warnings

import astropy.units as u
import numpy as np
import pandas as pd
import pytest
from astropy.cosmology import Planck18
from scipy import stats

from glaciar import constants as C
from glaciar.cli import main
from glaciar.inference import SelectionFunction, SurfaceModel
from glaciar.inference.sampling import ConvergenceWarning, SamplerSettings
from glaciar.pipeline import run_fit
from glaciar.rundir import RunLock, read_manifest
from glaciar.store import read_results, write_task_table

Z = np.array([6.0, 7.0, 8.0])
M = np.arange(25.0, 29.01, 0.5)
#: the truth of the hand-made runs: C_max = 0.92, m50 = 27.2, w = 0.3 mag, no z dependence
C_MAX, M50, W = 0.92, 27.2, 0.3


def make_run(run_dir, *, n_per_cell=12, selection=(), fields=("f1", "f2"), seed=3,
             recovered=None, selected=None):
    """A run directory with one task file per z and a manifest; returns the rows.

    ``selection=()`` is a detection-only run (selected = recovered); otherwise
    a source is selected with probability 0.7 once recovered.  ``recovered`` /
    ``selected`` (callables of the rows) override the flags.
    """
    rng = np.random.default_rng(seed)
    z = np.repeat(Z, len(M) * n_per_cell)
    m = np.tile(np.repeat(M, n_per_cell), len(Z))
    c = C_MAX / (1.0 + np.exp((m - M50) / W))
    df = pd.DataFrame({"field": np.resize(np.array(fields), z.size), "z": z, "mag": m,
                       "mag_input": m + 0.02 * rng.standard_normal(z.size)})
    df["recovered"] = rng.random(z.size) < c if recovered is None else recovered(df)
    if selected is not None:
        df["selected"] = selected(df) & df["recovered"]
    elif selection:
        df["selected"] = df["recovered"] & (rng.random(z.size) < 0.7)
    else:
        df["selected"] = df["recovered"]
    for i, (zv, d) in enumerate(df.groupby("z")):
        write_task_table(run_dir, f"task_f_z{i:03d}_m000_i0000.parquet", d)
    (run_dir / C.MANIFEST_NAME).write_text(json.dumps({
        "fields": list(fields), "area_arcmin2": {f: 2.0 for f in fields},
        "bands": ["f125w", "f160w"], "config_hash": "abc", "selection": list(selection)}))
    return df


FAST = dict(model="logistic", sampler=SamplerSettings(max_steps=150, seed=1))


@pytest.fixture(scope="module")
def detection_only_fit(tmp_path_factory):
    """A detection-only run fitted once (plots on): (run dir, rows, warnings, wall seconds)."""
    run = tmp_path_factory.mktemp("detonly")
    df = make_run(run)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_fit(run, **FAST)
    return run, df, caught, time.perf_counter() - t0


# ---------------------------------------------------------------- bullet 3: S = 1
def test_detection_only_has_s_exactly_one_and_p_equal_c(detection_only_fit):
    """Before: S was fitted (0.95-0.98), so P = C S was 2-5 % below C."""
    from astropy.io import fits

    run, df, _, _ = detection_only_fit
    sf = SelectionFunction.read(run / C.SELECTION_FUNCTION_NAME)
    assert sf.model.selection is False
    assert not any(n.startswith(("logit_s_max", "eta_", "log_dz_")) for n in sf.param_names)
    zz, mm = np.meshgrid(np.linspace(6, 8, 7), np.linspace(25, 29, 9))
    c = sf.completeness(mm, zz, draws=True)
    assert np.all(sf.selection_given_recovered(zz, mm, draws=True) == 1.0)
    assert np.array_equal(sf.selection_probability(zz, mm, draws=True), c)
    # the tabulated grids of the file, and the surfaces LF code integrates
    with fits.open(run / C.SELECTION_FUNCTION_NAME) as h:
        assert np.all(h["SR_GRID", 1].data == 1.0)
        assert np.array_equal(h["P_GRID", 1].data, h["C_GRID", 1].data)
        assert h["DRAWS", 1].header["SELFIT"] is False
    cg, sg = sf.model.surfaces_on_grid(sf.draws[:20], Z, M)
    assert np.all(sg == 1.0)
    from glaciar.inference.counts import _selection_table
    nodes, sr = np.array([np.nan]), np.array([1.0])
    assert np.array_equal(_selection_table(sf, np.arange(20), Z, M, nodes, sr), cg)


def test_detection_only_summary_has_no_s_outputs(detection_only_fit):
    """No selection figure, no z-edge advice; the summary says S = 1."""
    run, _, caught, _ = detection_only_fit
    summ = json.loads((run / "fit" / "summary.json").read_text())
    assert summ["detection_only"] is True
    assert summ["fits"]["all"]["z_edges"] == []
    assert not (run / "fit" / "selection_all.png").exists()
    assert (run / "fit" / "completeness_all.png").exists()
    assert not any("extend the z grid" in str(w.message) for w in caught)
    assert "S = 1 exactly" in (run / "fit" / "summary.txt").read_text()


def test_detection_only_report_draws_no_s(detection_only_fit, tmp_path):
    """The report's curves section and summary maps leave S out for a detection-only run."""
    from glaciar import report as R
    from glaciar.plots import plot_summary_maps

    run, df, _, _ = detection_only_fit
    sfd = R._read_selection_function(run / C.SELECTION_FUNCTION_NAME)
    summ = pd.DataFrame({"z": [6.0, 6.0], "mag": [25.0, 26.0], "n_input": [10, 10],
                         "n_recovered": [9, 5], "n_selected": [9, 5]})
    html = R._curves_section({"selection_function": sfd, "manifest": {"z_values": list(Z),
                              "mag_values": list(M), "selection": []},
                              "summaries": {"all": summ}})
    assert "fig-selection-" not in html and "S = 1" in html
    table = pd.DataFrame({"z": [6.0, 6.0, 7.0, 7.0], "mag": [25.0, 26.0, 25.0, 26.0],
                          "completeness": 0.5, "selection_total": 0.5, "selection": 1.0})
    paths = plot_summary_maps(table, tmp_path, "deep", selection=False)
    assert sorted(p.name for p in paths) == ["completeness_deep.png", "selection_total_deep.png"]


# ------------------------------------------------------- bullet 3: NaN outside the box
def test_magnitude_at_is_nan_outside_the_simulated_range():
    """A fit whose C falls to 0.5 at m = 22 while 25-29 was simulated: m50 is NaN, not 22.

    Before: magnitude_at searched +-5 mag around the range and returned 22.0 while
    completeness(22) was NaN.
    """
    mdl = SurfaceModel.for_data(Z, M, shape="logistic")
    th = mdl.prior_mean.copy()
    th[mdl.param_names.index("m50_0")] = 22.0
    th[mdl.param_names.index("logit_c_max_0")] = 3.0
    th[mdl.param_names.index("log_w_0")] = np.log(0.3)
    draws = th + 1e-3 * np.random.default_rng(0).standard_normal((50, mdl.n_params))
    sf = SelectionFunction(mdl, draws, domain={"z": (6.0, 8.0), "mag": (25.0, 29.0)})
    r = sf.magnitude_at(0.5, [7.0])
    assert np.isnan(r.median[0]) and np.isnan(r.lower[0]) and np.isnan(r.upper[0])
    assert np.isnan(sf.completeness(22.0, 7.0))
    # the same surface evaluated inside: a level inside the range is still found
    th[mdl.param_names.index("m50_0")] = 27.0
    sf2 = SelectionFunction(mdl, th[None, :], domain={"z": (6.0, 8.0), "mag": (25.0, 29.0)})
    c_max = 1 / (1 + np.exp(-3.0))
    assert abs(sf2.magnitude_at(0.5, [7.0]).median[0] - (27.0 + 0.3 * np.log(2 * c_max - 1))) < 1e-6
    # a redshift outside the simulated range is NaN too, as are grids reaching outside
    assert np.isnan(sf2.magnitude_at(0.5, [9.0]).median[0])
    g = sf2.grid_draws(np.array([7.0, 9.0]), np.array([24.0, 27.0]))
    for k in ("C", "S", "P"):
        assert np.isnan(g[k][0, 1]).all() and np.isnan(g[k][0, :, 0]).all()
        assert np.isfinite(g[k][0, 0, 1])


# ------------------------------------------------------------ bullet 4: honest output
def test_warnings_name_the_model_and_summary_says_why_kept(detection_only_fit):
    """Before: "emcee chain (c block) ... shorter than 50 tau" named no model."""
    run, _, caught, _ = detection_only_fit
    conv = [str(w.message) for w in caught if issubclass(w.category, ConvergenceWarning)]
    assert conv, "150 steps should not converge"
    assert all(m.startswith("fit 'all', model logistic (the only model fitted):") for m in conv)
    txt = (run / "fit" / "summary.txt").read_text()
    assert "kept logistic: the only model fitted (--model logistic)" in txt
    assert "logistic converged: NO" in txt


def test_kept_reason_names_the_rule():
    from glaciar.pipeline.fit import kept_reason

    table = [{"model": "logistic", "delta_elpd": -0.5}, {"model": "erf", "delta_elpd": 0.0}]
    assert "within 2 s.e. of the best (erf)" in kept_reason("logistic", table, "auto")
    assert "highest PSIS-LOO elpd" in kept_reason("erf", table, "auto")


def test_fit_wall_time_is_the_commands(detection_only_fit):
    """Before: the report showed the kept model's sampler time (8.2 s of a 3-minute fit)."""
    from glaciar import report as R

    run, _, _, elapsed = detection_only_fit
    summ = json.loads((run / "fit" / "summary.json").read_text())
    assert 0.8 * elapsed <= summ["wall_time_s"] <= elapsed
    e = summ["fits"]["all"]
    assert e["sampler_time_s"] < e["wall_time_s"] <= summ["wall_time_s"]
    html = R._statistics_section({"manifest": {"fields": []}, "summaries": {"all": pd.DataFrame(
        {"n_input": [1], "n_recovered": [1], "n_selected": [1]})}, "fit_summary": summ})
    assert f"Fit wall time: {summ['wall_time_s']:.1f} s" in html
    assert "the only model fitted (--model logistic)" in html       # why the model was kept


# ------------------------------------------------------ bullet 8: one unit, leftovers
def _snapshot(root):
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != C.LOCK_NAME}


def test_killed_fit_leaves_previous_result_and_its_leftovers_go(detection_only_fit, tmp_path,
                                                               monkeypatch):
    """A fit dying at its last write changes nothing; a killed fit's tmp files are removed.

    Before: the chains, tables and plots were written into fit/ one by one, so a fit
    dying before selection_function.fits left them beside the previous file, and
    fit/.chain*.tmp files were never removed.
    """
    import shutil

    from glaciar.inference.selection_function import SelectionFunction

    run = shutil.copytree(detection_only_fit[0], tmp_path / "run")
    before = _snapshot(run)
    # leftovers of a fit killed earlier (SIGKILL: no cleanup ran)
    junk = [run / "fit" / ".chain_all_logistic_c.npy.k3j2.tmp",
            run / f".{C.SELECTION_FUNCTION_NAME}.x81.tmp", run / ".fit.new" / "fit" / "chain.npy"]
    for p in junk:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"\0" * 4096)

    def die(*a, **k):
        raise RuntimeError("killed while writing the file")

    monkeypatch.setattr(SelectionFunction, "to_bytes", staticmethod(die))
    with pytest.raises(RuntimeError, match="killed"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_fit(run, model="logistic", sampler=SamplerSettings(max_steps=100, seed=7),
                plots=False)   # other chains
    assert _snapshot(run) == before
    assert not any(p.exists() for p in junk)
    assert sorted(p.name for p in run.iterdir() if p.name.startswith(".fit")) == []


def test_interrupted_commit_is_completed_at_the_next_start(tmp_path):
    """Killed between swapping fit/ and the file: the next reader completes the swap."""
    from glaciar.pipeline.fitdir import COMMIT_NAME, OLD_NAME, hold_run

    run = tmp_path / "run"
    (run / "fit").mkdir(parents=True)
    (run / "fit" / "summary.json").write_text("old")
    (run / C.SELECTION_FUNCTION_NAME).write_text("old")
    # the state after step "fit/ -> .fit.old, new fit/ in place", before the file moved
    (run / OLD_NAME).mkdir()
    commit = run / COMMIT_NAME
    (commit / "fit").mkdir(parents=True)
    (commit / "fit" / "summary.json").write_text("new")
    (commit / C.SELECTION_FUNCTION_NAME).write_text("new")
    with hold_run(run, "report"):
        pass
    assert (run / "fit" / "summary.json").read_text() == "new"
    assert (run / C.SELECTION_FUNCTION_NAME).read_text() == "new"
    assert not (run / OLD_NAME).exists() and not commit.exists()


# ------------------------------------------------------------------------------
# Hostile cases of `glaciar fit`, `report` and `next` (issue 21, bullets 3 and 8).
#
# Each case: exit status 2, one line on stderr naming the run, nothing outside the
# run directory touched, nothing already in it changed (the lock file aside, which
# a refused command may create and never removes).  The runs are hand-made
# (:func:`make_run` above); no case samples.
# ------------------------------------------------------------------------------
FAST_CLI = ["--quiet", "--model", "logistic", "--max-steps", "50"]


def _tree_snapshot(root):
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
    before = _tree_snapshot(tmp_path)
    capsys.readouterr()
    try:
        args = [command[0], str(run)] + command[1:] + (FAST_CLI if command[0] == "fit" else [])
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
    assert _tree_snapshot(tmp_path) == before


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
    before = _tree_snapshot(outside)
    assert main(["fit", str(run)] + FAST_CLI) == 2
    assert _tree_snapshot(outside) == before
    assert not any((run / n).is_symlink() for n in (".fit.new", ".fit.commit", ".fit.old"))
    assert not (run / "fit").exists() and not (run / C.SELECTION_FUNCTION_NAME).exists()


# ------------------------------------------------------------------------------
# Depth-aware selection functions on surveys simulated through the engine.
#
# * Two fields of areas ~1 : 4 and depths 1 mag apart: the pooled, area-weighted
#   P = C*S matches the area-weighted binned fractions, and V_eff matches the
#   area-weighted brute-force integral of those fractions; the injection-weighted
#   pooling of the previous release (a fit without depth) fails the same checks.
# * One field with a deep corner (noise x0.3 over a quarter): the depth-aware fit
#   is adequate by the posterior-predictive check, and its completeness at each
#   depth matches the binned fractions of the sources at that depth.
# ------------------------------------------------------------------------------
def _fit(run_dir, out_name, **kw):
    """Fit a copy of the run's store (fixtures are shared) and return the SelectionFunction."""
    dst = run_dir.parent / out_name
    if not dst.exists():
        shutil.copytree(run_dir, dst, ignore=shutil.ignore_patterns("fit", "selection_function.fits"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")       # z-edge warnings: the grid is inside the window
            run_fit(dst, model="logistic", plots=False, max_draws=600, **kw)
    return SelectionFunction.read(dst / C.SELECTION_FUNCTION_NAME), dst


def _area_weighted_binned(df, areas, zs, ms, rng, n_draws=2000):
    """Area-weighted binned P and C per (z, m), with Beta(k+1, n-k+1) draws of P."""
    tot = sum(areas.values())
    p = np.zeros((len(zs), len(ms)))
    c = np.zeros_like(p)
    pd_ = np.zeros((n_draws, len(zs), len(ms)))
    for (f, z, m), d in df.groupby([C.COL_FIELD, C.COL_Z, C.COL_MAG]):
        i, j = np.searchsorted(zs, z), np.searchsorted(ms, m)
        n, k, kr = len(d), int(d[C.COL_SELECTED].sum()), int(d[C.COL_RECOVERED].sum())
        w = areas[f] / tot
        p[i, j] += w * k / n
        c[i, j] += w * kr / n
        pd_[:, i, j] += w * rng.beta(k + 1, n - k + 1, n_draws)
    return p, c, pd_


@pytest.fixture(scope="module")
def two_depth(two_depth_run):
    cfg, run = two_depth_run
    df = read_results(run)
    areas = read_manifest(run)["area_arcmin2"]
    return run, df, areas


def test_two_fields_area_weighted_selection_and_veff(two_depth):
    run, df, areas = two_depth
    assert 3.5 < areas["deep"] / areas["shallow"] < 4.5
    zs, ms = np.unique(df[C.COL_Z]), np.unique(df[C.COL_MAG])
    rng = np.random.default_rng(0)
    p_bin, c_bin, p_draws = _area_weighted_binned(df, areas, zs, ms, rng)
    dvdz = Planck18.differential_comoving_volume(zs).to_value(u.Mpc ** 3 / u.sr)
    sr = (sum(areas.values()) * u.arcmin ** 2).to_value(u.sr)
    # brute force: trapezoid over the simulated z of the area-weighted binned fractions
    v_bf = np.trapezoid(p_draws * dvdz[None, :, None], zs, axis=1) * sr       # (draws, n_m)
    c_mean = c_bin.mean(axis=0)
    mid = (c_mean >= 0.1) & (c_mean <= 0.9)
    assert mid.sum() >= 3

    results = {}
    for name, depth in (("depth_aware", "auto"), ("injection_weighted", "off")):
        sf, _ = _fit(run, f"fit_{name}", depth=depth)
        assert sf.model.depth_aware == (depth == "auto")
        P = sf.selection_probability(zs[:, None], ms[None, :])
        v = sf.effective_volume(ms[mid])
        med, lo, hi = (q.to_value(u.Mpc ** 3) for q in (v.median, v.lower, v.upper))
        bf_med = np.median(v_bf[:, mid], axis=0)
        # combined 68 % half-widths of the model's and the brute force's intervals
        bf_lo, bf_hi = np.quantile(v_bf[:, mid], [0.16, 0.84], axis=0)
        sig = np.hypot(0.5 * (hi - lo), 0.5 * (bf_hi - bf_lo))
        results[name] = (np.mean(np.abs(P - p_bin)), (med - bf_med) / sig, med / bf_med)
        print(f"{name}: mean |P - P_binned| = {results[name][0]:.3f}; V_eff / brute force at "
              f"m = {ms[mid]}: {np.round(med / bf_med, 3)}; (V - V_bf) / sigma = "
              f"{np.round(results[name][1], 2)}")
    dp, z_score, ratio = results["depth_aware"]
    assert dp <= 0.03
    # no bias: each within 2 combined sigma, and the mean offset within 1 sigma
    assert np.all(np.abs(z_score) <= 2.0) and abs(np.mean(z_score)) <= 1.0
    # the previous release's pooling (by injections) fails the same test by far
    dp_old, z_old, ratio_old = results["injection_weighted"]
    assert dp_old > dp and np.max(np.abs(z_old)) > 4.0 and np.min(ratio_old) < 0.8


def test_two_fields_per_field_volumes_add_up_to_the_survey(two_depth):
    run, df, areas = two_depth
    sf, _ = _fit(run, "fit_depth_aware", depth="auto")
    m = [25.5, 26.0, 26.5]
    parts = [sf.effective_volume(m, field=f).draws.value for f in ("shallow", "deep")]
    # equal up to the merging of depth bins into <= 12 nodes (per field vs survey): 3e-3
    np.testing.assert_allclose(parts[0] + parts[1], sf.effective_volume(m).draws.value, rtol=3e-3)
    assert sf.area_arcmin2("shallow") == pytest.approx(areas["shallow"], rel=1e-9)
    # the shallow field is ~1 mag shallower: its V_eff per area falls at brighter m
    per_area = [p.mean(axis=0) / areas[f] for p, f in zip(parts, ("shallow", "deep"))]
    assert per_area[0][-1] < 0.5 * per_area[1][-1]


def test_deep_corner_adequate_and_per_depth_completeness(deep_corner_run):
    cfg, run = deep_corner_run
    # Two redshifts leave S's high-z edge to its prior: its chain mixes slowly (tau ~ 500
    # steps for logit_s_max), and 50 tau need more than the default 20 000 steps.
    sf, dst = _fit(run, "fit_corner", depth="auto", sampler=SamplerSettings(max_steps=60000))
    summ = json.loads((dst / "fit" / "summary.json").read_text())["fits"]["all"]
    ppc = summ["ppc"]
    print(f"deep corner: {ppc['n_extreme']} of {ppc['n_cells']} PPC cells extreme "
          f"({ppc['fraction_extreme']:.1%}), converged {summ['converged']}")
    assert summ["converged"] and summ["adequate"]
    assert ppc["fraction_extreme"] <= 0.10
    # per-depth completeness: model mean over the sources of a depth group vs binned fraction
    df = read_results(dst)
    deep = df[C.COL_DEPTH] > np.median(df[C.COL_DEPTH]) + 0.6
    assert 0.15 < deep.mean() < 0.35                       # the quarter with noise x 0.3
    rows = []
    for group in (deep, ~deep):
        for (z, m), d in df[group].groupby([C.COL_Z, C.COL_MAG]):
            c = sf.completeness(d[C.COL_MAG_INPUT].to_numpy(), d[C.COL_Z].to_numpy(),
                                d[C.COL_DEPTH].to_numpy(), draws=True).mean(axis=1)
            n, k = len(d), int(d[C.COL_RECOVERED].sum())
            q = np.median(c)
            # two-sided binomial p value of the observed count under the model's completeness
            pval = min(1.0, 2 * min(stats.binom.cdf(k, n, q), stats.binom.sf(k - 1, n, q)))
            rows.append((bool(group is deep), z, m, n, k / n, q, pval))
    pvals = np.array([r[-1] for r in rows])
    # the model curve agrees with the binned fraction of each depth group in (almost) every
    # cell: at most what chance gives at the 1 % level (binomial 99 % quantile)
    allowed = stats.binom.isf(0.01, len(pvals), 0.01)
    assert np.sum(pvals < 0.01) <= allowed, [r for r in rows if r[-1] < 0.01]
    # and the deep corner's completeness is shifted faint by its extra depth (~1.3 mag)
    d50 = [sf.magnitude_at(0.5, 9.0).median[0]]
    shift = np.median(df.loc[deep, C.COL_DEPTH]) - np.median(df.loc[~deep, C.COL_DEPTH])
    c_deep = sf.completeness(27.0, 9.0, np.median(df.loc[deep, C.COL_DEPTH]))
    c_shallow = sf.completeness(27.0, 9.0, np.median(df.loc[~deep, C.COL_DEPTH]))
    assert shift == pytest.approx(1.31, abs=0.1) and c_deep > 0.8 > 0.2 > c_shallow and np.isfinite(d50[0])


def test_deep_corner_documented_reader_averages_depth_bins(deep_corner_run):
    """The stand-alone reader (every 0.05 mag bin) agrees with glaciar's <= 24 merged nodes."""
    import pathlib
    import re
    cfg, run = deep_corner_run
    sf, dst = _fit(run, "fit_corner", depth="auto", sampler=SamplerSettings(max_steps=60000))
    doc = pathlib.Path(__file__).parents[2] / "docs" / "selection-function-file.md"
    code = re.findall(r"```python\n(.*?)```", doc.read_text(), re.S)[1]
    ns = {}
    exec(code.replace('"selection_function.fits"', repr(str(dst / C.SELECTION_FUNCTION_NAME))), ns)
    z, m = np.array([8.5, 9.0, 9.7]), np.array([26.0, 26.8, 27.5])
    got = sf.selection_probability(z, m, draws=True)
    np.testing.assert_allclose(ns["P"](z, m), got, atol=2e-3)
