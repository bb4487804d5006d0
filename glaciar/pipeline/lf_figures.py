"""Figure of a fitted luminosity function: the data against the model, in m_obs and in M_UV.

:func:`lf_figure` takes a :class:`glaciar.lf.LFResult` and returns a
:class:`matplotlib.figure.Figure` built without pyplot (no backend is selected);
:func:`glaciar.pipeline.lf.run_lf` saves it (:func:`glaciar.plots.save_png`) as
``RUN_DIR/lf/lf.png``.
"""
from __future__ import annotations

import numpy as np

from ..plots import LEGEND_PT, TITLE_PT, new_figure
from .figures import FIGURE_DPI

__all__ = ["lf_figure", "FIGURE_DPI"]


def lf_figure(res):
    """Two panels: observed vs expected counts per m_obs bin, and phi(M_UV).

    Left: the candidates per measured-magnitude bin (Poisson 1-sigma bars) and the
    posterior-predictive expected counts (median, 68 % band).  Right: the model's
    phi(M_UV) (posterior median, 68 % band) and the binned phi with its errors
    (:attr:`LFResult.binned_phi`), on a logarithmic scale.

    Parameters
    ----------
    res : glaciar.lf.LFResult

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = new_figure((12, 5))
    ax0, ax1 = fig.subplots(1, 2)
    c = res.counts
    mc = 0.5 * (c["m_lo"] + c["m_hi"])
    edges = np.append(c["m_lo"], c["m_hi"][-1])
    ax0.fill_between(edges, np.append(c["n_exp_lo68"], c["n_exp_lo68"][-1]),
                     np.append(c["n_exp_hi68"], c["n_exp_hi68"][-1]), step="post",
                     color="C0", alpha=0.3, lw=0)
    ax0.step(edges, np.append(c["n_exp"], c["n_exp"][-1]), where="post", color="C0",
             label=f"expected ({res.model})")
    n = c["n_obs"].astype(float)
    from ..lf.fit import gehrels_limits
    glo, ghi = gehrels_limits(n)
    ax0.errorbar(mc, n, yerr=[n - glo, ghi - n], fmt="o", ms=3, color="k", lw=0.8,
                 label=f"observed ({res.n_candidates})")
    ax0.set_xlabel("measured magnitude m_obs [AB mag]")
    ax0.set_ylabel("candidates per bin")
    ax0.set_yscale("symlog", linthresh=1.0)
    ax0.set_ylim(bottom=0)
    ax0.legend(fontsize=LEGEND_PT)

    b = res.binned_phi
    M = np.linspace(res.muv_range[0], res.muv_range[1], 300)
    pick = res.samples[np.unique(np.linspace(0, len(res.samples) - 1, 400).round().astype(int))]
    from ..lf.models import get_model
    mdl = get_model(res.model, edges=b["edges"] if res.model == "stepwise" else None)
    phi = mdl.phi(M, pick)
    q = np.quantile(phi, [0.5, 0.16, 0.84], axis=0)
    ax1.fill_between(M, q[1], q[2], color="C1", alpha=0.3, lw=0)
    ax1.plot(M, q[0], color="C1", label=f"{res.model} (median, 68 %)")
    # Bins where the model expects at least half a candidate: elsewhere the data say nothing.
    ok = np.isfinite(b["phi"]) & (b["phi"] > 0) & (b["n_exp"] >= 0.5)
    lo = np.clip(b["phi"] - b["phi_lo68"], 0, None)
    hi = np.clip(b["phi_hi68"] - b["phi"], 0, None)
    ax1.errorbar(b["M"][ok], b["phi"][ok], yerr=[lo[ok], hi[ok]],
                 xerr=0.5 * (b["M_hi"] - b["M_lo"])[ok], fmt="o", ms=3, color="k", lw=0.8,
                 label="binned")
    top = np.nanmax(q[2]) if np.isfinite(q[2]).any() else 1.0
    ax1.set_yscale("log")
    ax1.set_ylim(max(top * 1e-6, 1e-12), top * 3)
    ax1.set_xlabel("M_UV [AB mag]")
    ax1.set_ylabel("phi [Mpc^-3 mag^-1]")
    ax1.set_title(f"z = {res.z_range[0]:.2f}-{res.z_range[1]:.2f}", fontsize=TITLE_PT)
    ax1.legend(fontsize=LEGEND_PT)
    fig.tight_layout()
    return fig
