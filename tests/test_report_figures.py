"""The report's and the fit's figures, checked on the Figure objects (not on pixels).

* glaciar never changes the user's matplotlib backend nor touches pyplot (a notebook's
  inline figures keep working after a glaciar plot);
* legends name simulated values only; V_eff is on a log axis; a cell without data has
  no point; figures are drawn at a readable size.

All data are synthetic and tiny (no run, no fit): the file costs ~3 s.
"""
import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import glaciar
from glaciar import plots, report

#: simulated values of the synthetic run: 6.5 is not a row of the file's uniform grid
#: linspace(6, 7.3, 24) (step 0.0565), so a legend built from the grid rows says "z = 6.51"
SIM_Z = (6.0, 6.5, 7.3)
SIM_M = (26.0, 27.0, 28.5)


def _texts(fig):
    from matplotlib.text import Text

    return [t for t in fig.findobj(Text) if t.get_text().strip() and t.get_visible()]


def _legend_labels(ax):
    leg = ax.get_legend()
    return [t.get_text() for t in leg.get_texts()] if leg is not None else []


def _errorbar_x(ax):
    """x of every error-bar point drawn on ``ax``."""
    from matplotlib.container import ErrorbarContainer

    return np.concatenate([c.lines[0].get_xdata() for c in ax.containers
                           if isinstance(c, ErrorbarContainer)] or [np.empty(0)])


def _report_data():
    """What load_report_data returns, for a fitted run of SIM_Z × SIM_M (one field)."""
    zg, mg = np.linspace(6.0, 7.3, 24), np.linspace(25.5, 29.0, 36)
    zz, mm = np.meshgrid(zg, mg, indexing="ij")
    c = 1 / (1 + np.exp((mm - 27.5 + 0.1 * (zz - 6)) / 0.3))
    s = np.clip(1.2 - 0.1 * (zz - 6) - 0.05 * (mm - 26), 0, 1)
    shift = np.array([0.0, -0.1, 0.1, -0.2, 0.2])[:, None, None]   # planes 0.5, 16, 84, 2.5, 97.5 %
    q = lambda g: np.clip(g[None] + shift, 0, 1)                     # noqa: E731
    rows = []
    for z in SIM_Z:
        for m in SIM_M:
            n = 40
            k = 0 if m == 28.5 else int(n * (1 / (1 + np.exp((m - 27.5) / 0.3))))
            rows.append({"z": z, "mag": m, "n_input": n, "n_recovered": k, "n_selected": k // 2})
    summary = pd.DataFrame(rows)
    fit = {"field": "all", "draws_header": {"SELFIT": True},
           "C_GRID": {"q": q(c), "z": zg, "m": mg}, "SR_GRID": {"q": q(s), "z": zg, "m": mg},
           "P_GRID": {"q": q(c * s), "z": zg, "m": mg}}
    manifest = {"z_values": list(SIM_Z), "mag_values": list(SIM_M), "fields": ["f1"],
                "magnitude_type": "apparent", "detection_band": "f160w"}
    return {"manifest": manifest, "summaries": {"all": summary, "f1": summary},
            "selection_function": {"fits": [fit], "primary": {}}, "fit_summary": None,
            "run_dir": "/tmp/run"}


@pytest.fixture(scope="module")
def curve_figures():
    """The C(m) and S(z) figures of the report's curves section (captured Figure objects)."""
    made = []
    real = plots.plot_quantile_curves

    def capture(*a, **k):
        made.append(real(*a, **k))
        return made[-1]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(plots, "plot_quantile_curves", capture)
        # the figures are read as objects: no PNG rendering (a 1×1 PNG header for the page)
        mp.setattr(plots, "png_bytes", lambda fig, dpi=None: bytes(16) + bytes([0, 0, 0, 1] * 2))
        report._curves_section(_report_data())
    assert len(made) == 2
    return made


def test_report_c_and_s_legends_list_only_simulated_values(curve_figures):
    c_fig, s_fig = curve_figures
    assert _legend_labels(c_fig.axes[0]) == ["z = 6", "z = 6.5", "z = 7.3"]
    assert _legend_labels(s_fig.axes[0]) == ["m = 26", "m = 27", "m = 28.5"]


def test_report_curves_are_the_stored_quantiles_at_the_simulated_value(curve_figures):
    """z = 6 is a grid row: that row of C_GRID's median plane; z = 6.5 lies between two rows:
    linear in z between them (before: the row nearest 6.5, z = 6.5087)."""
    g = _report_data()["selection_function"]["fits"][0]["C_GRID"]
    line = {ln.get_label(): ln for ln in curve_figures[0].axes[0].get_lines()}
    np.testing.assert_array_equal(line["z = 6"].get_ydata(), g["q"][0, 0])
    want = [np.interp(6.5, g["z"], g["q"][0, :, j]) for j in range(g["m"].size)]
    np.testing.assert_allclose(line["z = 6.5"].get_ydata(), want, rtol=0, atol=1e-12)


def test_report_draws_no_point_for_a_cell_without_recovered_sources(curve_figures):
    c_fig, s_fig = curve_figures
    # C: every cell has injected sources, so 3 magnitudes × 3 redshifts of points
    assert np.sort(_errorbar_x(c_fig.axes[0])).tolist() == sorted(list(SIM_M) * 3)
    # S at m = 28.5: nothing recovered, so no S point (not a 0.50 ± 0.34 from the prior)
    assert _errorbar_x(s_fig.axes[0]).size == 2 * len(SIM_Z)
    ys = np.concatenate([c.lines[0].get_ydata() for c in s_fig.axes[0].containers])
    assert not np.any(np.isclose(ys, 0.5))


def test_effective_volume_is_on_a_log_axis_showing_the_faint_end():
    m = np.linspace(24, 30, 25)
    v = 1e5 / (1 + np.exp((m - 28) / 0.25))        # falls by ~4 decades to m = 30
    fig = plots.plot_effective_volume(m, v, 0.8 * v, 1.2 * v, mag_label="m", title="V")
    ax = fig.axes[0]
    assert ax.get_yscale() == "log"
    lo, hi = ax.get_ylim()
    assert 0 < lo <= v[m <= 29.5].min() and hi >= 1.2 * v.max()


def test_effective_volume_leaves_out_zero_volume_instead_of_clipping():
    m = np.array([26.0, 27.0, 28.0, 29.0])
    v = np.array([1e5, 1e4, 1e2, 0.0])
    ax = plots.plot_effective_volume(m, v, v, v, mag_label="m").axes[0]
    y = ax.get_lines()[0].get_ydata()
    assert np.isnan(y[-1]) and np.all(y[:-1] == v[:-1])


def _report_figures():
    labels = {0: ("n_status_0", "recovered"), -3: ("n_status_m3", "not detected")}
    summ = pd.DataFrame({"mag": [26.0, 27.0], "n_input": [10, 10], "n_status_0": [9, 3],
                         "n_status_m3": [1, 7]})
    ppc = pd.DataFrame({k: [0.5, 0.6] for k in (
        "c_binned", "c_binned_q16", "c_binned_q84", "c_model", "c_model_q16", "c_model_q84",
        "s_binned", "s_binned_q16", "s_binned_q84", "s_model", "s_model_q16", "s_model_q84")})
    ppc["n"], ppc["k_rec"], ppc["extreme"] = [10, 10], [5, 0], [False, True]
    grid = np.full((3, 4), 0.5)
    m = np.linspace(25, 28, 7)
    return {
        "status": plots.plot_status_fractions(summ, labels, "m"),
        "curves": plots.plot_quantile_curves(m, [("z = 7", np.tile(np.linspace(1, 0, 7), (5, 1)))],
                                             xlabel="m", ylabel="C", title="C"),
        "grid": plots.plot_grid_map(np.arange(4.0), np.arange(3.0), grid, xlabel="m", ylabel="z",
                                    label="P", title="P"),
        "ppc": plots.plot_ppc(ppc),
        "depth": plots.plot_depth_completeness(np.arange(4.0), np.array([27.0, 27.25, 27.5]), 0.25,
                                               grid, grid, mag_label="m"),
        "area": plots.plot_area_by_depth({"f1": ([27.0, 27.05, 27.1], [1.0, 2.0])}),
        "veff": plots.plot_effective_volume(m, 10 ** (5 - m / 10), 10 ** (4.9 - m / 10),
                                            10 ** (5.1 - m / 10), mag_label="m", title="V"),
    }


def test_report_figures_are_drawn_at_a_readable_size():
    """Shown at one PNG pixel per CSS pixel: >= 800 px wide and no text under 9 pt (12.5 px)."""
    for name, fig in _report_figures().items():
        png = plots.png_bytes(fig)
        width = int.from_bytes(png[16:20], "big")
        assert width >= 800, (name, width)
        small = [(t.get_text(), t.get_fontsize()) for t in _texts(fig) if t.get_fontsize() < 9]
        assert small == [], (name, small)


def _toy_sf(with_ppc: bool):
    from glaciar.inference import SelectionFunction, SurfaceModel

    zg, mg = np.linspace(6.0, 7.3, 27), np.linspace(25.5, 29.0, 36)
    mdl = SurfaceModel.for_data(np.array(SIM_Z), np.array(SIM_M))
    th = mdl.sample_prior(8, np.random.default_rng(0))
    ppc = None
    if with_ppc:
        z, m = (a.ravel() for a in np.meshgrid(SIM_Z, SIM_M, indexing="ij"))
        ppc = np.zeros(z.size, dtype=[("z", float), ("mag", float), ("n", int), ("k_rec", int),
                                      ("k_sel", int), ("extreme", bool)])
        ppc["z"], ppc["mag"], ppc["n"] = z, m, 20
        ppc["k_rec"] = np.where(m < 28, 15, 0)
        ppc["k_sel"] = ppc["k_rec"] // 2
    return SelectionFunction(mdl, th, zg, mg, field="all", ppc=ppc,
                             domain={"z": (6.0, 7.3), "mag": (25.5, 29.0)})


@pytest.mark.parametrize("with_ppc", [True, False])
def test_fit_figure_legends_list_only_simulated_values(with_ppc):
    from glaciar.pipeline.figures import completeness_figure, selection_figure

    sf = _toy_sf(with_ppc)
    zs = SIM_Z if with_ppc else (6.0, 7.3)         # without a PPC table: the simulated range's ends
    assert _legend_labels(completeness_figure(sf).axes[0]) == [f"z = {z:g}" for z in zs]
    ms = SIM_M if with_ppc else (25.5, 29.0)
    assert _legend_labels(selection_figure(sf).axes[0]) == [f"m = {m:g}" for m in ms]


_NOTEBOOK_USER = """
    import sys, tempfile
    import matplotlib
    matplotlib.use("svg")                        # the user's choice (a notebook: inline)
    import numpy as np, pandas as pd
    from glaciar.plots import plot_summary_maps
    from glaciar.pipeline.figures import completeness_figure, selection_figure
    sys.path.insert(0, {tests!r})
    from test_report_figures import _report_figures, _toy_sf
    summ = pd.DataFrame({{"z": [7.0, 7.0], "mag": [26.0, 27.0], "completeness": [0.9, 0.2],
                         "selection_total": [0.5, 0.1], "selection": [0.55, 0.5]}})
    plot_summary_maps(summ, tempfile.mkdtemp(), "f1")
    _report_figures()
    sf = _toy_sf(True)
    completeness_figure(sf), selection_figure(sf)
    print(matplotlib.get_backend(), "matplotlib.pyplot" in sys.modules)
"""


def test_plotting_leaves_the_users_backend_and_pyplot_alone(tmp_path):
    """Before: plot_summary_maps and the fit figures called matplotlib.use("Agg")."""
    code = textwrap.dedent(_NOTEBOOK_USER.format(tests=str(Path(__file__).parent)))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["svg", "False"], out.stdout


def test_no_glaciar_module_selects_a_backend_or_imports_pyplot():
    """Also covers figures no test above draws (``lf_figure``)."""
    bad = []
    for path in Path(glaciar.__file__).parent.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        if "matplotlib" not in text and "pyplot" not in text:
            continue
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                    and node.func.attr == "use" and getattr(node.func.value, "id", "") == "matplotlib":
                bad.append((path.name, node.lineno, "matplotlib.use"))
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [f"{node.module}.{a.name}" for a in node.names]
                     if isinstance(node, ast.ImportFrom) and node.module else [])
            bad += [(path.name, node.lineno, n) for n in names if "pyplot" in n]
    assert bad == []
