"""Interlopers in the luminosity-function fit: a background in every bin's Poisson mean."""
import numpy as np
import pandas as pd
import pytest
from scipy.stats import poisson

from analytic_sf import TRUE, lf_sf, mock_candidates
from glaciar import constants as C
from glaciar.inference.contamination import fit_contamination
from glaciar.inference.sampling import SamplerSettings
from glaciar.lf import LFPosterior, fit_lf
from glaciar.lf.models import get_model, schechter
from glaciar.lf.predict import interloper_background


def test_background_enters_the_poisson_mean_and_its_gradient():
    rng = np.random.default_rng(0)
    K = rng.uniform(0.0, 50.0, (6, 3, 5))                 # (cells, draws, bins)
    bg = rng.uniform(0.5, 3.0, (3, 5))
    n = np.array([3, 0, 7, 1, 12])
    M = np.linspace(-22, -19.5, 6)
    post = LFPosterior(get_model("schechter"), K, n, {}, M=M, background=bg)
    th = np.array([[-3.0, -21.0, -1.8]])
    lam = np.einsum("m,mdk->dk", schechter(M, *th[0]), K) + bg
    np.testing.assert_allclose(post.expected(th)[0], lam, rtol=1e-12)
    per = poisson.logpmf(n, lam).sum(axis=-1)
    from scipy.special import gammaln
    np.testing.assert_allclose(post.log_like_draws(th)[0], per + gammaln(n + 1).sum(), rtol=1e-12)
    g = post.grad_log_like(th[0])
    h = 1e-5
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        num = (post.log_like(th + e) - post.log_like(th - e))[0] / (2 * h)
        assert g[i] == pytest.approx(num, rel=1e-4, abs=1e-6)
    one = post.draw(1)
    np.testing.assert_allclose(one.expected(th)[0, 0], lam[1], rtol=1e-12)


def test_fit_recovers_the_lf_under_a_known_interloper_population():
    window = np.round(np.arange(25.0, 28.01, 0.2), 6)
    sf = lf_sf(n_draws=1)
    # interlopers passing 5-20 % at 25-27 mag, ~3e2 of them over 800 arcmin^2
    edges = np.arange(24.0, 28.51, 0.5)
    cells = np.repeat(0.5 * (edges[:-1] + edges[1:]), 400)
    rng = np.random.default_rng(5)
    m_in = cells + rng.uniform(-0.25, 0.25, cells.size)
    frac = 0.05 + 0.15 * np.exp(-0.5 * ((m_in - 26.0) / 0.7) ** 2)
    rows = pd.DataFrame({C.COL_MAG: cells, C.COL_MAG_INPUT: m_in, "mag_auto_f160w": m_in,
                         C.COL_SELECTED: rng.random(cells.size) < frac})
    counts = (0.0, 0.2, 26.0)
    w = 10 ** (counts[0] + counts[1] * (m_in - counts[2])) * 0.5 / 400
    lf = mock_candidates(sf, lambda M: schechter(M, **TRUE), window, seed=21)   # LF alone
    sf.interlopers = fit_contamination(rows, w, edges, obs_column="mag_auto_f160w",
                                       counts=counts)
    bg = interloper_background([sf], window, 1)[0]
    n_int = rng.poisson(bg)
    extra = np.concatenate([rng.uniform(a, b, k) for a, b, k in
                            zip(window[:-1], window[1:], n_int)])
    # phi* alone free (the shape fixed at the truth): a quick fit of what the interlopers bias
    res = fit_lf(sf, np.concatenate([lf, extra]), m_obs_edges=window,
                 fix={"M_star": TRUE["M_star"], "alpha": TRUE["alpha"]},
                 sampler=SamplerSettings(seed=3, max_steps=2000))
    np.testing.assert_allclose(res.counts["n_interlopers"], bg, rtol=1e-12)    # one draw
    assert res.counts["n_interlopers"].sum() > 100
    p = res.parameters["log_phi_star"]
    sd = 0.5 * (p["hi68"] - p["lo68"])
    assert abs(p["median"] - TRUE["log_phi_star"]) < 2.5 * sd, p
    # without the interlopers phi* would absorb them: the same data, ~10 % more phi*
    share = bg.sum() / (len(lf) + bg.sum())
    assert share > 0.05 and np.log10(1 / (1 - share)) > 2.5 * sd
