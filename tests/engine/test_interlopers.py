"""The interloper population's draws and weights (glaciar.engine.interlopers), and its tasks."""
import numpy as np
import pytest

from glaciar.config.interlopers import InterloperConfig
from glaciar.engine.interlopers import InterloperModel, count_weights, draw_interlopers
from glaciar.engine.task import TaskSpec
from glaciar.galaxy.filters import get_filter
from glaciar.galaxy.population import SourceModel, get_cosmology

BANDS = [get_filter(b) for b in ("wfc3_uvis_f606w", "wfc3_ir_f098m", "wfc3_ir_f125w",
                                 "wfc3_ir_f160w")]
SECTION = {"z_range": [1.0, 3.0], "z_step": 1.0, "mag_range": [25.0, 27.0], "mag_step": 0.5,
           "n_per_task": 2000, "dusty": {"weight": 0.1, "beta": [-2.0, -1.0], "a_v": [1.0, 3.0]},
           "balmer": {"weight": 0.3, "d4000": [1.5, 2.0]},
           "counts": {"a": 1.5, "b": 0.3, "m0": 26.0},
           "r_eff_kpc_z6": 1.2, "size_evolution": -1.0, "r_eff_scatter_dex": 0.25}


def model(**changes):
    return InterloperModel.from_config(InterloperConfig.model_validate({**SECTION, **changes}),
                                       SourceModel())


def draws(z=2.0, mag=25.75, seed=1, **changes):
    return draw_interlopers(np.random.default_rng(seed), model(**changes), z, mag, BANDS, 3,
                            get_cosmology("Planck18"), lambda r: (r / 0.06, r))


def test_draws_follow_the_configured_population():
    d = draws()
    x = d["extra"]
    n = 2000
    dusty = x["interloper_family"] == "dusty"
    # family weights 0.1 : 0.3 -> 25 % dusty (binomial sd 1 %)
    assert abs(dusty.mean() - 0.25) < 4 * np.sqrt(0.25 * 0.75 / n)
    m = d["mag_in"][:, 3]
    assert m.min() >= 25.5 and m.max() < 26.0                     # uniform in the cell
    assert abs(m.mean() - 25.75) < 4 * 0.5 / np.sqrt(12 * n)
    assert np.all((x["a_v"][dusty] >= 1) & (x["a_v"][dusty] <= 3))
    assert np.all((x["d4000"][~dusty] >= 1.5) & (x["d4000"][~dusty] <= 2.0))
    assert np.all(np.isnan(x["d4000"][dusty])) and np.all(np.isnan(d["M_uv"]))
    assert np.all((d["beta"][dusty] >= -2) & (d["beta"][dusty] <= -1))
    # r_e law of source: with the section's parameters: 1.2 ((1 + 2) / 7)^-1 kpc, 0.25 dex
    logr = np.log10(d["r_eff_kpc"])
    assert np.median(logr) == pytest.approx(np.log10(1.2 * 7 / 3), abs=0.02)
    assert np.std(logr) == pytest.approx(0.25, rel=0.06)
    # Balmer-break interlopers at z = 2 are red in F606W - F160W, far more than dusty ones
    # of low A_V would be.
    assert np.median(d["mag_in"][~dusty, 0] - m[~dusty]) > 1.5


def test_count_weights_integrate_the_number_counts():
    mdl = model()
    rng = np.random.default_rng(3)
    cells = np.repeat(np.asarray(mdl.mag_cells), 5000)
    m_in = cells + (rng.random(cells.size) - 0.5) * 0.5
    w = count_weights(m_in, cells, mdl)
    a, b, m0 = 1.5 + np.log10(0.4), 0.3, 26.0        # the families: 40 % of the counts
    k = b * np.log(10)
    for c in mdl.mag_cells:
        lo, hi = c - 0.25, c + 0.25
        exact = 10 ** a * (np.exp(k * (hi - m0)) - np.exp(k * (lo - m0))) / k
        got = w[cells == c].sum()
        assert got == pytest.approx(exact, rel=0.01)
        assert mdl.integral(lo, hi) == pytest.approx(exact, rel=1e-12)


def test_interloper_streams_are_their_own():
    hz = TaskSpec("f", 0, 0, 0, 0, 2.0, 26.0)
    il = TaskSpec("f", 0, 0, 0, 0, 2.0, 26.0, population="interloper-abc")
    assert len(hz.spawn_key()) == 4                      # the target's keys as before
    assert il.spawn_key()[:4] == hz.spawn_key() and len(il.spawn_key()) == 5
