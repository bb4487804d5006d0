"""The adaptive loop at the edge: fit → propose → simulate into one store, round by round.

``glaciar simulate CONFIG --adaptive`` runs the configuration's design (the
coarse grid plus any ``grid.cells``) when it fits in the budget, else a coarse
subset of it (:func:`coarse_design`), then repeats

1. fit the run (:func:`glaciar.pipeline.run_fit`, the logistic surface),
2. measure the largest posterior sd of P = C·S over the (z, m) box,
3. stop when it is below ``target_sd`` or ``budget`` sources are spent,
4. otherwise share ~``round_size`` sources (at most what the budget has left,
   to half a task per field) among the candidate cells
   (:func:`glaciar.inference.plan_round`: expected information gain about
   P = C·S plus the posterior-predictive misfit term), log the proposal,
   and simulate it into the same store.

Every round is written to ``RUN/adaptive_rounds.json`` (atomically) before
its cells are simulated, so a run killed at any instant resumes where it
stopped: logged proposals are simulated again by task key (finished tasks
are skipped), and a round killed during its fit is fitted again from the
same store, which gives the same proposal (the fit's seed is fixed).  The
cells of the rounds are part of the run: its stored ``config.yaml`` lists
them as ``grid.cells``.

The budget is kept: a design that costs more than ``budget`` sources starts
from every k-th z and magnitude value of its Cartesian grid (the extreme
values kept; k the smallest stride whose cost is at most half the budget,
:func:`glaciar.inference.adaptive.coarse_plan`; fewer iterations per cell when
even the grid's corners cost more), without its ``grid.cells`` and
``grid.box`` points.  The rounds' candidates stay the full design's lattice,
so they fill in the values the coarse start skipped.  The loop stops before a
round would exceed the budget by a whole task per field.
"""
from __future__ import annotations

import json
import math
import time
import warnings
from pathlib import Path

import numpy as np

from .. import constants as C

__all__ = ["ADAPTIVE_ROUNDS_NAME", "AdaptiveSettings", "read_rounds", "with_cells",
           "design_sources", "coarse_design",
           "run_adaptive", "proposal_cells", "round_cells", "cells_yaml"]

ADAPTIVE_ROUNDS_NAME = C.ADAPTIVE_ROUNDS_NAME
#: The surface each round fits (the default model of ``glaciar fit``).
ROUND_MODEL = "logistic"
#: Candidate points per unit of the simulated grid's spacing (2: the values and midpoints).
REFINE = 2


class AdaptiveSettings:
    """Stopping rule and round size of the loop (validated on construction).

    Parameters
    ----------
    target_sd : float
        Stop when the largest posterior sd of P = C·S over the box is below this.
    budget : int
        Stop when the store holds this many injected sources (the coarse design counts).
    round_size : int
        Sources to add per round (rounded to whole tasks of ``n_galaxies`` per field).
    max_steps : int, optional
        Cap on each round's sampler steps (default: ``glaciar fit``'s).
    """

    def __init__(self, target_sd: float, budget: int, round_size: int,
                 max_steps: int | None = None):
        for name, v in (("--target-sd", target_sd), ("--budget", budget),
                        ("--round-size", round_size)):
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(v) or v <= 0:
                raise ValueError(f"{name}: expected a positive finite number, got {v!r}")
        self.target_sd = float(target_sd)
        self.budget = int(budget)
        self.round_size = int(round_size)
        self.max_steps = max_steps


def read_rounds(run_dir) -> list[dict]:
    """The rounds logged in ``RUN/adaptive_rounds.json`` ([] when there are none)."""
    p = Path(run_dir) / ADAPTIVE_ROUNDS_NAME
    if not p.exists():
        return []
    try:
        rounds = json.loads(p.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: not a valid rounds log ({exc}); move it away to restart the "
                         "adaptive loop from the store") from None
    if not isinstance(rounds, list) or not all(isinstance(r, dict) for r in rounds):
        raise ValueError(f"{p}: expected a JSON list of rounds")
    return rounds


def _write_rounds(run_dir, rounds: list[dict]) -> None:
    from ..rundir import atomic_write_text

    atomic_write_text(Path(run_dir) / ADAPTIVE_ROUNDS_NAME, json.dumps(rounds, indent=1) + "\n")


def with_cells(cfg, cells: list[dict], source_name: str = "cells"):
    """``cfg`` with ``cells`` ({z, mag, n_iterations[, fields]}) added to ``grid.cells``.

    Errors in the cells are reported as coming from ``source_name``.
    """
    from ..config import config_from_dict, config_to_dict

    if not cells:
        return cfg
    d = config_to_dict(cfg)
    d["grid"]["cells"] = list(d["grid"].get("cells", [])) + [dict(c) for c in cells]
    return config_from_dict(d, base_dir=cfg.base_dir, source_name=source_name)


def design_sources(cfg) -> int:
    """Sources the configuration's design injects: its tasks (all fields) x ``n_galaxies``."""
    from ..plan import task_cells

    return int(sum(task_cells(cfg).values())) * cfg.simulation.n_galaxies


def coarse_design(cfg, budget: int):
    """The design the adaptive loop starts from: ``cfg`` itself, or a coarse subset of it.

    When the design costs at most ``budget`` sources it runs as configured.
    Otherwise the start is the Cartesian grid's every k-th z and magnitude value
    (first and last kept) at the iterations of :func:`glaciar.inference.adaptive.
    coarse_plan` (at most half the budget), without ``grid.cells`` and
    ``grid.box``; the same inputs give the same start, so a resumed loop
    starts from the same cells.

    Returns
    -------
    start : Config
    note : str or None
        One line saying what the coarse start is (None when ``start`` is ``cfg``).
    """
    from ..config import config_from_dict, config_to_dict
    from ..inference.adaptive import coarse_axis, coarse_plan

    full = design_sources(cfg)
    if full <= budget:
        return cfg, None
    zs, ms = list(cfg.grid.z_values), list(cfg.grid.mag_values)
    per_iteration = cfg.simulation.n_galaxies * len(cfg.survey.fields)
    k, n_it, cost = coarse_plan(len(zs), len(ms), cfg.simulation.n_iterations, per_iteration,
                                budget)
    z_keep = [zs[i] for i in coarse_axis(len(zs), k)]
    m_keep = [ms[i] for i in coarse_axis(len(ms), k)]
    d = config_to_dict(cfg)
    d["grid"]["z"], d["grid"]["mag"] = {"values": z_keep}, {"values": m_keep}
    for key in ("cells", "cells_file", "box"):
        d["grid"].pop(key, None)
    d["simulation"]["n_iterations"] = n_it
    start = config_from_dict(d, base_dir=cfg.base_dir, source_name="the coarse design")
    note = (f"coarse start: the design costs {full} sources, the budget {budget}: z and mag "
            f"values at stride {k} (extremes kept; {len(z_keep)} z x {len(m_keep)} mag), "
            f"{n_it} iteration(s) per cell, {cost} sources; the rounds fill in the rest")
    return start, note


def _simulated_values(cfg):
    from ..plan import task_cells

    cells = task_cells(cfg)
    return (np.array(sorted({z for _, z, _ in cells})), np.array(sorted({m for _, _, m in cells})),
            cells)


def _candidates(cfg, box=None, z_limit=None, design=None):
    """The candidate (z, m) lattice: the design's values and the midpoints between them.

    The design (the Cartesian axes, and a regular lattice over ``grid.box``
    (:func:`glaciar.box.box_lattice`); every simulated value on an axis the
    design does not span) fixes the lattice, so a cell proposed again gains
    iterations instead of new midpoints halving the spacing round after round
    (:func:`glaciar.inference.candidate_grid`, which assumes no uniform spacing).
    ``design`` is the configured design when ``cfg`` is its coarse start
    (:func:`coarse_design`): the lattice is the full design's.
    """
    from ..inference import candidate_grid

    zs, ms, simulated = _simulated_values(cfg)
    design = cfg if design is None else design
    zd, md = np.asarray(design.grid.z_values, float), np.asarray(design.grid.mag_values, float)
    if design.grid.box is not None:
        # A box's points are scattered: its candidates are a lattice over the box, united
        # with the Cartesian axes (also simulated), and never the points' own values.
        from ..box import box_lattice

        b = design.grid.box
        zl, ml = box_lattice(b.z, b.mag, b.n_points)
        zd, md = np.union1d(zl, zd), np.union1d(ml, md)
    zb = None if box is None else ((box[0], box[1]), (box[2], box[3]))
    zc, mc = candidate_grid(zd if zd.size > 1 else zs, md if md.size > 1 else ms, box=zb,
                            refine=REFINE)
    # Midpoints carry binary noise (9.4 + 9.8) / 2 = 9.600000000000001; cells are
    # keyed by exact values, so they are named to 1e-6 as the design's axes are.
    zc, mc = np.unique(np.round(zc, 6)), np.unique(np.round(mc, 6))
    if z_limit is not None:
        zc = zc[zc < float(z_limit)]
    if zc.size == 0 or mc.size == 0:
        raise ValueError("no candidate cell inside the box (and below the detection band's "
                         "redshift limit)")
    return zc, mc, simulated


def _scored(sf, zc, mc):
    """Draws of C, S and P on the candidates, and the PPC's misfit mask there."""
    from ..inference.adaptive import misfit_on_candidates

    g = sf.grid_draws(zc, mc, outside="extrapolate")   # candidates may lie past the data
    misfit = None
    if getattr(sf, "ppc", None) is not None and len(sf.ppc):
        misfit = misfit_on_candidates(sf.ppc, zc, mc)
    return g, misfit


def _with_totals(cells_zm_n, cfg, simulated) -> list[dict]:
    out = []
    for z, m, add in cells_zm_n:
        have = max((simulated.get((f, float(z), float(m)), 0) for f in cfg.survey.fields),
                   default=0)
        out.append({"z": float(z), "mag": float(m), "n_iterations": int(have + add)})
    return out


def proposal_cells(sf, cfg, n_cells: int, *, add_iterations: int = 1,
                   z_limit: float | None = None, box=None) -> tuple[list[dict], dict]:
    """The ``n_cells`` cells where one more injection teaches most, as ``grid.cells`` entries.

    Ranked by :func:`glaciar.inference.propose_cells` with the information
    criterion: the expected information gain of one more selected / not
    selected outcome about P = C·S, plus a term for the cells the
    posterior-predictive check flags as misfit.

    Parameters
    ----------
    sf : SelectionFunction
        The current fit.
    cfg : Config
        The run's configuration (with the cells simulated so far).
    n_cells : int
        Cells to propose.
    add_iterations : int
        Iterations (tasks per field, ``n_galaxies`` sources each) each cell gains.
    z_limit : float, optional
        No candidate at or beyond this redshift (the detection band receives no flux).
    box : (z_lo, z_hi, m_lo, m_hi), optional
        Where to look (default: the design's range).

    Returns
    -------
    cells : list of dict
        ``{z, mag, n_iterations}``, ``n_iterations`` being the cell's new total.
    stats : dict
        ``max_sd`` (largest posterior sd of P over the candidates), ``at`` ([z, m] where
        it is) and ``ranked`` (the scored cells, best first).
    """
    from ..inference import propose_cells

    zc, mc, simulated = _candidates(cfg, box, z_limit)
    g, misfit = _scored(sf, zc, mc)
    ranked = propose_cells(g["P"], zc, mc, int(n_cells), criterion="information",
                           misfit=misfit)
    cells = _with_totals([(r["z"], r["mag"], add_iterations) for r in ranked], cfg, simulated)
    return cells, {**_stopping(g["P"], zc, mc), "ranked": ranked}


def _stopping(p_draws, zc, mc) -> dict:
    """The stopping statistic (as :func:`glaciar.inference.max_posterior_sd`) and where it is."""
    sd = np.std(p_draws, axis=0)
    iz, im = np.unravel_index(int(np.nanargmax(sd)), sd.shape)
    return {"max_sd": float(np.max(sd)), "at": [float(zc[iz]), float(mc[im])]}


def round_cells(sf, cfg, n_units: int, *, z_limit=None, box=None,
                design=None) -> tuple[list[dict], dict]:
    """One adaptive round: ``n_units`` cell-iterations shared among the candidates.

    :func:`glaciar.inference.plan_round` (information criterion with the PPC
    misfit term) shares the units in proportion to the score (largest
    remainders, at least one per chosen cell); each unit is one more task per
    field of a cell.  ``design``: as :func:`_candidates`.
    """
    from ..inference import plan_round

    zc, mc, simulated = _candidates(cfg, box, z_limit, design)
    g, misfit = _scored(sf, zc, mc)
    request = plan_round(g["C"], g["S"], (zc, mc), int(n_units), criterion="information",
                         misfit=misfit)
    cells = _with_totals([(r["z"], r["mag"], int(r["n"])) for r in request], cfg, simulated)
    return cells, _stopping(g["P"], zc, mc)


def cells_yaml(cells: list[dict], header: str = "") -> str:
    """The text of a cells file (``grid.cells_file``) for ``cells``."""
    import yaml

    body = yaml.safe_dump({"cells": [dict(c) for c in cells]}, sort_keys=False)
    return "".join(f"# {line}\n" for line in header.splitlines()) + body


def _sources_in_store(run_dir) -> int:
    """Injected sources of the run's current tasks: from the stored counts, else the rows."""
    from ..counting import COUNT_N
    from ..store import read_current_counts
    from .inputs import read_columns

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")        # the fit that follows says what it leaves out
        got = read_current_counts(run_dir)
    if got is not None:
        return int(got[0][COUNT_N].sum())
    return int(len(read_columns(run_dir, [C.COL_Z])))


def run_adaptive(cfg, run_dir, settings: AdaptiveSettings, *, workers: int = 1,
                 seed: int | None = None, executor=None, progress: bool = True,
                 mode: str = "windowed", box=None, echo=print) -> list[dict]:
    """Run (or resume) the adaptive loop; return the rounds log.

    Parameters
    ----------
    cfg : Config
        The configured design; when it costs more than ``settings.budget`` the loop
        starts from its coarse subset (:func:`coarse_design`, said by ``echo``).
    run_dir : path
        Results store; ``adaptive_rounds.json`` there is read and extended.
    settings : AdaptiveSettings
    workers, seed, executor, progress, mode
        As :func:`glaciar.execute.simulate`.
    box : (z_lo, z_hi, m_lo, m_hi), optional
        Where the stopping statistic and proposals are evaluated.
    echo : callable
        Prints one line per round.
    """
    from ..execute import simulate
    from ..inference.sampling import SamplerSettings
    from ..rundir import read_manifest
    from .fit import run_fit

    run_dir = Path(run_dir)
    rounds = read_rounds(run_dir)
    design = cfg
    cfg, note = coarse_design(design, settings.budget)
    if note:
        echo(note)
    cfg = with_cells(cfg, [c for r in rounds for c in r.get("cells", [])])
    while True:
        stats = simulate(cfg, run_dir, workers=workers, seed=seed, executor=executor,
                         progress=progress, mode=mode)
        if rounds and "simulated" not in rounds[-1] and rounds[-1].get("cells"):
            rounds[-1]["simulated"] = {"n_tasks_run": stats["n_run"],
                                       "cpu_seconds": round(stats["cpu_seconds"], 3)}
            _write_rounds(run_dir, rounds)
        t0 = time.process_time()
        n_sources = _sources_in_store(run_dir)
        # The rounds' sampler: seed 0, the default step cap unless the settings give one.
        sampler = SamplerSettings(max_steps=settings.max_steps or None, seed=0, progress=False)
        # Rounds fit in memory (no file, no summaries); the round that stops the loop is
        # fitted again with the same seed (the same draws) and written in full.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sf = run_fit(run_dir, model=ROUND_MODEL, sampler=sampler, resume=False,
                         plots=False, write=False)[0]
        manifest = read_manifest(run_dir) or {}
        remaining = settings.budget - n_sources
        per_task = cfg.simulation.n_galaxies * len(cfg.survey.fields)
        # One more iteration of a cell adds n_galaxies sources per field.
        n_units = max(1, int(round(min(settings.round_size, remaining) / per_task)))
        cells, st = round_cells(sf, cfg, n_units, z_limit=manifest.get("detection_z_limit"),
                                box=box, design=design)
        if rounds and rounds[-1].get("stop"):
            rounds = rounds[:-1]            # a finished loop resumed with a new target/budget
        entry = {"round": len(rounds), "n_sources": n_sources, "max_sd": round(st["max_sd"], 5),
                 "max_sd_at": st["at"],
                 "fit_cpu_seconds": round(time.process_time() - t0, 3)}
        if st["max_sd"] <= settings.target_sd:
            entry["stop"] = f"max sd {st['max_sd']:.4f} <= target {settings.target_sd:g}"
        elif remaining < per_task:
            entry["stop"] = f"budget: {n_sources} of {settings.budget} sources spent"
        else:
            entry["cells"] = cells
        rounds.append(entry)
        _write_rounds(run_dir, rounds)
        echo(f"round {entry['round']}: {n_sources} sources, max sd of C·S {st['max_sd']:.4f} at "
             f"z = {st['at'][0]:g}, m = {st['at'][1]:g}"
             + (f"; stop ({entry['stop']})" if "stop" in entry else
                f"; adding {n_units} task(s) per field in {len(cells)} cell(s)"))
        if "stop" in entry:
            # Each round's fit warns about the same things: only the final fit's
            # warnings are shown (they describe the selection function the run ends with).
            # (No PNG plots: `glaciar fit RUN` draws them, and `glaciar report` reads the file.)
            run_fit(run_dir, model=ROUND_MODEL, sampler=sampler, resume=False, plots=False)
            return rounds
        cfg = with_cells(cfg, cells)
