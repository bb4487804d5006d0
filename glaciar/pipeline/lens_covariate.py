"""The magnification covariate of lensed runs, fitted by ``glaciar fit`` by default.

Behind a lens the injections are made at the observed magnitude, so the pooled fit's
C(m_obs) averages over the image-plane |mu| distribution of the injected positions.  At
fixed observed magnitude a more magnified source is more stretched (lower surface
brightness) and less often recovered, and V_eff weights the source plane (1/|mu|), not
the image plane.  :func:`fit_magnification` fits the pooled model to bins of log10|mu|
(quantile levels that resolve the high-|mu| tail;
:func:`glaciar.inference.covariates.fit_covariate_nodes`, with the per-bin
posterior-predictive check) so that V_eff and the count tables behind the lens read C at
each lens node's own |mu| (:mod:`glaciar.inference.lensed`).  Unlensed runs never get it.
"""
from __future__ import annotations

from .. import constants as C
from ..inference.covariates import MAGNIFICATION_QUANTILES, fit_covariate_nodes
from ..inference.fit import fit_surfaces
from .inputs import read_columns

__all__ = ["magnification_rows", "fit_magnification"]
#: Seed stream of the magnification bins' chains (distinct from ``--covariates``').
_SEED_STREAM = 25


def magnification_rows(run_dir, mag_col: str, fields):
    """The per-source columns the magnification fit needs, for the listed ``fields``."""
    want = [C.COL_FIELD, C.COL_Z, C.COL_MAG, mag_col, C.COL_RECOVERED, C.COL_SELECTED,
            C.COL_DEPTH, C.COL_MAGNIFICATION]
    rows = read_columns(run_dir, want)
    if C.COL_MAGNIFICATION not in rows.columns:
        raise ValueError(f"{run_dir}: the manifest has a lens but the per-source table has no "
                         f"{C.COL_MAGNIFICATION!r} column (simulate the run again)")
    if C.COL_FIELD not in rows.columns:
        rows[C.COL_FIELD] = "all"
    return rows[rows[C.COL_FIELD].astype(str).isin(list(map(str, fields)))]


def fit_magnification(rows, name: str, index: int, model, *, seed, n_walkers, max_steps,
                      max_draws: int, mag_col: str, mag_resolution):
    """The ``magnification`` :class:`~glaciar.inference.covariates.CovariateNodes` of one fit.

    Raises ValueError when the rows span no range of |mu| (``fit_covariate_nodes``).

    Parameters
    ----------
    rows : pandas.DataFrame
        :func:`magnification_rows` (all fields).
    name : str
        The fit's name: a field, or "all" for a pooled fit.
    index : int
        The fit's position in the file (its seed stream for per-field fits).
    model : SurfaceModel
        The fit's model (every bin uses it).
    seed, n_walkers, max_steps, max_draws, mag_col, mag_resolution
        As the pooled fit's.
    """
    sub = rows if name == "all" else rows[rows[C.COL_FIELD].astype(str) == name]
    sub = sub.reset_index(drop=True)
    base = [int(seed), _SEED_STREAM] + ([] if name == "all" else [int(index)])

    def fit(cells, mdl, s):
        return fit_surfaces(cells, mdl, seed=base + list(s[1:]), n_walkers=n_walkers,
                            max_steps=max_steps)

    return fit_covariate_nodes(sub, "magnification", model, quantiles=MAGNIFICATION_QUANTILES,
                               fit=fit,
                               max_draws=max_draws, mag_col=mag_col,
                               mag_resolution=mag_resolution)
