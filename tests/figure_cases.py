"""Figures and selection functions the plotting tests draw: the report's figures on small
tables, and a toy selection function fitted to a synthetic run of SIM_Z x SIM_M.

Also imported by a subprocess in tests/test_report.py (a notebook user's session), so this
module imports neither pyplot nor anything that would.
"""
import numpy as np
import pandas as pd

from glaciar import plots


#: simulated values of the synthetic run: 6.5 is not a row of the file's uniform grid
#: linspace(6, 7.3, 24) (step 0.0565), so a legend built from the grid rows says "z = 6.51"
SIM_Z = (6.0, 6.5, 7.3)
SIM_M = (26.0, 27.0, 28.5)


def legend_labels(ax):
    """The texts of ``ax``'s legend ([] without one)."""
    leg = ax.get_legend()
    return [t.get_text() for t in leg.get_texts()] if leg is not None else []


def report_figures():
    """Every kind of figure the report draws, on tables of two or three rows: {name: Figure}."""
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






def toy_sf(with_ppc: bool):
    """A SelectionFunction of prior draws on the box of SIM_Z x SIM_M (with a PPC table or not)."""
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
