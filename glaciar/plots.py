"""Plots of binned simulation summaries: C(m, z), C·S and S, and the HTML report's figures.

Every figure is a :class:`matplotlib.figure.Figure` built without pyplot: glaciar
never selects a backend nor registers figures with pyplot, so a notebook's inline
backend (or any backend a user chose) is the same after a glaciar plot as before.
PNGs are rendered by the Agg canvas that ``Figure.savefig`` picks for the format.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd

from .rundir import atomic_write_bytes

__all__ = ["plot_summary_maps", "summary_grid", "save_png"]


def save_png(fig, path, **savefig_kwargs) -> Path:
    """Write a matplotlib figure as PNG atomically (temporary name, then rename).

    ``fig`` is a :class:`matplotlib.figure.Figure` (:func:`new_figure`): it belongs to
    no pyplot figure manager, so there is nothing to close.
    """
    buf = io.BytesIO()
    fig.savefig(buf, format="png", **savefig_kwargs)
    path = Path(path)
    atomic_write_bytes(path, buf.getvalue())
    return path


def summary_grid(summary: pd.DataFrame, column: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(z values, mag values, 2-D array [z, mag]) of one summary column; NaN where no cell."""
    zs = np.unique(summary["z"].to_numpy())
    ms = np.unique(summary["mag"].to_numpy())
    grid = np.full((zs.size, ms.size), np.nan)
    iz = np.searchsorted(zs, summary["z"].to_numpy())
    im = np.searchsorted(ms, summary["mag"].to_numpy())
    grid[iz, im] = summary[column].to_numpy(dtype=float)
    return zs, ms, grid


def _edges(v: np.ndarray) -> np.ndarray:
    if v.size == 1:
        return np.array([v[0] - 0.5, v[0] + 0.5])
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[2 * v[0] - mid[0]], mid, [2 * v[-1] - mid[-1]]])


def plot_summary_maps(summary: pd.DataFrame, out_dir, label: str, mag_label: str = "m (AB)",
                      selection: bool = True) -> list[Path]:
    """Write ``completeness_<label>.png``, ``selection_total_<label>.png`` and ``selection_<label>.png``.

    ``selection=False`` (a detection-only run: S = 1 by definition) omits the S map.
    """
    from .tables import summary_stem   # the file name of a field's label (never a path)

    out = []
    titles = {"completeness": "C(m, z)", "selection_total": "C(m, z) · S(z, m)", "selection": "S(z, m)"}
    if not selection:
        del titles["selection"]
    for column, title in titles.items():
        zs, ms, grid = summary_grid(summary, column)
        fig = new_figure((6, 4.5), dpi=110)
        ax = fig.subplots()
        pcm = ax.pcolormesh(_edges(ms), _edges(zs), grid, vmin=0, vmax=1, cmap="viridis", shading="flat")
        fig.colorbar(pcm, ax=ax, label=title)
        ax.set_xlabel(mag_label)
        ax.set_ylabel("z")
        ax.set_title(f"{title} — {label}")
        out.append(save_png(fig, Path(out_dir) / f"{column}_{summary_stem(label)}.png",
                            bbox_inches="tight"))
    return out


# --------------------------------------------------------------------------------------
# Figures of the HTML report (glaciar.report).  Each takes arrays the run already holds
# (summary tables, the selection-function file's grids and PPC table, fit/summary.json,
# manifest.json) and returns a matplotlib Figure; nothing here reads or writes files.

#: plotting order and colours of the status codes (GLACiAR's meaning, see README)
STATUS_COLOURS = {0: "#1b9e77", 1: "#66a61e", 2: "#a6d854", -1: "#e7298a", -2: "#e6ab02",
                  -3: "#d95f02"}
#: resolution of the report's PNGs [dots per inch]; the page shows them at one PNG pixel
#: per CSS pixel, so a 10 pt label is 14 px on screen and a 9.5 in figure 950 px wide
REPORT_DPI = 100
#: font sizes [pt] of legends and titles (axis labels and ticks keep matplotlib's 10 pt):
#: at REPORT_DPI, 9 pt is 12.5 px, the smallest text a reader is asked to read
LEGEND_PT = 9
TITLE_PT = 11
#: the faint end of V_eff(m) is shown down to this fraction of its largest value (4 decades)
VEFF_LOG_RANGE = 1e-4


def new_figure(figsize, dpi: float | None = None):
    """A matplotlib Figure outside pyplot: no backend switch, no global state, nothing to close.

    Parameters
    ----------
    figsize : (float, float)
        Width and height [inch].
    dpi : float, optional
        Resolution [dots per inch] (matplotlib's default when None).
    """
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, dpi=dpi)


def _cmap(name):
    import matplotlib

    return matplotlib.colormaps[name]


def png_bytes(fig, dpi: int = REPORT_DPI) -> bytes:
    """The figure as PNG bytes (``dpi`` [dots per inch]), cropped to its content."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return buf.getvalue()


def plot_status_fractions(summary: pd.DataFrame, labels: dict, mag_label: str = "m (AB)"):
    """Stacked fractions of the status codes per magnitude, all redshifts pooled.

    Parameters
    ----------
    summary : pandas.DataFrame
        A summary table (:func:`glaciar.tables.summary_table`): ``mag``, ``n_input`` and
        ``n_status_*`` columns.
    labels : dict
        {status code: (summary column, legend text)}.
    mag_label : str
        Label of the magnitude axis.
    """
    g = summary.groupby("mag", sort=True)[["n_input"] + [c for c, _ in labels.values()]].sum()
    mags = g.index.to_numpy(float)
    width = 0.8 * (np.min(np.diff(mags)) if mags.size > 1 else 1.0)
    fig = new_figure((9.5, 4.5))
    ax = fig.subplots()
    bottom = np.zeros(mags.size)
    for code, (col, text) in labels.items():
        frac = g[col].to_numpy(float) / np.maximum(g["n_input"].to_numpy(float), 1)
        ax.bar(mags, frac, width, bottom=bottom, color=STATUS_COLOURS.get(code, "grey"),
               label=f"{code}: {text}")
        bottom += frac
    ax.set_xlabel(mag_label)
    ax.set_ylabel("fraction of injected sources")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=LEGEND_PT, loc="center left", bbox_to_anchor=(1.01, 0.5))
    ax.set_title("status per magnitude (all z and fields pooled)", fontsize=TITLE_PT)
    return fig


def plot_quantile_curves(x, curves, *, xlabel: str, ylabel: str, title: str = "", points=None):
    """Curves with 68 % and 95 % credible bands from stored posterior quantiles.

    Parameters
    ----------
    x : array_like
        Abscissa of the quantiles.
    curves : list of (label, q)
        ``q`` has shape (5, len(x)): the quantiles 0.5, 0.16, 0.84, 0.025, 0.975 (the planes
        of the selection-function file's grids).  Each label is one legend entry.
    points : list of (x, y, lo, hi) or None, optional
        Binned data per curve (same order), drawn with error bars as given: a caller
        leaves out the cells without data (no point is drawn for them).
    """
    fig = new_figure((9.5, 5))
    ax = fig.subplots()
    colours = _cmap("viridis")(np.linspace(0, 0.9, max(len(curves), 1)))
    for i, ((label, q), col) in enumerate(zip(curves, colours)):
        q = np.asarray(q, float)
        ax.fill_between(x, q[3], q[4], color=col, alpha=0.15, lw=0)
        ax.fill_between(x, q[1], q[2], color=col, alpha=0.35, lw=0)
        ax.plot(x, q[0], color=col, label=label)
        if points is not None and len(points[i][0]):
            px, py, lo, hi = (np.asarray(a, float) for a in points[i])
            ax.errorbar(px, py, yerr=[np.clip(py - lo, 0, None), np.clip(hi - py, 0, None)],
                        fmt="o", ms=4, color=col, lw=0.9)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(title, fontsize=TITLE_PT)
    ax.legend(fontsize=LEGEND_PT)
    return fig


def plot_grid_map(x, y, grid, *, xlabel: str, ylabel: str, label: str, title: str = "",
                  vmin=0.0, vmax=1.0, cmap: str = "magma"):
    """A 2-D map of ``grid`` [len(y), len(x)] on cell centres ``x``, ``y`` (NaN left blank)."""
    fig = new_figure((10, 5))
    ax = fig.subplots()
    pcm = ax.pcolormesh(_edges(np.asarray(x, float)), _edges(np.asarray(y, float)),
                        np.ma.masked_invalid(grid), vmin=vmin, vmax=vmax, cmap=cmap, shading="flat")
    fig.colorbar(pcm, ax=ax, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=TITLE_PT)
    return fig


def plot_ppc(ppc):
    """Posterior-predictive check: binned fractions against the model's cell means.

    ``ppc`` is the PPC table of the selection-function file (columns ``c_binned``,
    ``c_model`` with ``_q16``/``_q84``, ``s_*`` likewise, ``n``, ``k_rec``, ``extreme``).
    Extreme cells are drawn in red; a cell without injected sources (C panel) or without
    a recovered one (S panel) has no fraction and gets no point.
    """
    fig = new_figure((11, 5))
    axes = fig.subplots(1, 2)
    ext = np.asarray(ppc["extreme"], bool)
    for ax, name, title, keep in ((axes[0], "c", "C: recovered / injected", np.asarray(ppc["n"]) > 0),
                                  (axes[1], "s", "S: selected / recovered",
                                   np.asarray(ppc["k_rec"]) > 0)):
        for sel, colour, lab in ((keep & ~ext, "C0", "cell"), (keep & ext, "red", "extreme cell")):
            if not sel.any():
                continue
            mx = np.asarray(ppc[f"{name}_model"], float)[sel]
            by = np.asarray(ppc[f"{name}_binned"], float)[sel]
            col = lambda c: np.asarray(ppc[c], float)[sel]  # noqa: E731
            ax.errorbar(mx, by,
                        xerr=np.clip([mx - col(f"{name}_model_q16"), col(f"{name}_model_q84") - mx],
                                     0, None),
                        yerr=np.clip([by - col(f"{name}_binned_q16"), col(f"{name}_binned_q84") - by],
                                     0, None),
                        fmt="o", ms=4, lw=0.7, color=colour, label=lab)
        ax.plot([0, 1], [0, 1], color="grey", lw=0.8, ls="--")
        ax.set_xlim(-0.02, 1.02)
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel("model (posterior median, 68 %)")
        ax.set_ylabel("binned (k+1)/(n+2), 68 %")
        ax.set_title(title, fontsize=TITLE_PT)
        ax.legend(fontsize=LEGEND_PT)
    fig.tight_layout()
    return fig


def plot_depth_completeness(mags, depth_lo, depth_step, observed, model, *, mag_label: str):
    """Completeness on a (magnitude, local depth) map: binned fractions and the model.

    ``observed`` and ``model`` have shape (len(depth_lo), len(mags)); NaN where no source
    (left blank).  ``depth_step`` is the depth bin width [mag].
    """
    mags = np.asarray(mags, float)
    dlo = np.asarray(depth_lo, float)
    dedges = np.append(dlo, dlo[-1] + depth_step)
    fig = new_figure((11, 4.8))
    axes = fig.subplots(1, 2, sharey=True)
    for ax, grid, title in ((axes[0], observed, "binned k_rec / n"),
                            (axes[1], model, "model C (posterior median of the cell means)")):
        pcm = ax.pcolormesh(_edges(mags), dedges, np.ma.masked_invalid(grid), vmin=0, vmax=1,
                            cmap="viridis", shading="flat")
        ax.set_xlabel(mag_label)
        ax.set_title(title, fontsize=TITLE_PT)
    axes[0].set_ylabel("local depth (5σ, AB)")
    fig.colorbar(pcm, ax=axes, label="completeness C")
    return fig


def plot_area_by_depth(depth_area: dict):
    """Each field's footprint area [arcmin²] per bin of local depth (manifest ``depth_area``)."""
    fig = new_figure((9.5, 4.2))
    ax = fig.subplots()
    for field, (edges, area) in sorted(depth_area.items()):
        e = np.asarray(edges, float)
        a = np.asarray(area, float)
        ax.stairs(a, e, label=f"{field} ({a.sum():.3g} arcmin²)")
    ax.set_xlabel("local depth (5σ, AB)")
    ax.set_ylabel("area per bin [arcmin²]")
    ax.set_title("area by local depth", fontsize=TITLE_PT)
    ax.legend(fontsize=LEGEND_PT)
    return fig


def plot_effective_volume(mag, median, lower, upper, *, mag_label: str, title: str = ""):
    """V_eff(m) [Mpc³] with its credible interval (from ``fit/summary.json``), on a log axis.

    A linear axis hides the faint end, where V_eff falls by decades; the log axis shows
    it down to ``VEFF_LOG_RANGE`` times the top of the 68 % interval.  Values <= 0 (no volume at
    all) have no logarithm and are left out rather than clipped.
    """
    fig = new_figure((9.5, 4.8))
    ax = fig.subplots()
    m = np.asarray(mag, float)
    med, lo, hi = (np.where(np.asarray(v, float) > 0, np.asarray(v, float), np.nan)
                   for v in (median, lower, upper))
    ax.fill_between(m, lo, hi, color="C1", alpha=0.35, lw=0, label="68 % interval")
    ax.plot(m, med, color="C1", label="median")
    ax.set_yscale("log")
    top = np.nanmax(hi) if np.isfinite(hi).any() else np.nanmax(med) if np.isfinite(med).any() else None
    if top is not None and np.isfinite(top):
        ax.set_ylim(top * VEFF_LOG_RANGE, top * 2)
    ax.set_xlabel(mag_label)
    ax.set_ylabel("V_eff [Mpc³]")
    ax.set_title(title, fontsize=TITLE_PT)
    ax.legend(fontsize=LEGEND_PT)
    return fig


__all__ += ["new_figure", "png_bytes", "plot_status_fractions", "plot_quantile_curves",
            "plot_grid_map", "plot_ppc", "plot_depth_completeness", "plot_area_by_depth",
            "plot_effective_volume", "STATUS_COLOURS", "REPORT_DPI", "LEGEND_PT", "TITLE_PT"]
