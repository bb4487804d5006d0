"""Figures of a fitted selection function (glaciar.pipeline.figures), checked on the Figure objects."""
import pytest

from figure_cases import SIM_M, SIM_Z, legend_labels, toy_sf


@pytest.mark.parametrize("with_ppc", [True, False])
def test_fit_figure_legends_list_only_simulated_values(with_ppc):
    from glaciar.pipeline.figures import completeness_figure, selection_figure

    sf = toy_sf(with_ppc)
    zs = SIM_Z if with_ppc else (6.0, 7.3)         # without a PPC table: the simulated range's ends
    assert legend_labels(completeness_figure(sf).axes[0]) == [f"z = {z:g}" for z in zs]
    ms = SIM_M if with_ppc else (25.5, 29.0)
    assert legend_labels(selection_figure(sf).axes[0]) == [f"m = {m:g}" for m in ms]
