"""A run's identity and start: the manifest, the store's settings, resume, the set-up steps.

:func:`open_run` checks everything (inputs, store identity, lock) before it creates
or modifies the run directory; with an executor, the detection z limit is
computed on one of its workers meanwhile (:class:`_SetupJobs`).  With workers (a
process pool or another executor) the fields are measured there, one job per field
(:func:`glaciar.contexts.measure_field`); this process writes the manifest from the
records they return and holds no field's context.
"""
from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import os
import shutil
import warnings
from pathlib import Path

import numpy as np
import yaml

from .version import __version__
from . import constants as C
from .config import Config, config_from_dict, config_hash, config_to_dict
from .config.models import SECTIONS
from .config.user_selection import selection_description
from .contexts import (context_dir, field_records, main_context, measure_field,
                       prepare_context_cache)
from .fieldprep import field_settings
from .engine.shotnoise import shot_noise_gains
from .galaxy import sed
from .inputs import InputFile, check_inputs, file_or_none, input_files
from .lensmaps import lens_z_range
from .plan import detection_z_limit, manifest_cells, placement_preflight, plan_tasks
from .store import StoreWarning, field_file_prefix, finished_task_names
from .rundir import (RunLock, StoreMismatchError, atomic_temporary_target, atomic_write_text,
                     check_shard_count, manifest_text, read_manifest, running_shards,
                     store_format, write_manifest, write_shard_record)
from .shards import shard_task_names
from .paths import check_run_tree, disk_full
from .survey import Survey, clear_cache as clear_survey_cache


def _load_fingerprint_cache(run_dir: Path) -> dict:
    p = run_dir / C.FINGERPRINT_CACHE_NAME
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


# --------------------------------------------------------------------------
# Store identity: the settings that fix every task's rows (no paths, no task list)
# --------------------------------------------------------------------------
_FILE = "<file>"   #: stands for a path in the store settings (its content is fingerprinted)


def store_settings(cfg: Config) -> dict:
    """The configuration's settings that fix every task's rows, as plain data.

    ``config_to_dict(cfg)`` without ``output``, the field list, the grid's z
    and magnitude values, ``simulation.n_iterations`` and ``simulation.seed``
    (the run's seed is compared on its own), and with every path replaced by
    ``"<file>"``: files are identified by content (the manifest's ``inputs``),
    so a run directory's own ``config.yaml`` (absolute paths) or a moved project
    is the same store.
    """
    d = config_to_dict(cfg)
    d.pop("output", None)
    # Interloper tasks carry their settings in their own keys (glaciar.plan.interloper_tasks):
    # adding or changing them leaves the target population's store as it is.
    d.pop("interlopers", None)
    # Definitions that change rows without a config key: a store made under another
    # definition is another store.
    d["classification"]["flux_test"] = "auto_vs_template"
    # Shot noise as it acts (on in some band, or not at all): None when off records a store
    # without it like one made before the key existed (those had noiseless stamps).
    gains = {b.name: b.gain for b in cfg.survey.bands}
    d["source"]["shot_noise"] = True if shot_noise_gains(cfg.source.shot_noise, gains) else None
    if isinstance(d.get("selection"), dict):
        # A selection function is identified by the version it declares, not only its name.
        d["selection"]["version"] = cfg.selection.version
    sv = d["survey"]
    sv.pop("fields", None)
    sv.pop("image_dir", None)
    sv.pop("science", None)
    sv["noise"] = _FILE if sv.get("noise") is not None else None
    sv["band_order"] = list(sv["bands"])
    for b in sv["bands"].values():
        if isinstance(b.get("psf"), str):
            b["psf"] = _FILE
        if file_or_none(b.get("filter"), cfg.base_dir) is not None:
            b["filter"] = _FILE
    if sv.get("lens") is not None:      # lens maps are identified by content too
        for m in sv["lens"].get("models") or ():
            for key in ("kappa", "gamma1", "gamma2", "alpha_x", "alpha_y"):
                if m.get(key) is not None:
                    m[key] = _FILE
    d["grid"].pop("z", None)
    d["grid"].pop("mag", None)
    d["grid"].pop("cells", None)
    d["grid"].pop("box", None)       # box points are cells: they only add tasks
    d["simulation"].pop("n_iterations", None)
    d["simulation"].pop("seed", None)
    det = d.get("detection") or {}
    for key in ("sex_file", "FILTER_NAME"):
        if file_or_none(det.get(key), cfg.base_dir) is not None:
            det[key] = _FILE
    return json.loads(json.dumps(d, sort_keys=True))


def store_hash(settings: dict) -> str:
    text = json.dumps(settings, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _flatten(d, prefix=""):
    if isinstance(d, dict):
        out = {}
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out or {prefix[:-1]: {}}
    return {prefix[:-1]: d}


def _flat_defaults() -> dict:
    """Every default of the sections that have one for each key, flattened like the settings."""
    out = {}
    for name, field in SECTIONS.items():
        try:
            section = field.annotation()
        except Exception:  # noqa: BLE001 - sections with required keys (survey) or no model
            continue
        out.update(_flatten(json.loads(json.dumps(section.model_dump(mode="json", by_alias=True))),
                            f"{name}."))
    return out


def _settings_differences(old: dict, new: dict) -> list[str]:
    """What differs between two stores' settings, one ``key: old -> new`` string each.

    A key the older store does not record (added to glaciar since) counts as the
    same when its value now is its default: a new key's default keeps the rows
    glaciar made before the key existed, so the older store stays extendable.
    """
    a, b = _flatten(old), _flatten(new)
    defaults = _flat_defaults()
    diffs = []
    for k in sorted(set(a) | set(b)):
        if k not in a and k in defaults and b[k] == defaults[k]:
            continue
        if a.get(k, "<unset>") != b.get(k, "<unset>"):
            diffs.append(f"{k}: {str(a.get(k, '<unset>'))[:40]} -> {str(b.get(k, '<unset>'))[:40]}")
    return diffs


def _summary(diffs: list[str], limit: int = 3) -> str:
    more = f" and {len(diffs) - limit} more" if len(diffs) > limit else ""
    return "; ".join(diffs[:limit]) + more


def _manifest(cfg: Config, seed: int) -> dict:
    """The run's manifest but its measured fields' records and detection z limit (added by
    :func:`_measure_fields`): what identifies the store."""
    settings = store_settings(cfg)
    return {
        "store_format": C.STORE_FORMAT,
        "glaciar_version": __version__,
        "glaciar_versions": [__version__],
        "config_hash": config_hash(cfg),
        "store_hash": store_hash(settings),
        "store_settings": settings,
        "seed": int(seed),
        "fields": list(cfg.survey.fields),
        "bands": [b.name for b in cfg.survey.bands],
        "detection_band": cfg.survey.detection_band,
        "selection": selection_description(cfg.selection),
        "z_values": list(map(float, cfg.grid.z_values)),
        "mag_values": list(map(float, cfg.grid.mag_values)),
        "magnitude_type": cfg.grid.magnitude_type,
        "n_galaxies": cfg.simulation.n_galaxies,
        "n_iterations": cfg.simulation.n_iterations,
        "cells": manifest_cells(cfg),
        **({} if cfg.grid.box is None else
           {"box": {"z": list(cfg.grid.box.z), "mag": list(cfg.grid.box.mag),
                    "n_points": cfg.grid.box.n_points}}),
    }


def _measure_fields(cfg: Config, survey: Survey, manifest: dict, z_limit=None,
                    cached: dict | None = None, save: bool = False,
                    measure_on: cf.Executor | None = None) -> None:
    """Add the fields' records (area, depth, noise) and the detection z limit to ``manifest``.

    ``z_limit``: a future of :func:`glaciar.plan.detection_z_limit` (None: computed here);
    ``cached``: field -> its context's cache directory in the run, and ``save``: write
    a measured context there (:func:`glaciar.contexts.main_context`).  If a field cannot
    be measured, the caches this call wrote are removed before the error is raised.
    ``measure_on``: an executor whose workers measure the fields, one job per field
    (:func:`glaciar.contexts.measure_field`, each writing its field's cache: ``cached``
    holds every field), while this process computes the z limit; None: measured here, in
    turn.  Warnings are raised in this process either way.
    """
    before = {f for f, path in (cached or {}).items() if path.exists()}
    try:
        if measure_on is None:
            records = {}
            for f in cfg.survey.fields:
                # The field's context is built here once, in this process (or mapped from an
                # interrupted run's cache): the records read it, a serial run's tasks use it
                # (glaciar.contexts.worker_context) or, with ``save``, map its cache.
                ctx = main_context(cfg, survey, f, (cached or {}).get(f), save=save)
                records[f] = field_records(cfg, survey, f, ctx)
            limit = detection_z_limit(cfg) if z_limit is None else z_limit.result()
        else:
            records, limit = _measured_on(cfg, measure_on, cached, z_limit)
    except Exception:
        # A field that cannot be measured: the caches written meanwhile go (the run
        # directory stays as it was, its lock file aside).  (An interrupt goes at once: an
        # unfinished cache is a temporary that the next run removes, a finished one its
        # resume maps.)
        for f, path in (cached or {}).items():
            if f not in before:
                shutil.rmtree(path, ignore_errors=True)
        raise
    fields = cfg.survey.fields
    manifest["pixel_scale_arcsec"] = {f: records[f]["pixel_scale_arcsec"] for f in fields}
    manifest["area_arcmin2"] = {f: records[f]["area_arcmin2"] for f in fields}
    manifest["area_arcmin2_total"] = float(sum(manifest["area_arcmin2"].values()))
    manifest["depth_area"] = {f: records[f]["depth_area"] for f in fields}
    manifest["noise"] = {f: records[f]["noise"] for f in fields}
    if cfg.survey.lens is not None:
        # Read by V_eff behind the lens (glaciar.lensmaps.field_lens_nodes; docs/lensing.md).
        manifest["lens"] = {"z_lens": cfg.survey.lens.z_lens,
                            "models": list(cfg.survey.lens.model_names),
                            "cosmology": cfg.source.cosmology,
                            "z_range": list(lens_z_range(cfg))}
        manifest["lens_nodes"] = {f: records[f]["lens_nodes"] for f in fields}
    manifest["detection_z_limit"] = limit


def _measured_on(cfg: Config, where: cf.Executor, cached: dict, z_limit) -> tuple[dict, object]:
    """The fields measured by ``where``'s workers (their warnings raised here, in the serial
    run's order: the fields', then the z limit's), and the detection z limit.

    If a field's measurement fails, the other jobs are cancelled or waited for before the
    error is raised.
    """
    cfg_dict, base_dir, chash = config_to_dict(cfg), str(cfg.base_dir), config_hash(cfg)
    jobs = {f: where.submit(measure_field, cfg_dict, base_dir, chash, f, str(cached[f]),
                            os.getpid()) for f in cfg.survey.fields}
    try:
        # This process is idle until the fields are measured: it computes the z limit
        # (a bisection over the SED), unless an executor's worker already does.
        with warnings.catch_warnings(record=True) as later:
            warnings.simplefilter("always")
            limit = detection_z_limit(cfg) if z_limit is None else z_limit.result()
        records = {}
        for f, job in jobs.items():
            records[f], caught = job.result()
            for message, category, filename, lineno in caught:
                warnings.warn_explicit(message, category, filename, lineno)
    except Exception:
        # The other fields' jobs are cancelled or finish (their caches are then removed).
        for job in jobs.values():
            job.cancel()
        cf.wait(list(jobs.values()))
        raise
    for w in later:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return records, limit


def _check_same_store(run_dir: Path, old: dict, manifest: dict, items: list[InputFile],
                      finished: set[str]) -> None:
    """Refuse to add tasks to a store whose finished tasks were made differently."""
    what = []
    if old.get("seed") != manifest["seed"]:
        what.append(f"seed: {old.get('seed')} -> {manifest['seed']}")
    if old.get("store_hash") != manifest["store_hash"]:
        diffs = _settings_differences(old.get("store_settings") or {}, manifest["store_settings"])
        if diffs:
            what.append(_summary(diffs))
    if what:
        raise StoreMismatchError(
            f"{run_dir}: results were made with a different configuration or seed "
            f"({'; '.join(what)}); only fields, grid values and n_iterations may change between "
            "runs into one directory; use another --out")
    old_inputs = old.get("inputs") or {}
    for item in items:
        prev, now = old_inputs.get(item.key), manifest["inputs"][item.key]
        if not isinstance(prev, dict) or (prev.get("size"), prev.get("blake2b")) == \
                (now["size"], now["blake2b"]):
            continue
        if item.field is None:
            used = bool(finished)
        else:
            prefix = field_file_prefix(item.field)
            used = any(n.startswith(prefix) for n in finished)
        if used:
            raise StoreMismatchError(f"{item.key}: {item.path} changed since the run started "
                                     "(content differs); use another --out")


def _check_old(run_dir: Path, old: dict | None, finished: set[str]) -> None:
    """Refuse a store with task files but no manifest, or of another store format."""
    if finished and old is None:
        raise StoreMismatchError(f"{run_dir / C.RESULTS_DIRNAME}: holds task files but "
                                 f"{run_dir / C.MANIFEST_NAME} is missing; use another --out")
    if finished and store_format(old) != C.STORE_FORMAT:
        raise StoreMismatchError(
            f"{run_dir}: made by glaciar {old.get('glaciar_version', '?')} (store format "
            f"{store_format(old)}, whose task file names can collide); glaciar {__version__} "
            f"(format {C.STORE_FORMAT}) does not add to it; use another --out "
            "(fit and report still read it)")


def open_run(cfg: Config, run_dir: Path, seed: int, parallel: cf.Executor | None = None,
             warm: int = 1, shard: tuple[int, int] | None = None,
             measure_on: cf.Executor | None = None) -> tuple[dict, RunLock]:
    """Validate everything, then create or update the run directory under its lock.

    Every check (inputs, store identity, lock) runs before anything is
    created or modified: a refused start leaves an existing run directory
    byte-identical and creates no new one.  Returns the manifest and the held
    lock (the caller releases it).

    ``parallel``: None, or an executor that computes the detection z limit (and, when it
    is the process pool that measures the fields, the placement preflight) while this
    process checks the inputs, and of which ``warm`` workers are asked to import glaciar
    and warm their caches meanwhile (:class:`_SetupJobs`).

    ``shard``: ``(k, n)`` for shard k of n (:mod:`glaciar.shards`).  Its lock
    (:class:`glaciar.rundir.RunLock`) is taken once the inputs are checked, then the
    set-up lock, waiting for a sibling shard's set-up: the manifest is read, the
    fields measured (or a sibling's field caches mapped; caches written at once) and
    the shared files written under it.  A shard whose manifest or stored config
    differs from the run's is refused while a sibling shard runs; identical ones are
    not written again; the field caches are prepared
    (:func:`glaciar.contexts.prepare_context_cache`) before the set-up lock is released.
    A refused shard may leave its (empty) lock file.

    ``measure_on``: None (the fields are measured here, in turn), or an executor (a
    process pool, Dask's) whose workers measure them, one job per field
    (:func:`glaciar.contexts.measure_field`: each writes its field's cache and keeps the
    context for its tasks; this process holds none).  The run's lock is then taken
    before the fields are measured (so it is for a run of several fields, whose caches
    are written as each field is measured); a measurement that fails leaves the run
    directory as it was but for its (empty) lock file.
    """
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise FileExistsError(f"{run_dir}: exists and is not a directory")
    if run_dir.is_dir():
        # A results/, .context/, summary/, ... that is a symbolic link would receive task
        # files, caches and reports outside the run: refused before anything is written.
        check_run_tree(run_dir)
    lock = RunLock(run_dir, shard=shard)
    lock.check_free()
    if shard is not None:
        check_shard_count(run_dir, shard)
    old = read_manifest(run_dir) if run_dir.is_dir() else None
    finished = finished_task_names(run_dir)
    _check_old(run_dir, old, finished)
    cache = _load_fingerprint_cache(run_dir) if run_dir.is_dir() else {}
    cache_before = json.dumps(cache, sort_keys=True)
    survey = Survey.from_config(cfg)
    if isinstance(parallel, cf.ProcessPoolExecutor):
        # Imported here anyway (the input check reads FITS headers and PSFs): before the
        # pool's first job forks its workers, which then inherit it (~0.3 s CPU each).
        import astropy.io.fits  # noqa: F401
    jobs = _SetupJobs(cfg, parallel, warm,
                      preflight=isinstance(measure_on, cf.ProcessPoolExecutor)
                      and parallel is measure_on)
    # A process pool whose workers measure the fields next also checks each field's files.
    inputs = check_inputs(cfg, survey, cache, executor=parallel if jobs.preflight is not None else None)
    _preflight(cfg, survey, jobs)  # before the field is measured: a field nothing fits fails fast
    if shard is not None:
        # A shard locks before it measures: a sibling's set-up is waited for, its field
        # caches then mapped (never measured twice at once); what it wrote is read afresh.
        _create(run_dir)
        lock.acquire()
        try:
            lock.begin_setup()
            check_shard_count(run_dir, shard)
            old, finished = read_manifest(run_dir), finished_task_names(run_dir)
            _check_old(run_dir, old, finished)
        except BaseException:
            lock.release()
            raise
    # Workers that measure the fields write their caches into the run, and so does a run
    # of several fields (each field's context goes before the next is measured: its tasks
    # map the cache instead of measuring the field again): an unsharded run takes its lock
    # first (every check but the measurement itself passed).
    lock_first = shard is None and (measure_on is not None or len(cfg.survey.fields) > 1)
    try:
        manifest = _identity(cfg, run_dir, seed, old, finished, inputs)
        if lock_first:
            _create(run_dir)
            lock.acquire()
        manifest, config_text = _new_manifest(cfg, run_dir, survey, manifest, old, finished,
                                              jobs, measure_on, save=lock_first or shard is not None)
    except BaseException:
        lock.release()
        raise
    # ---- everything is checked: from here on the directory is created or modified ----
    if shard is None and not lock_first:
        _create(run_dir)
        lock.acquire()
    try:
        if shard is None and (read_manifest(run_dir) != old
                              or finished_task_names(run_dir) - finished):
            raise StoreMismatchError(f"{run_dir}: changed while this run was starting (another "
                                     "glaciar run?); run the command again")
        mpath = run_dir / C.MANIFEST_NAME
        cpath = run_dir / C.RUN_CONFIG_NAME
        stale = [p for p, text in ((mpath, manifest_text(manifest)), (cpath, config_text))
                 if not p.exists() or p.read_text(encoding="utf-8") != text]
        differ = [p for p in stale if p.exists()]        # absent: this shard is the first
        if shard is not None and differ:
            _refuse_while_siblings_run(run_dir, shard, differ)
        if mpath in stale:
            write_manifest(run_dir, manifest)
        if cpath in stale:
            atomic_write_text(cpath, config_text)
        _write_fingerprint_cache(run_dir, cache, cache_before, shard)
        if shard is None:
            # Temporary files of tasks that were in flight when an earlier run was killed:
            # removed only while holding the lock, so never those of a live run.
            for tmp in (run_dir / C.RESULTS_DIRNAME).glob(".task_*.tmp"):
                tmp.unlink(missing_ok=True)
        else:
            write_shard_record(run_dir, shard)
            # A shard's own only: its siblings' temporaries may be in flight.
            own = shard_task_names(cfg, shard)
            for tmp in (run_dir / C.RESULTS_DIRNAME).glob(".task_*.tmp"):
                if atomic_temporary_target(tmp) in own:
                    tmp.unlink(missing_ok=True)
            # The field caches (each written once its field was measured, above): those of
            # other configurations go; then the sibling shards may start.
            prepare_context_cache(run_dir, cfg, config_hash(cfg), set(cfg.survey.fields),
                                  keep_temporaries=True)
            lock.end_setup()
    except BaseException:
        lock.release()
        raise
    return manifest, lock


def _identity(cfg, run_dir, seed, old, finished, inputs) -> dict:
    """The run's manifest without its measured records, checked against the store's: a store
    made with other settings, seed or inputs is refused before any field is measured."""
    manifest = _manifest(cfg, seed)
    manifest["inputs"] = _recorded_inputs(old, finished, inputs)
    if old is not None and finished:
        _check_same_store(run_dir, old, manifest, input_files(cfg), finished)
    return manifest


def _create(run_dir: Path) -> None:
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise (disk_full(run_dir, exc) or exc) from None


def _new_manifest(cfg, run_dir, survey, manifest, old, finished, jobs, measure_on=None,
                  save=False):
    """The run's manifest (:func:`_identity`'s, with the fields measured) and stored config text."""
    # An interrupted run left its fields' contexts on disk: with the inputs checked first
    # (the cache's key holds their fingerprints), the resume maps them, not measuring again.
    # ``save`` (the run's lock held: a shard's, which maps a sibling's caches, or a run of
    # several fields) writes each measured field's cache at once; so do workers that
    # measure the fields (measure_on).
    resuming = old is not None and (run_dir / C.CONTEXT_DIRNAME).is_dir()
    cached = None
    if resuming or save or measure_on is not None:
        chash = config_hash(cfg)
        cached = {f: context_dir(run_dir, chash, f, manifest["inputs"]) for f in cfg.survey.fields}
    # Each warning of measuring the fields is said once (not per field or band that repeats it).
    with warnings.catch_warnings(record=True) as measured:
        warnings.simplefilter("always")
        _measure_fields(cfg, survey, manifest, z_limit=jobs.z_limit, cached=cached, save=save,
                        measure_on=measure_on)
    for w in {(str(w.message), w.category): w for w in measured}.values():
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    if old is not None and finished:
        versions = old.get("glaciar_versions") or [old.get("glaciar_version", "?")]
        if __version__ not in versions:
            warnings.warn(f"{run_dir}: started with glaciar {', '.join(map(str, versions))}; "
                          f"glaciar {__version__} adds its tasks", StoreWarning)
        manifest["glaciar_version"] = old.get("glaciar_version", __version__)
        manifest["glaciar_versions"] = sorted(set(map(str, versions)) | {__version__})
    elif old is not None:
        manifest["glaciar_version"] = old.get("glaciar_version", __version__)
    config_text = yaml.safe_dump(config_to_dict(cfg), sort_keys=False, allow_unicode=True)
    return manifest, config_text


def _refuse_while_siblings_run(run_dir: Path, shard: tuple[int, int], stale: list[Path]) -> None:
    """A shard whose manifest or config differs from the run's: refused while a sibling runs
    (its tasks were planned from the stored ones; two plans could give one task two shards)."""
    others = running_shards(run_dir, exclude=shard[0])
    if others:
        k, n = shard
        who = ", ".join(f"{j}/{n} (pid {pid})" for j, pid in others.items())
        raise StoreMismatchError(
            f"{run_dir}: shard {who} is running with another configuration "
            f"({' and '.join(p.name for p in stale)} differ from this shard's); start shard "
            f"{k}/{n} with the same configuration, or once the others have finished")


def _write_fingerprint_cache(run_dir: Path, cache: dict, cache_before: str, shard) -> None:
    """Write the input-fingerprint cache if this run learnt something (a shard: unless the
    file already says it, e.g. a sibling shard wrote the same)."""
    text = json.dumps(cache, sort_keys=True, indent=1)
    path = run_dir / C.FINGERPRINT_CACHE_NAME
    if json.dumps(cache, sort_keys=True) == cache_before:
        return
    if shard is not None and path.is_file() and path.read_text(encoding="utf-8") == text:
        return
    atomic_write_text(path, text)


def _recorded_inputs(old: dict | None, finished, inputs: dict) -> dict:
    """The manifest's input fingerprints: a store with finished tasks keeps the inputs of
    fields no longer listed (they are checked if the field returns)."""
    if old is not None and finished:
        return {**(old.get("inputs") or {}), **inputs}
    return inputs


def _z_limit_job(cfg_dict: dict, base_dir: str) -> tuple[float | None, list]:
    """:func:`glaciar.plan.detection_z_limit` on an executor's worker: ``(z limit, warnings)``,
    the warnings as ``(message, category)`` pairs for the run's own process to raise."""
    cfg = config_from_dict(cfg_dict, base_dir)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        z_limit = detection_z_limit(cfg)
    return z_limit, [(str(w.message), w.category) for w in caught]


class _Later:
    """A future computed when its result is first asked for."""

    def __init__(self, fn, *args):
        self._call, self._done, self._value = (fn, args), False, None

    def result(self):
        if not self._done:
            fn, args = self._call
            self._value, self._done = fn(*args), True
        return self._value


def _prewarm(cfg_dict: dict, base_dir: str) -> None:
    """In a spawned worker, during the run's set-up: what its first task would do before its
    sources -- imports, the first field's settings (PSFs, filters, cosmology) and the SED
    colour tables of the run's redshifts (each cached per process, ~0.7 s for the demo).

    Its warnings are dropped: whatever it reads, the run's own checks read and report (a
    forked worker would print them with the CLI's inherited warning format, before the
    input check's one-line error about the same file)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _warm(cfg_dict, base_dir)


def _warm(cfg_dict: dict, base_dir: str) -> None:
    cfg = config_from_dict(cfg_dict, base_dir)
    survey = Survey.from_config(cfg)
    settings, _ = field_settings(cfg, survey, cfg.survey.fields[0])
    igm = settings["source_model"].igm
    for z in sorted({float(s.z) for s in plan_tasks(cfg)}):
        if cfg.grid.magnitude_type == "absolute":
            sed.band_magnitudes(z, np.zeros(1), settings["filters"], M_uv=np.full(1, -20.0),
                                cosmology=settings["cosmology"], igm=igm)
        else:
            sed.band_magnitudes(z, np.zeros(1), settings["filters"], mag=np.full(1, 25.0),
                                detection_index=settings["detection_index"], igm=igm)


def _preflight_job(cfg_dict: dict, base_dir: str) -> tuple[list[str], list]:
    """:func:`glaciar.plan.placement_preflight` on a pool's worker: ``(messages, warnings)``."""
    cfg = config_from_dict(cfg_dict, base_dir)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        messages = placement_preflight(cfg, Survey.from_config(cfg))
    clear_survey_cache()        # the footprints' images: the worker measures one field next
    return messages, [(str(w.message), w.category) for w in caught]


def _preflight(cfg: Config, survey: Survey, jobs: "_SetupJobs | None" = None) -> None:
    """Raise :func:`glaciar.plan.placement_preflight`'s error (no source fits a field) or warn
    its messages (computed by ``jobs``' worker, if it has the job)."""
    later = None if jobs is None else jobs.preflight
    for message in (placement_preflight(cfg, survey) if later is None else later.result()):
        if "no source fits" in message:
            raise ValueError(message)
        warnings.warn(message, UserWarning)


class _SetupJobs:
    """The jobs a run's executor does while this process checks the inputs and measures the field.

    With an executor (e.g. Dask's): :func:`glaciar.plan.detection_z_limit` (a
    bisection over the SED, a pure function of the configuration) on one of its
    workers, which then also imports glaciar before its first task, and ``warm - 1``
    jobs that set up what a first task needs (:func:`_prewarm`) for other workers; with
    ``preflight`` (a process pool whose workers measure the fields next, issue 24) also
    :func:`glaciar.plan.placement_preflight` on one of them.  Without one, the z limit is computed here when the manifest asks for it.  (The
    input check and the preflight ran in a forked helper beside the field's
    measurement until issue 22; ``benchmarks/setup_helper.py`` of commit faa86f5
    measured no gain: 0.90x on the demo, 1 and 2 workers.)
    """

    def __init__(self, cfg: Config, where: cf.Executor | None, warm: int = 1,
                 preflight: bool = False):
        self.z_limit = self.preflight = None
        if where is None:
            return
        args = (config_to_dict(cfg), str(cfg.base_dir))
        job = where.submit(_z_limit_job, *args)
        if preflight:
            # A process pool whose workers measure the fields next: the preflight (each
            # field's footprint and a random fill, ~0.35 s per 1000^2 field) runs on one
            # of them while this process checks the inputs.
            self.preflight = _Later(self._result, where.submit(_preflight_job, *args))
        # Spawned workers import glaciar and set up a field's settings and colour tables
        # when their first task arrives (~2 s each): jobs that only do that let up to
        # ``warm`` workers do it now, beside the set-up.
        for _ in range(max(0, warm - 1)):
            where.submit(_prewarm, *args)
        self.z_limit = _Later(self._result, job)

    @staticmethod
    def _result(job):
        z_limit, caught = job.result()
        for message, category in caught:
            warnings.warn(message, category)
        return z_limit


def prepare_run_dir(cfg: Config, run_dir: Path, seed: int) -> dict:
    """Create or validate the run directory and return its manifest.

    A store made with other science settings, another seed, changed input
    files (by content) or an older store format is refused.  A config that
    only adds (or drops) fields, grid values or iterations is accepted:
    finished tasks keep their rows, and the manifest and the stored config are
    updated to describe the run as now configured.  Nothing is created or
    modified unless every check passes.
    """
    manifest, lock = open_run(cfg, Path(run_dir), seed)
    lock.release()
    return manifest
