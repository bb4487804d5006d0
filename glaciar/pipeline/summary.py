"""The fit's summary: per-parameter table, m50(z), C_max, V_eff, and the lines ``glaciar fit`` prints.

``run_fit`` writes the summary to ``RUN_DIR/fit/summary.json`` (and
:func:`format_summary` of it to ``summary.txt``); the per-parameter table
(:func:`param_table`) to ``parameters_<field>.ecsv``.
"""
from __future__ import annotations

import warnings

import numpy as np

from ..inference.sampling import FitResult
from ..inference.products import GRID_QUANTILES
from ..inference.selection_function import SelectionFunction

__all__ = ["param_table", "param_summary", "m50_summary", "cmax_summary", "veff_summary",
           "format_summary", "json_default"]


def json_default(o):
    """``json.dumps(default=...)``: numpy scalars and arrays as Python numbers and lists."""
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def param_table(res: FitResult, draws) -> dict:
    """Columns of the per-parameter table: MAP, quantiles of ``draws``, chain diagnostics, prior."""
    mdl = res.model
    q = np.quantile(draws, GRID_QUANTILES, axis=0)
    return {"name": mdl.param_names, "map": res.theta_map, "median": q[0], "q16": q[1],
            "q84": q[2], "q025": q[3], "q975": q[4], "tau": res.tau, "ess": res.ess,
            "rhat": res.split_rhat, "acceptance_fraction": res.acceptance_fraction,
            "n_steps": res.n_steps, "prior_mean": mdl.prior_mean, "prior_sd": mdl.prior_sd}


def param_summary(res: FitResult, draws) -> dict:
    """{parameter: MAP, median, 68 and 95 % intervals, tau [steps], ESS, R-hat}."""
    t = param_table(res, draws)
    return {n: {"map": float(t["map"][j]), "median": float(t["median"][j]),
                "ci68": [float(t["q16"][j]), float(t["q84"][j])],
                "ci95": [float(t["q025"][j]), float(t["q975"][j])], "tau": float(t["tau"][j]),
                "ess": float(t["ess"][j]), "rhat": float(t["rhat"][j])}
            for j, n in enumerate(res.model.param_names)}


def m50_summary(sf: SelectionFunction, zg) -> list:
    """The magnitude of 50 % completeness [mag] with its 68 % interval at up to 5 redshifts of ``zg``."""
    zs = np.unique(np.round(np.linspace(zg[0], zg[-1], min(len(zg), 5)), 3))
    r = sf.magnitude_at(0.5, zs)
    return [{"z": float(z), "m50": float(a), "ci68": [float(b), float(c)]}
            for z, a, b, c in zip(zs, r.median, r.lower, r.upper)]


def cmax_summary(sf: SelectionFunction, zg) -> dict:
    """The bright-end completeness C_max at the median redshift of ``zg``: median and 68 %."""
    from scipy.special import expit
    s = sf.model._slices["logit_c_max"]
    zc = (np.median(zg) - sf.model.z_ref) / sf.model.z_scale
    v = expit(sf.draws[:, s] @ zc ** np.arange(s.stop - s.start))
    q = np.quantile(v, [0.5, 0.16, 0.84])
    return {"z": float(np.median(zg)), "median": float(q[0]), "ci68": [float(q[1]), float(q[2])]}


def veff_summary(sf: SelectionFunction, mg, zg, cosmology) -> dict:
    """V_eff [Mpc^3] on the file's magnitude grid ``mg``, and at three magnitudes around m50.

    Parameters
    ----------
    sf : SelectionFunction
        The fit with (a subset of) its posterior draws and its simulated box.
    mg, zg : ndarray
        The file's magnitude [mag] and redshift grids.
    cosmology : astropy Cosmology or None
        Default Planck18.

    Raises
    ------
    ValueError
        No survey area, or a single redshift (nothing to integrate over).
    """
    with warnings.catch_warnings():
        # the z-edge warning of the fit already covers V_eff's truncation
        warnings.filterwarnings("ignore", message="effective_volume: C\\*S is still")
        # the full magnitude grid with 200 draws (its median to ~1/15 of the 68 % width)
        few = SelectionFunction(sf.model, sf.draws[:200], meta=sf.meta, field=sf.field,
                                depth_area=sf.depth_area, domain=sf.domain)
        few.lens_nodes = sf.lens_nodes
        ve = few.effective_volume(mg, cosmology=cosmology, n_z=201)
        lev = sf.magnitude_at(0.5, [np.median(zg)])
        quote = ([float(x) for x in np.round(lev.median[0] + np.array([-1.0, 0.0, 0.5]), 2)]
                 if np.isfinite(lev.median[0]) else [float(x) for x in mg[[0, len(mg) // 2, -1]]])
        vq = sf.effective_volume(quote, cosmology=cosmology, n_z=401)
        lens = None
        if sf.lens_nodes:
            # Behind a lens: the intrinsic magnitude; V_eff per lens model and their spread.
            lv = sf.lens_model_volumes(quote, cosmology=cosmology, n_z=401)
            lens = {"models": sf.lens_models, "spread_mpc3": lv.spread.value.tolist(),
                    "median_mpc3": {k: v.median.value.tolist() for k, v in lv.per_model.items()}}
    return {"area_arcmin2": sf.area_arcmin2(), "z_range": list(sf.domain["z"]),
            "lens": lens,
            "cosmology": getattr(cosmology, "name", None) or "Planck18",
            "mag": mg.tolist(), "median_mpc3": ve.median.value.tolist(),
            "lower_mpc3": ve.lower.value.tolist(), "upper_mpc3": ve.upper.value.tolist(),
            "quoted": {"mag": quote, "median_mpc3": vq.median.value.tolist(),
                       "lower_mpc3": vq.lower.value.tolist(), "upper_mpc3": vq.upper.value.tolist()}}


def _finite(v) -> bool:
    return v is not None and np.isfinite(float(v))


def _mag_text(v) -> str:
    """A magnitude to 0.01, or "n/a" (NaN: outside the simulated range or not reached)."""
    return f"{float(v):.2f}" if _finite(v) else "n/a"


def format_summary(summary: dict) -> str:
    """The few lines ``glaciar fit`` prints: per fit, the verdicts, m50(z), C_max, V_eff."""
    lines = []
    mlabel = "M_UV" if summary.get("magnitude_type") == "absolute" else "m"
    for name, e in summary["fits"].items():
        depth = (f"depth-aware (d_ref = {summary['depth_ref']:.2f})" if summary.get("depth_aware")
                 else "no depth")
        ppc = e["ppc"]
        # The verdicts are the kept model's: say so, and why it was kept.
        lines.append(f"fit {name}: model {e['model']}, {depth}, {e['n_sources']} sources; "
                     f"{e['model']} converged: {'yes' if e['converged'] else 'NO'}; adequate: "
                     f"{'yes' if e['adequate'] else 'NO'} ({ppc['n_extreme']}/{ppc['n_cells']} "
                     f"PPC cells extreme, chance allows {ppc['max_allowed']})")
        if e.get("model_kept_because"):
            lines.append(f"  kept {e['model']}: {e['model_kept_because']}")
        if e.get("model_comparison"):
            lines.append("  PSIS-LOO elpd relative to the best: " + ", ".join(
                f"{r['model']} {r['delta_elpd']:+.1f}±{r['se_delta']:.1f}" for r in e["model_comparison"]))
        if summary.get("detection_only"):
            lines.append("  S = 1 exactly (detection only: the run has no selection criteria), "
                         "so P = C")
        lines.append(f"  {mlabel} at C = 0.5: " + "; ".join(
            f"z {r['z']:g}: {_mag_text(r['m50'])} [{_mag_text(r['ci68'][0])}, "
            f"{_mag_text(r['ci68'][1])}]" for r in e["m50"])
            + ("" if all(_finite(r["m50"]) for r in e["m50"]) else
               " (n/a: outside the simulated magnitude range, or never reached)"))
        cm = e["c_max"]
        lines.append(f"  C_max(z = {cm['z']:g}) = {cm['median']:.3f} [{cm['ci68'][0]:.3f}, "
                     f"{cm['ci68'][1]:.3f}]")
        ve = e.get("effective_volume")
        if ve:
            q = ve["quoted"]
            lines.append(f"  V_eff ({ve['area_arcmin2']:.2f} arcmin², z {ve['z_range'][0]:g}–"
                         f"{ve['z_range'][1]:g}): " + "; ".join(
                             f"{mlabel} {m:.2f}: {v:.3g} [{lo:.3g}, {hi:.3g}] Mpc³" for m, v, lo, hi in
                             zip(q["mag"], q["median_mpc3"], q["lower_mpc3"], q["upper_mpc3"])))
            if ve.get("lens"):
                lz = ve["lens"]
                lines.append("  behind the lens (intrinsic magnitude; mean of the models above): "
                             + "; ".join(f"{name}: " + ", ".join(f"{v:.3g}" for v in med)
                                         for name, med in lz["median_mpc3"].items())
                             + " Mpc³; spread across models " + ", ".join(
                                 f"{v:.2g}" for v in lz["spread_mpc3"]) + " Mpc³")
        elif e.get("effective_volume_note"):
            lines.append(f"  V_eff: not computed ({e['effective_volume_note']})")
    return "\n".join(lines) + "\n"
