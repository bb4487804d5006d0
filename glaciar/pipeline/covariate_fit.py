"""``glaciar fit --covariates r_eff,beta``: size- and beta-aware fits added to a fitted run.

After :func:`glaciar.pipeline.run_fit` has written the pooled fit (unchanged, bit for
bit), :func:`add_covariates` reads the run's per-source rows with their covariate
columns (``r_eff_arcsec``, ``beta``), fits the pooled fit's model to each quantile bin
of each covariate (:func:`glaciar.inference.covariates.fit_covariate_nodes`, with the
posterior-predictive check per bin), and rewrites ``selection_function.fits`` with the
``CV_*`` extensions added and ``fit/summary.json`` with a ``covariates`` entry per fit,
holding the run's lock throughout.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from .. import constants as C
from ..inference.covariates import COVARIATES, DEFAULT_BINS, fit_covariate_nodes, parse_covariates
from ..inference.fit import fit_surfaces
from ..inference.sampling import DEFAULT_MAX_STEPS, SamplerSettings
from ..inference.selection_function import SelectionFunction
from .fitdir import hold_run
from .inputs import read_columns

__all__ = ["add_covariates", "covariate_summary", "CovariateWarning"]


class CovariateWarning(UserWarning):
    """A covariate bin fails its posterior-predictive check."""


def covariate_summary(name, covs) -> dict:
    """The summary entry of one fit's covariates; warns about bins the PPC rejects."""
    out = {}
    for cov_name, nodes in covs.items():
        bad = [k for k, ok in enumerate(nodes.adequate) if not ok]
        if bad:
            warnings.warn(f"fit {name!r}, covariate {cov_name}: the posterior-predictive check "
                          f"rejects bin(s) {bad} (x = "
                          f"{[round(float(nodes.centres[k]), 3) for k in bad]}); use more bins "
                          "(--covariate-bins) or more injections", CovariateWarning)
        out[cov_name] = {"x": nodes.spec.label, "covered": list(nodes.covered),
                         "nodes": nodes.centres.tolist(), "n_sources": nodes.n_sources.tolist(),
                         "n_cells": nodes.n_cells.tolist(), "n_extreme": nodes.n_extreme.tolist(),
                         "adequate": nodes.adequate.tolist()}
    return out


def add_covariates(run_dir, covariates, *, n_bins: int | None = None,
                   sampler: SamplerSettings = SamplerSettings(), max_draws: int = 1000) -> dict:
    """Fit the covariates of every fit in ``RUN_DIR/selection_function.fits`` and rewrite it.

    Parameters
    ----------
    run_dir : path-like
        A run fitted by ``glaciar fit``.
    covariates : str or sequence of str
        ``"r_eff"``, ``"beta"`` or both (``"r_eff,beta"``).
    n_bins : int, optional
        Quantile bins per covariate (default :data:`DEFAULT_BINS`).
    sampler : SamplerSettings
        Seed, walkers and step cap of each bin's chains (as ``glaciar fit``'s).
    max_draws : int
        Draws kept per bin.

    Returns
    -------
    dict
        ``{field: {covariate: summary}}`` (also in ``fit/summary.json``).

    Raises
    ------
    ValueError
        Unknown covariate, no fitted file, or injections that do not span the covariate.
    """
    from ..rundir import atomic_write_bytes, atomic_write_text

    names = parse_covariates(covariates)
    n_bins = DEFAULT_BINS if n_bins is None else int(n_bins)
    if not names:
        return {}
    if n_bins < 1:
        raise ValueError(f"--covariate-bins must be >= 1, not {n_bins}")
    run_dir = Path(run_dir)
    with hold_run(run_dir, "fit"):
        path = run_dir / "selection_function.fits"
        if not path.exists():
            raise ValueError(f"{run_dir}: no selection_function.fits to add covariates to "
                             "(run `glaciar fit` first)")
        fits_ = SelectionFunction.read_all(path)
        first = next(iter(fits_.values()))
        mag_col = str(first.meta.get("magnitude_column", C.COL_MAG_INPUT))
        want = [C.COL_FIELD, C.COL_Z, C.COL_MAG, mag_col, C.COL_RECOVERED, C.COL_SELECTED,
                C.COL_DEPTH] + [COVARIATES[n].column for n in names]
        rows = read_columns(run_dir, want)
        if C.COL_FIELD not in rows.columns:
            rows[C.COL_FIELD] = "all"
        listed = first.meta.get("fields")
        if listed:
            rows = rows[rows[C.COL_FIELD].astype(str).isin(list(map(str, listed)))]
        max_steps = DEFAULT_MAX_STEPS if sampler.max_steps is None else sampler.max_steps
        out = {}
        for i, (field, sf) in enumerate(fits_.items()):
            sub = rows if field == "all" else rows[rows[C.COL_FIELD].astype(str) == field]
            sub = sub.reset_index(drop=True)
            seed = [int(sampler.seed)] + ([] if field == "all" else [i])

            def fit(cells, model, s, seed=seed):
                return fit_surfaces(cells, model, seed=seed + list(s[1:]),
                                    n_walkers=sampler.n_walkers, max_steps=max_steps)

            # Added to the file's covariates (a lensed fit's magnification stays).
            new = {n: fit_covariate_nodes(
                sub, n, sf.model, n_bins=n_bins, fit=fit, max_draws=max_draws, mag_col=mag_col,
                mag_resolution=sf.meta.get("mag_resolution", 0.01)) for n in names}
            sf.covariates = {**sf.covariates, **new}
            out[field] = covariate_summary(field, new)
        atomic_write_bytes(path, SelectionFunction.to_bytes(list(fits_.values()), first.meta))
        summ = run_dir / "fit" / "summary.json"
        if summ.exists():
            s = json.loads(summ.read_text())
            for field, entry in out.items():
                s.setdefault("fits", {}).setdefault(field, {})["covariates"] = entry
            atomic_write_text(summ, json.dumps(s, indent=2, default=_json))
    return out


def _json(o):
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
