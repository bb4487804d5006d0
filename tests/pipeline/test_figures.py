"""Figures of a fitted selection function (glaciar.pipeline.figures), checked on the Figure objects."""
import numpy as np
import pytest


#: simulated values of the synthetic run: 6.5 is not a row of the file's uniform grid
#: linspace(6, 7.3, 24) (step 0.0565), so a legend built from the grid rows says "z = 6.51"
SIM_Z = (6.0, 6.5, 7.3)
SIM_M = (26.0, 27.0, 28.5)


def _legend_labels(ax):
    leg = ax.get_legend()
    return [t.get_text() for t in leg.get_texts()] if leg is not None else []


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
