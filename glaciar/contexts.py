"""The run's field contexts: on disk in the run directory, and one per process.

A field's :class:`~glaciar.engine.context.FieldContext` is measured once
(:func:`glaciar.fieldprep.build_field_context`), written to the run's field cache
(:func:`save_field_context`, keyed by :func:`context_dir`) and memory-mapped by
every process that runs its tasks (:func:`open_field_context`); each process keeps
one field's context at a time (:func:`worker_context`, :func:`main_context`).

A run with workers measures its fields there (:func:`measure_field`, one field per
job): the worker writes the field's cache and returns the small records the run's
manifest keeps (:func:`field_records`); the main process never holds a context.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import threading
import warnings
from pathlib import Path

import numpy as np

from .version import __version__
from . import constants as C
from .config import Config, config_from_dict, config_hash
from .engine import fieldcache
from .engine.context import FieldContext
from .fieldprep import (build_field_context, field_depth_area, field_noise_record,
                        field_settings)
from .lensmaps import field_lens_nodes
from .paths import run_subdir
from .store import StoreWarning
from .rundir import read_manifest
from .survey import Survey, clear_cache as clear_survey_cache


def open_field_context(cfg: Config, survey: Survey, field: str, path) -> FieldContext:
    """A field's context from its cache directory (:func:`save_field_context`): the measured
    arrays memory-mapped read-only, the rest set up from the configuration (no image read)."""
    settings, _ = field_settings(cfg, survey, field)
    items, maps = fieldcache.load(path)
    return FieldContext(**settings, **items, _trimmer=fieldcache.Trimmer(maps))


def _cache_items(ctx: FieldContext) -> dict:
    """A context's measured fields as its cache stores them.

    When the field's mapped arrays exceed a worker's resident budget
    (:data:`glaciar.engine.fieldcache.RESIDENT_BUDGET_BYTES`: their pages will be
    dropped and faulted in again during the run), the images the engine reads by
    window (images, RMS maps, mask, reference segmentation) are stored as tiles: a window then
    reads the tiles under it with positional reads, nothing mapped (benchmarks/window_reads.py).
    Smaller fields stay row-major (their pages stay resident, a plain slice is cheapest).
    """
    items = ctx.measured()
    arrays = [a for a in (*ctx.bases.values(), *ctx.rms.values(), ctx.mask, ctx.footprint,
                          ctx.depth, getattr(ctx.reference, "segmap", None),
                          ctx.detection_image_rms, ctx.detection_background)
              if isinstance(a, np.ndarray)]
    if not fieldcache.TILED_CACHE or \
            sum(a.nbytes for a in arrays) <= fieldcache.RESIDENT_BUDGET_BYTES:
        return items

    def tiled(a):
        return fieldcache.Tiled(a) if isinstance(a, np.ndarray) and a.ndim == 2 else a

    items["bases"] = {b: tiled(a) for b, a in ctx.bases.items()}
    items["rms"] = {b: tiled(a) for b, a in ctx.rms.items()}
    items["mask"] = tiled(ctx.mask)
    items["detection_image_rms"] = tiled(ctx.detection_image_rms)
    if isinstance(getattr(ctx.reference, "segmap", None), np.ndarray):
        items["reference"] = dataclasses.replace(ctx.reference, segmap=tiled(ctx.reference.segmap))
    return items


def save_field_context(ctx: FieldContext, path) -> FieldContext:
    """Write a context's measured fields to ``path`` (unless a cache is there already) and
    return the context with them memory-mapped from it (the in-memory arrays can go).

    If the cache cannot be written (e.g. the disk is full), warns and returns ``ctx``
    unchanged: the run goes on with the field in memory (forked workers inherit it,
    spawned ones measure it again).
    """
    try:
        if not fieldcache.exists(path):
            fieldcache.save(_cache_items(ctx), path)
        items, maps = fieldcache.load(path)
    except (OSError, ValueError) as exc:     # ValueError: fieldcache.load's unreadable cache
        # One reason, not DiskFullError's whole advice: the run goes on.
        why = os.strerror(exc.errno) if getattr(exc, "errno", None) else str(exc)
        warnings.warn(f"{path}: field cache not written ({why}); the field's arrays stay in "
                      "memory", UserWarning)
        return ctx
    return dataclasses.replace(ctx, **items, _trimmer=fieldcache.Trimmer(maps))


def context_dir(run_dir, cfg_hash: str, field: str, inputs: dict | None = None) -> Path | None:
    """Cache directory of a field's context in a run (None: no manifest yet).

    Keyed on everything the measurement depends on: the config's hash, the field,
    the run's input files (size and BLAKE2b: ``inputs``, by default the manifest's),
    glaciar's version and the cache's format; a changed config or input gets a new
    directory.
    """
    if inputs is None:
        manifest = read_manifest(run_dir)
        if manifest is None:
            return None
        inputs = manifest.get("inputs") or {}
    ident = json.dumps({"format": fieldcache.FORMAT, "glaciar": __version__, "config": cfg_hash,
                        "field": field, "inputs": inputs}, sort_keys=True)
    return Path(run_dir) / C.CONTEXT_DIRNAME / hashlib.sha256(ident.encode("utf-8")).hexdigest()[:24]


def prepare_context_cache(run_dir: Path, cfg: Config, cfg_hash: str, fields,
                          keep_temporaries: bool = False) -> None:
    """Before tasks run (lock held, no worker yet): remove caches of other configs or inputs
    and half-written ones, and put the context this process built (for the manifest) on disk,
    so its tasks, forked workers and spawned workers all map the same files.

    ``keep_temporaries``: leave caches being written (``.*.tmp``,
    :func:`glaciar.engine.fieldcache.save`) alone -- a shard (a sibling's worker may be
    writing one); it holds
    the set-up lock, and the sibling shards share its configuration, so the caches of
    other configurations are no one's."""
    keep = {context_dir(run_dir, cfg_hash, f) for f in cfg.survey.fields}
    root = run_subdir(run_dir, C.CONTEXT_DIRNAME, create=False)     # refused if a link
    if root.is_dir():
        for entry in root.iterdir():
            if entry.is_symlink():
                entry.unlink()          # the link only: nothing outside the run is touched
            elif keep_temporaries and entry.name.startswith("."):
                continue
            elif entry not in keep:
                shutil.rmtree(entry, ignore_errors=True)
            elif fieldcache.exists(entry):
                try:                    # mapping only: a truncated file would fail the workers
                    fieldcache.load(entry)
                except fieldcache.UnreadableCache:
                    shutil.rmtree(entry, ignore_errors=True)      # written again below
    for key, ctx in list(_CONTEXTS.items()):
        if key[0] == cfg_hash and key[2] in fields:
            _CONTEXTS[key] = save_field_context(ctx, context_dir(run_dir, cfg_hash, key[2]))
            # The masks the build left in the survey's cache: forked workers would inherit them.
            clear_survey_cache()


def finish_context_cache(run_dir: Path, complete: bool) -> None:
    """A run with no task left pending removes its field caches; an unfinished one keeps them
    for its resume (they are as large as the images)."""
    if complete:
        shutil.rmtree(Path(run_dir) / C.CONTEXT_DIRNAME, ignore_errors=True)


#: This process's field contexts, ``{(config hash, base_dir, field): FieldContext}``: one at a time.
_CONTEXTS: dict = {}
#: How many fields this process has measured (:func:`fields_measured`).
_MEASURED = [0]


def fields_measured() -> int:
    """How many field contexts this process has measured from the images so far (not
    mapped from a cache): a caller can tell whether a step ran a field's set-up here."""
    return _MEASURED[0]


def _build(cfg: Config, survey: Survey, field: str) -> FieldContext:
    _MEASURED[0] += 1
    return build_field_context(cfg, survey, field)


def clear_contexts() -> None:
    """Forget the field contexts this process keeps (e.g. once forked workers hold their own)."""
    _CONTEXTS.clear()


def worker_context(cfg_dict: dict, base_dir: str, cfg_hash: str, field: str,
                   run_dir: str | None = None) -> FieldContext:
    """The field's context in this process: kept from an earlier call, opened from the run's
    field cache, or built (and then cached for the other workers)."""
    key = (cfg_hash, base_dir, field)
    ctx = _CONTEXTS.get(key)
    if ctx is None:
        cfg = config_from_dict(cfg_dict, base_dir)
        _CONTEXTS.clear()          # one field at a time per process bounds memory
        path = None if run_dir is None else context_dir(run_dir, cfg_hash, field)
        survey = Survey.from_config(cfg)
        if path is not None and fieldcache.exists(path):
            ctx = open_field_context(cfg, survey, field, path)
        else:
            ctx = _build(cfg, survey, field)
            if path is not None:
                ctx = save_field_context(ctx, path)
        _CONTEXTS[key] = ctx
    return ctx


def main_context(cfg: Config, survey: Survey, field: str, cached: Path | None = None,
                 save: bool = False) -> FieldContext:
    """The field's context from the main process's config, under :func:`worker_context`'s key.

    ``cached``: the field's cache directory in the run, if known: a complete cache
    there (an interrupted run's, for its resume, or a sibling shard's) is mapped instead
    of measuring the field again.  ``save``: a context measured here is written there
    at once (a shard, under the run's set-up lock: the shards started after it map it,
    none measures it again).
    """
    key = (config_hash(cfg), str(cfg.base_dir), field)
    ctx = _CONTEXTS.get(key)
    if ctx is None:
        _CONTEXTS.clear()
        if cached is not None and fieldcache.exists(cached):
            try:
                ctx = open_field_context(cfg, survey, field, cached)
            except fieldcache.UnreadableCache as exc:
                # A copy of measurements: measured again (the run replaces it, under its lock).
                warnings.warn(f"{exc.path}: unreadable field cache ({exc.why}); the field is "
                              "measured again", StoreWarning)
        if ctx is None:
            ctx = _build(cfg, survey, field)
            if save and cached is not None:
                ctx = save_field_context(ctx, cached)
        _CONTEXTS[key] = ctx
    return ctx


def field_records(cfg: Config, survey: Survey, field: str, ctx: FieldContext) -> dict:
    """What the run's manifest keeps of a measured field: its pixel scale [arcsec], footprint
    area [arcmin^2], area by local depth (:func:`glaciar.fieldprep.field_depth_area`) and
    noise record (:func:`glaciar.fieldprep.field_noise_record`), as plain data."""
    ps = survey.pixel_scale_arcsec(field)
    out = {"pixel_scale_arcsec": ps,
           "area_arcmin2": float(ctx.footprint_count) * ps ** 2 / 3600.0,
           "depth_area": field_depth_area(cfg, survey, field, ctx),
           "noise": field_noise_record(cfg, survey, field, ctx)}
    if cfg.survey.lens is not None:
        out["lens_nodes"] = field_lens_nodes(cfg, survey, field, ctx.depth, ctx.footprint)
    return out


#: One field measured at a time per process: an executor whose workers run several threads
#: (or that runs its jobs in threads of the run's own process) shares one ``_CONTEXTS``,
#: one survey cache and one warnings state between them.
_MEASURING = threading.Lock()


def measure_field(cfg_dict: dict, base_dir: str, cfg_hash: str, field: str, cache_dir: str,
                  submitter_pid: int) -> tuple[dict, list]:
    """A worker's job of a run's set-up: the field's context measured (or mapped from a
    complete cache at ``cache_dir``), written to ``cache_dir`` and kept for this process's
    tasks (:func:`worker_context` finds it); returns ``(field_records(...), warnings)``.

    ``warnings``: those raised while measuring, as ``(message, category, filename,
    lineno)`` for the submitting process to raise (once per run, however many fields
    repeat them).  A job run by a thread of the submitting process (``submitter_pid``)
    leaves its warnings to that process's own record (a list, empty here).
    """
    cfg = config_from_dict(cfg_dict, base_dir)
    survey = Survey.from_config(cfg)
    in_submitter = os.getpid() == submitter_pid
    with _MEASURING:
        if in_submitter:
            ctx = _measured(cfg, survey, cfg_hash, field, Path(cache_dir))
            return field_records(cfg, survey, field, ctx), []
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            ctx = _measured(cfg, survey, cfg_hash, field, Path(cache_dir))
            records = field_records(cfg, survey, field, ctx)
        # The images and masks the build read: this process's tasks map the field's cache.
        clear_survey_cache()
    return records, [(str(w.message), w.category, w.filename, w.lineno) for w in caught]


def _measured(cfg: Config, survey: Survey, cfg_hash: str, field: str, cache_dir: Path):
    """:func:`main_context`, written to ``cache_dir``, under :func:`worker_context`'s key."""
    ctx = main_context(cfg, survey, field, cache_dir, save=True)
    _CONTEXTS.clear()
    _CONTEXTS[(cfg_hash, str(cfg.base_dir), field)] = ctx
    return ctx
