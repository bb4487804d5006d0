"""Plots of binned simulation summaries: C(m, z), C·S and S (PNG, matplotlib Agg)."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd

from .store import atomic_write_bytes

__all__ = ["plot_summary_maps", "summary_grid", "save_png"]


def save_png(fig, path, **savefig_kwargs) -> Path:
    """Write a matplotlib figure as PNG atomically (temporary name, then rename) and close it."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", **savefig_kwargs)
    plt.close(fig)
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


def plot_summary_maps(summary: pd.DataFrame, out_dir, label: str, mag_label: str = "m (AB)") -> list[Path]:
    """Write ``completeness_<label>.png``, ``selection_total_<label>.png`` and ``selection_<label>.png``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = []
    titles = {"completeness": "C(m, z)", "selection_total": "C(m, z) · S(z, m)", "selection": "S(z, m)"}
    for column, title in titles.items():
        zs, ms, grid = summary_grid(summary, column)
        fig, ax = plt.subplots(figsize=(6, 4.5), dpi=110)
        pcm = ax.pcolormesh(_edges(ms), _edges(zs), grid, vmin=0, vmax=1, cmap="viridis", shading="flat")
        fig.colorbar(pcm, ax=ax, label=title)
        ax.set_xlabel(mag_label)
        ax.set_ylabel("z")
        ax.set_title(f"{title} — {label}")
        out.append(save_png(fig, Path(out_dir) / f"{column}_{label}.png", bbox_inches="tight"))
    return out
