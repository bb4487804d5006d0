"""``glaciar fit``'s interloper step: the contamination of a run with an ``interlopers:`` section.

Reads the interloper rows of ``RUN/interlopers`` (:func:`glaciar.plan.spec_store`) that
the run's stored configuration plans, weights them to the configured number counts
(:func:`glaciar.engine.interlopers.count_weights`), fits the passing fraction per
measured magnitude (:func:`glaciar.inference.contamination.fit_contamination`) and
attaches it to every fit, so that the selection-function file carries it (``CONTAM``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import constants as C

__all__ = ["interloper_rows", "run_contamination", "add_contamination"]


def interloper_rows(run_dir, cfg):
    """The rows of the interloper tasks ``cfg`` plans (an empty frame if none is stored).

    Raises
    ------
    ValueError
        ``cfg`` has no ``interlopers:`` section.
    """
    import pandas as pd

    from ..engine.task import task_rng
    from ..plan import INTERLOPER_DIRNAME, interloper_tasks
    from ..store import read_results

    if cfg.interlopers is None:
        raise ValueError("the configuration has no interlopers: section")
    store = Path(run_dir) / INTERLOPER_DIRNAME
    if not (store / C.RESULTS_DIRNAME).is_dir():
        return pd.DataFrame()
    rows = read_results(store)
    if rows.empty:
        return rows
    # A task's stream id (task_seed) names its population's settings and the run's seed:
    # rows of tasks made with other interloper settings are not counted.
    planned = {task_rng(cfg.simulation.seed, s)[1] for s in interloper_tasks(cfg)}
    keep = np.isin(np.asarray(rows[C.COL_TASK_SEED], np.int64), np.fromiter(planned, np.int64))
    return rows[keep].reset_index(drop=True)


def run_contamination(run_dir, cfg, detection_band: str, seed: int = 0):
    """The run's :class:`~glaciar.inference.contamination.Contamination`, or None (no section or
    no interloper row yet)."""
    from ..engine.interlopers import COL_FAMILY, InterloperModel, count_weights
    from ..galaxy.population import SourceModel
    from ..inference.contamination import fit_contamination

    if cfg.interlopers is None:
        return None
    rows = interloper_rows(run_dir, cfg)
    if rows.empty:
        return None
    model = InterloperModel.from_config(cfg.interlopers, SourceModel(**cfg.source.model_dump()))
    w = count_weights(rows[C.COL_MAG_INPUT], rows[C.COL_MAG], model)
    half = 0.5 * model.mag_step
    edges = np.append(np.asarray(model.mag_cells) - half, model.mag_cells[-1] + half)
    obs = C.band_column(C.OBS_MAG_QUANTITY, detection_band)
    return fit_contamination(rows, w, edges, obs_column=obs, counts=model.family_counts,
                             z_range=(model.z_nodes[0], model.z_nodes[-1]),
                             family_column=COL_FAMILY, seed=seed)


def add_contamination(run_dir, manifest: dict, fits_list, seed: int = 0) -> None:
    """Attach the run's contamination to each fit (nothing without an ``interlopers:`` section)."""
    from ..config import load_config

    cpath = Path(run_dir) / C.RUN_CONFIG_NAME
    if not cpath.is_file():
        return
    cfg = load_config(cpath)
    if cfg.interlopers is None:
        return
    contam = run_contamination(run_dir, cfg, manifest.get("detection_band")
                               or cfg.survey.detection_band, seed=seed)
    for sf in fits_list:
        sf.interlopers = contam
