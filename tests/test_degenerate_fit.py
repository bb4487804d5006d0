"""Issue 21, bullets 3, 4 and 8: degenerate outcomes are not fits, honest fit output,
one consistent reader/writer of a run's fit.

The runs here are hand-made (a known logistic completeness, one task file per z),
a few hundred sources, fitted with one model and short chains: the fixture fit
costs ~5 s and is shared by the module.
"""
import json
import time
import warnings

import numpy as np
import pandas as pd
import pytest

from glaciar import constants as C
from glaciar.inference import SelectionFunction, SurfaceModel
from glaciar.inference.sampling import ConvergenceWarning, SamplerSettings
from glaciar.pipeline import run_fit
from glaciar.store import write_task_table

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
