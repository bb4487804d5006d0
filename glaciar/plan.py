"""The task plan: which (field, z, mag, iteration) a run simulates, and what it can hold.

Pure functions of the configuration (the preflight also reads the footprints).
"""
from __future__ import annotations

import functools
import hashlib
import json
import math
from pathlib import Path

import numpy as np

from .config import Config
from .engine.context import FieldContext
from .engine.interlopers import POPULATION, InterloperModel
from .engine.positions import placement_capacity
from .engine.task import TaskSpec, draw_task_sources
from .fieldprep import band_psf, resolve_filter
from .galaxy import population, sed
from .galaxy.psf import measure_fwhm
from .store import task_filename, task_key
from .survey import Survey


def box_cells(cfg: Config) -> list[dict]:
    """The points of ``grid.box`` as cells (plain JSON, fields resolved); [] without a box.

    The points depend on ``simulation.seed`` (:func:`glaciar.box.box_points`;
    :func:`glaciar.execute.simulate` puts a ``seed`` override into the config first).
    """
    box = cfg.grid.box
    if box is None:
        return []
    fields = list(box.fields or cfg.survey.fields)
    return [{"z": z, "mag": m, "n_iterations": int(box.n_iterations), "fields": fields}
            for z, m in box.points(cfg.simulation.seed)]


def task_cells(cfg: Config) -> dict[tuple[str, float, float], int]:
    """Every simulated cell of a run: ``{(field, z, mag): n_iterations}``.

    The Cartesian grid (``simulation.n_iterations`` each) united with
    ``grid.cells`` and the points of ``grid.box``; a cell given twice (or also
    on the grid) runs the largest of its iteration counts, so re-applying a
    proposal adds nothing.
    """
    n_it = cfg.simulation.n_iterations
    cells: dict[tuple[str, float, float], int] = {}
    for f in cfg.survey.fields:
        for z in cfg.grid.z_values:
            for m in cfg.grid.mag_values:
                cells[(f, float(z), float(m))] = n_it
    for cell in manifest_cells(cfg):
        for f in cell["fields"]:
            key = (f, cell["z"], cell["mag"])
            cells[key] = max(cells.get(key, 0), cell["n_iterations"])
    return cells


def plan_tasks(cfg: Config) -> list[TaskSpec]:
    """All tasks of a run, ordered field → z → mag → iteration (so per-process caches stay warm).

    Tasks are keyed by exact values (field name, z, mag, iteration); the
    indices are positions in the sorted values the run simulates.
    """
    cells = task_cells(cfg)
    field_index = {f: i for i, f in enumerate(cfg.survey.fields)}
    zs = sorted({z for _, z, _ in cells})
    ms = sorted({m for _, _, m in cells})
    zi, mi = {z: i for i, z in enumerate(zs)}, {m: i for i, m in enumerate(ms)}
    out = []
    for (f, z, m), n in sorted(cells.items(), key=lambda kv: (field_index[kv[0][0]],) + kv[0][1:]):
        for it in range(n):
            out.append(TaskSpec(field=f, field_index=field_index[f], z_index=zi[z],
                                mag_index=mi[m], iteration=it, z=z, mag=m))
    return out + interloper_tasks(cfg, z_offset=len(zs))


#: Sub-directory of a run holding the interloper tasks' store (its own ``results/``).
INTERLOPER_DIRNAME = "interlopers"


def interloper_tasks(cfg: Config, z_offset: int = 0) -> list[TaskSpec]:
    """The interloper tasks of ``cfg.interlopers`` (none without the section).

    Ordered field -> z node -> magnitude cell -> iteration; their ``z_index`` starts at
    ``z_offset`` so that a (field, z_index) group never mixes the two populations
    (:func:`glaciar.execute` chunks by it).
    """
    sec = cfg.interlopers
    if sec is None:
        return []
    # The population names the settings that make the rows (the section and the source
    # settings it shares): other settings, other streams and task keys, so that a changed
    # section's tasks run again while the target population's store stays valid.
    ident = json.dumps([sec.model_dump(mode="json"), cfg.source.model_dump(mode="json")],
                       sort_keys=True)
    pop = f"{POPULATION}-{hashlib.sha256(ident.encode('utf-8')).hexdigest()[:12]}"
    out = []
    for fi, f in enumerate(cfg.survey.fields):
        for i, z in enumerate(sec.z_nodes()):
            for j, m in enumerate(sec.mag_cells()):
                for it in range(int(sec.n_iterations)):
                    out.append(TaskSpec(field=f, field_index=fi, z_index=z_offset + i,
                                        mag_index=j, iteration=it, z=float(z), mag=float(m),
                                        population=pop))
    return out


@functools.lru_cache(maxsize=8)
def _model_of(section_json: str, source_json: str) -> InterloperModel:
    return InterloperModel.from_config(json.loads(section_json),
                                       population.SourceModel(**json.loads(source_json)))


def interloper_model(cfg_dict: dict) -> InterloperModel | None:
    """The run's :class:`~glaciar.engine.interlopers.InterloperModel` from its plain config dict."""
    sec = cfg_dict.get("interlopers")
    if sec is None:
        return None
    src = dict(cfg_dict["source"])
    src["sersic_indices"] = tuple(src["sersic_indices"])
    src["sersic_fractions"] = tuple(src["sersic_fractions"])
    return _model_of(json.dumps(sec, sort_keys=True), json.dumps(src, sort_keys=True))


def spec_store(run_dir, spec: TaskSpec) -> Path:
    """The store a task's file goes to: the run's, or ``RUN/interlopers`` for interlopers."""
    return Path(run_dir) / INTERLOPER_DIRNAME if spec.population else Path(run_dir)


def finished_specs(run_dir, specs, quarantine: bool = False,
                   verify: bool = True) -> set[TaskSpec]:
    """The tasks among ``specs`` stored completely, each looked for in its own store:
    :func:`glaciar.store.verified_task_names` (``verify``), else the names the store lists
    (:func:`glaciar.store.finished_task_names`)."""
    from .store import finished_task_names, verified_task_names

    done = set()
    for pop in sorted({s.population for s in specs}):
        group = [s for s in specs if s.population == pop]
        store = spec_store(run_dir, group[0])
        if pop and not store.is_dir():
            continue
        if verify:
            names = verified_task_names(store, {spec_filename(s): spec_key(s) for s in group},
                                        quarantine=quarantine)
        else:
            names = finished_task_names(store)
        done.update(s for s in group if spec_filename(s) in names)
    return done


def manifest_cells(cfg: Config) -> list[dict]:
    """``grid.cells`` and the points of ``grid.box`` as the manifest records them.

    Plain JSON, fields resolved: the rows of every listed cell are current
    (:func:`glaciar.store.current_rows_mask`).
    """
    return [{"z": float(c.z), "mag": float(c.mag),
             "n_iterations": int(c.n_iterations or cfg.simulation.n_iterations),
             "fields": list(c.fields or cfg.survey.fields)} for c in cfg.grid.cells] \
        + box_cells(cfg)


def spec_filename(spec: TaskSpec) -> str:
    """File name of a task's rows (:func:`glaciar.store.task_filename`)."""
    return task_filename(spec.field, spec.z, spec.mag, spec.iteration)


def spec_key(spec: TaskSpec) -> str:
    """Exact identity of a task (:func:`glaciar.store.task_key`; with its population, if any)."""
    key = task_key(spec.field, spec.z, spec.mag, spec.iteration)
    return key if not spec.population else key[:-1] + "," + json.dumps(spec.population) + "]"


def detection_z_limit(cfg: Config, z_max: float = 30.0) -> float | None:
    """Lowest z (to 0.005) where the detection band receives no flux (apparent-magnitude grids).

    Beyond it no source of an apparent detection-band magnitude exists, so the
    selection function is 0 there (:func:`glaciar.galaxy.sed.band_magnitudes`
    refuses such tasks). None for absolute-magnitude grids or below ``z_max``.
    """
    if cfg.grid.magnitude_type != "apparent":
        return None
    det = cfg.survey.detection_band
    filters = [resolve_filter(cfg.survey.band(det).filter, cfg.base_dir)]
    beta = np.array([cfg.source.beta_mean])

    def ok(z):
        try:
            sed.band_magnitudes(z, beta, filters, mag=np.array([26.0]), detection_index=0,
                                igm=cfg.source.igm)
            return True
        except ValueError:
            return False

    lo = max(z for _, z, _ in task_cells(cfg))
    if not ok(lo):
        return float(lo)
    hi = lo
    while ok(hi):
        lo, hi = hi, hi + 0.25
        if hi > z_max:
            return None
    while hi - lo > 0.005:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return round(hi, 3)


def placement_preflight(cfg: Config, survey: Survey) -> list[str]:
    """Fields where ``n_galaxies`` sources will not fit, one message each (before any task runs).

    Sizes are drawn as a task at the grid's lowest redshift and brightest
    magnitude would draw them (the largest sources of the run); the count that
    fits is :func:`glaciar.engine.positions.placement_capacity`'s random fill
    of that footprint. Tasks then place fewer sources; those that fit lean
    slightly toward small sizes when a crowded field ends the sequence early.
    """
    n = cfg.simulation.n_galaxies
    cells = task_cells(cfg)
    z, mag = min(z for _, z, _ in cells), min(m for _, _, m in cells)
    model = population.SourceModel(**cfg.source.model_dump())
    out = []
    for field in cfg.survey.fields:
        pixscale = survey.pixel_scale_arcsec(field)
        psfs = [band_psf(cfg, b, pixscale) for b in cfg.survey.bands]
        bands = tuple(b.name for b in cfg.survey.bands)
        lite = FieldContext(
            field=field, bands=bands, detection_band=cfg.survey.detection_band,
            detection_index=bands.index(cfg.survey.detection_band), shape=survey.shape(field),
            pixel_scale_arcsec=pixscale, zeropoints={}, gains={},
            filters=[resolve_filter(b.filter, cfg.base_dir) for b in cfg.survey.bands],
            bases={}, rms={}, mask=None, footprint=None, depth=None, reference=None, cache=None,
            isolation_margin_pix=int(math.ceil(2.0 * max(measure_fwhm(p, 1.0) for p in psfs))),
            source_model=model, cosmology=population.get_cosmology(model.cosmology),
            magnitude_type=cfg.grid.magnitude_type, n_galaxies=n, detection_params=None,
            classification_params=None, selection=None, enclosed_fraction=model.stamp_flux_fraction,
            isolation_fraction=cfg.simulation.isolation_fraction)
        src = draw_task_sources(np.random.default_rng(0), n, z, mag, lite)
        hh, hw = lite.stamp_half_sizes(src.sersic_n, src.r_eff_pix, src.axis_ratio,
                                       src.position_angle_deg)
        cap = placement_capacity(survey.footprint(field), hh, hw)
        if cap.upper_bound == 0:
            out.append(f"field {field!r}: no source fits in its footprint (no pixel with data in "
                       f"every band of survey.coverage, outside survey.mask)")
        elif cap.random_fill < n:
            out.append(f"field {field!r}: about {cap.random_fill} of simulation.n_galaxies = {n} "
                       f"sources fit per task at z = {z:g}, mag = {mag:g} (at most "
                       f"{cap.upper_bound}); tasks will place fewer (lower n_galaxies and raise "
                       "n_iterations to keep the count)")
    return out
