"""Figures of a fitted selection function: C and S with credible bands over binned points.

Each function takes a :class:`~glaciar.inference.SelectionFunction` and
returns a :class:`matplotlib.figure.Figure` built without pyplot (no backend is
selected, so a user's notebook backend is left alone);
:func:`glaciar.pipeline.fit.run_fit` saves them (:func:`glaciar.plots.save_png`)
under ``RUN_DIR/fit/``.  Legends name only simulated redshifts and magnitudes:
those of the file's PPC table (the simulated cells), else the ends of the
simulated range.
"""
from __future__ import annotations

import numpy as np

from ..plots import LEGEND_PT, TITLE_PT, new_figure

__all__ = ["completeness_figure", "selection_figure", "FIGURE_DPI"]

FIGURE_DPI = 110    #: resolution of the saved PNGs [dots per inch]


def _credible_band(ax, x, draws, color, label):
    """Median line with 68 % and 95 % bands of posterior ``draws`` (shape (n_draws, len(x)))."""
    q = np.quantile(draws, [0.5, 0.16, 0.84, 0.025, 0.975], axis=0)
    ax.fill_between(x, q[3], q[4], color=color, alpha=0.15, lw=0)
    ax.fill_between(x, q[1], q[2], color=color, alpha=0.35, lw=0)
    ax.plot(x, q[0], color=color, label=label)


def _spread(values, max_n):
    """At most ``max_n`` of the sorted ``values``, evenly spread, ends included."""
    values = np.unique(values)
    if len(values) > max_n:
        values = values[np.linspace(0, len(values) - 1, max_n).round().astype(int)]
    return values


def _zs_to_show(sf, max_panels=6):
    """Simulated redshifts: the PPC table's, else the two ends of the simulated range."""
    if sf.ppc is not None and len(sf.ppc):
        zs = np.unique(sf.ppc["z"])
    else:
        zs = np.unique([sf.z_grid[0], sf.z_grid[-1]])
    if len(zs) > max_panels:
        zs = zs[np.linspace(0, len(zs) - 1, max_panels).round().astype(int)]
    return zs


def _binned(ppc, mask, k, n):
    """(x, (k+1)/(n+2), 16 %, 84 %) of the PPC rows ``mask``, depth bins summed per magnitude."""
    from scipy import stats

    r = ppc[mask]
    mags = np.unique(r["mag"])
    kk = np.array([r[k][r["mag"] == m].sum() for m in mags], float)
    nn = np.array([r[n][r["mag"] == m].sum() for m in mags], float)
    keep = nn > 0
    mags, kk, nn = mags[keep], kk[keep], nn[keep]
    return (mags, (kk + 1) / (nn + 2), stats.beta.ppf(0.16, kk + 1, nn - kk + 1),
            stats.beta.ppf(0.84, kk + 1, nn - kk + 1))


def completeness_figure(sf):
    """C(m) at the simulated redshifts: median, 68 % and 95 % bands, binned points.

    Points are the binned (k_rec+1)/(n+2) of the posterior-predictive table
    with 68 % Beta intervals; cells the check flags are marked.

    Parameters
    ----------
    sf : SelectionFunction

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib import colormaps

    zs = _zs_to_show(sf)
    m = np.linspace(sf.m_grid[0], sf.m_grid[-1], 200)
    fig = new_figure((8, 5))
    ax = fig.subplots()
    colors = colormaps["viridis"](np.linspace(0, 0.9, len(zs)))
    for z, col in zip(zs, colors):
        # ``g``: the simulated value as configured (9.125, not a rounded 9.12)
        _credible_band(ax, m, sf.completeness(m, z, draws=True), col, f"z = {z:g}")
        if sf.ppc is not None:
            at_z = np.isclose(sf.ppc["z"], z)
            x, y, lo, hi = _binned(sf.ppc, at_z, "k_rec", "n")
            ax.errorbar(x, y, yerr=[y - lo, hi - y], fmt="o", ms=3, color=col, lw=0.8)
            # cells the posterior-predictive check flags (any depth bin): marked
            bad = sf.ppc[at_z & sf.ppc["extreme"]]
            if len(bad):
                mags = np.unique(bad["mag"])
                ax.plot(mags, np.interp(mags, x, y), "x", color="red", ms=8, mew=1.5,
                        label="PPC extreme" if z == zs[0] else None)
    ax.set_xlabel("input magnitude" + (" (M_UV)" if sf.magnitude_type == "absolute" else " [AB]"))
    ax.set_ylabel("completeness C(m)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"C, area-weighted ({sf.model.shape}, field {sf.field}); points: (k+1)/(n+2)",
                 fontsize=TITLE_PT)
    ax.legend(fontsize=LEGEND_PT)
    fig.tight_layout()
    return fig


def selection_figure(sf, n_mags: int = 4):
    """S(z) at a few magnitudes (bands, binned (k_sel+1)/(k_rec+2)) and the median P = C S map.

    Parameters
    ----------
    sf : SelectionFunction
    n_mags : int
        Magnitudes shown in the left panel.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib import colormaps

    z = np.linspace(sf.z_grid[0], sf.z_grid[-1], 200)
    if sf.ppc is not None and len(sf.ppc):
        mags = _spread(sf.ppc["mag"], n_mags)            # the simulated (nominal) magnitudes
    else:
        mags = np.unique([sf.m_grid[0], sf.m_grid[-1]])  # the ends of the simulated range
    fig = new_figure((12, 5))
    ax, ax2 = fig.subplots(1, 2)
    colors = colormaps["plasma"](np.linspace(0, 0.85, len(mags)))
    for mv, col in zip(mags, colors):
        _credible_band(ax, z, sf.selection_given_recovered(z, mv, draws=True), col, f"m = {mv:g}")
        if sf.ppc is not None:
            zs = np.unique(sf.ppc["z"])
            pts = [_binned(sf.ppc, np.isclose(sf.ppc["z"], zz) & np.isclose(sf.ppc["mag"], mv),
                           "k_sel", "k_rec") for zz in zs]
            for zz, (x, y, lo, hi) in zip(zs, pts):
                if len(x):
                    ax.errorbar([zz], y, yerr=[y - lo, hi - y], fmt="o", ms=3, color=col, lw=0.8)
    ax.set_xlabel("redshift z")
    ax.set_ylabel("S(z, m) = P(selected | recovered)")
    ax.set_ylim(-0.02, 1.02)
    ax.legend(fontsize=LEGEND_PT)
    P = sf.grid_quantiles("P", quantiles=(0.5,))[0]
    im = ax2.imshow(P, origin="lower", aspect="auto", vmin=0, vmax=1, cmap="magma",
                    extent=[sf.m_grid[0], sf.m_grid[-1], sf.z_grid[0], sf.z_grid[-1]])
    fig.colorbar(im, ax=ax2, label="median selection probability P = C S")
    ax2.set_xlabel("input magnitude [AB]")
    ax2.set_ylabel("redshift z")
    fig.suptitle(f"selection (field {sf.field})", fontsize=TITLE_PT + 1)
    fig.tight_layout()
    return fig
