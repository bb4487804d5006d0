"""The interlopers' passing fraction: its estimate and interval, the file's CONTAM, the counts."""
import numpy as np
import pandas as pd
import pytest

from analytic_sf import lf_sf
from glaciar import constants as C
from glaciar.inference import SelectionFunction
from glaciar.inference.contamination import fit_contamination
from glaciar.inference.counts import Quadrature

OBS = "mag_auto_f160w"
COUNTS = (1.8, 0.25, 26.0)
EDGES = np.arange(24.0, 28.01, 0.5)


def density(m):
    a, b, m0 = COUNTS
    return 10.0 ** (a + b * (m - m0))


def p_true(m):
    """A passing probability that rises and falls with magnitude."""
    return 0.35 * np.exp(-0.5 * ((m - 26.2) / 0.8) ** 2)


def synthetic(seed, n_per_cell=150, scatter=0.0):
    """Rows as a run's interloper tasks give them: uniform in each cell, weighted to the counts."""
    rng = np.random.default_rng(seed)
    cells = np.repeat(0.5 * (EDGES[:-1] + EDGES[1:]), n_per_cell)
    m_in = cells + rng.uniform(-0.25, 0.25, cells.size)
    rows = pd.DataFrame({C.COL_MAG: cells, C.COL_MAG_INPUT: m_in,
                         OBS: m_in + scatter * rng.standard_normal(cells.size),
                         C.COL_SELECTED: rng.random(cells.size) < p_true(m_in)})
    w = density(m_in) * 0.5 / n_per_cell
    return rows, w


def test_estimate_is_the_weighted_fraction_per_measured_magnitude():
    rows, w = synthetic(1, scatter=0.2)
    c = fit_contamination(rows, w, EDGES, obs_column=OBS, counts=COUNTS)
    m_in, m_obs = rows[C.COL_MAG_INPUT].to_numpy(), rows[OBS].to_numpy()
    sel = rows[C.COL_SELECTED].to_numpy()
    for k in range(len(EDGES) - 1):
        lo, hi = EDGES[k], EDGES[k + 1]
        num = w[sel & (m_obs >= lo) & (m_obs < hi)].sum()
        den = w[(m_in >= lo) & (m_in < hi)].sum()
        assert c.estimate[k] == pytest.approx(num / den, rel=1e-12)
        assert c.n_selected[k] == np.sum(sel & (m_obs >= lo) & (m_obs < hi))
    assert np.all(c.lower <= c.fraction) and np.all(c.fraction <= c.upper)
    # the step function: the bin's value inside, 0 where nothing was injected
    assert c.fraction_at(26.3) == c.fraction[4] and c.fraction_at([23.0, 29.0]).tolist() == [0, 0]


def test_intervals_cover_the_truth_68_percent_of_the_time():
    # Truth of each bin: ∫ n p dm / ∫ n dm (measured = true magnitude here).
    fine = np.linspace(EDGES[0], EDGES[-1], 8001)
    truth = np.array([np.trapezoid((density(fine) * p_true(fine))[(fine >= lo) & (fine <= hi)],
                                   fine[(fine >= lo) & (fine <= hi)])
                      / np.trapezoid(density(fine)[(fine >= lo) & (fine <= hi)],
                                     fine[(fine >= lo) & (fine <= hi)])
                      for lo, hi in zip(EDGES[:-1], EDGES[1:])])
    inside = []
    for seed in range(30):
        rows, w = synthetic(100 + seed, n_per_cell=60)
        c = fit_contamination(rows, w, EDGES, obs_column=OBS, counts=COUNTS, seed=seed)
        inside.append((c.lower <= truth) & (truth <= c.upper))
    cover = np.mean(inside)                     # 240 intervals: sd of the coverage ~ 0.03
    assert 0.58 < cover < 0.80, cover


def test_a_bin_without_selected_interlopers_gets_an_upper_limit():
    rows, w = synthetic(2)
    rows[C.COL_SELECTED] = rows[C.COL_SELECTED] & (rows[C.COL_MAG_INPUT] > 25.0)
    c = fit_contamination(rows, w, EDGES, obs_column=OBS, counts=COUNTS)
    assert c.estimate[0] == 0 and c.lower[0] < 1e-3 and 0 < c.upper[0] < 0.03


@pytest.fixture(scope="module")
def sf_with():
    rows, w = synthetic(3, scatter=0.15)
    sf = lf_sf()
    sf.interlopers = fit_contamination(rows, w, EDGES, obs_column=OBS, counts=COUNTS,
                                       z_range=(1.0, 6.0), family_column=None)
    return sf


def test_contam_extension_round_trips_and_old_files_read(sf_with):
    back = SelectionFunction.from_bytes(SelectionFunction.to_bytes([sf_with]))["all"]
    a, b = sf_with.interlopers, back.interlopers
    for name in ("m_edges", "fraction", "lower", "upper", "estimate", "draws", "n_injected",
                 "n_selected", "n_eff"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert b.counts == COUNTS and b.z_range == (1.0, 6.0)
    np.testing.assert_array_equal(back.contamination([24.2, 26.1]), a.fraction_at([24.2, 26.1]))
    # a file without interlopers: no CONTAM, the API says so in one line
    old = SelectionFunction.from_bytes(SelectionFunction.to_bytes([lf_sf()]))["all"]
    assert old.interlopers is None
    with pytest.raises(ValueError, match="no contamination"):
        old.contamination(26.0)


def test_expected_counts_add_the_expected_interlopers(sf_with):
    E = np.array([24.6, 25.4, 26.0, 26.9, 27.5])
    phi = lambda M, z: 1e-4 + 0 * M          # noqa: E731
    quad = Quadrature(n_z=9, n_beta=3, dM=0.1)
    plain = sf_with.expected_counts(phi, E, draws=False, warn=False, interlopers=False,
                                    quadrature=quad)
    both = sf_with.expected_counts(phi, E, draws=False, warn=False, quadrature=quad)
    # area x ∫_bin n(m) f(m) dm per contamination draw, f the step function of the bins
    c = sf_with.interlopers
    fine = np.linspace(E[0], E[-1], 200001)
    k = np.clip(np.searchsorted(c.m_edges, fine, side="right") - 1, 0, len(c.fraction) - 1)
    per_draw = []
    for f in c.draws:
        y = density(fine) * f[k]
        per_draw.append([np.trapezoid(y[(fine >= lo) & (fine <= hi)],
                                      fine[(fine >= lo) & (fine <= hi)])
                         for lo, hi in zip(E[:-1], E[1:])])
    want = 800.0 * np.median(per_draw, axis=0)
    np.testing.assert_allclose(both.interlopers, want, rtol=2e-3)
    np.testing.assert_allclose(both.median - plain.median, both.interlopers, rtol=1e-12)
    assert not hasattr(plain, "interlopers")
