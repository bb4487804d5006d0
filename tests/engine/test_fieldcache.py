"""Field contexts on disk (glaciar.engine.fieldcache, glaciar.contexts' field cache).

* Round trip: every array, nested dataclass and scalar comes back equal; large
  arrays as read-only native-endian memory maps, small ones in memory; no pickle
  (object arrays and unknown classes are refused).
* Writing is atomic and a second writer of the same cache keeps the first copy.
* A context opened from its cache gives the same task rows as the one built in
  memory, and a run keeps its cache exactly while it has pending tasks.
* Dropping mapped pages returns them (resident file-backed memory, /proc).
"""
from __future__ import annotations

import os
import sys

import numpy as np
import pytest

import glaciar.constants as C
from glaciar import contexts, fieldprep
from glaciar.config import config_hash, load_config
from glaciar.engine import fieldcache
from glaciar.engine.measure import FieldReference
from glaciar.engine.noise import CorrelatedNoise
from glaciar.engine.canvas import ObjectBoxes
from glaciar.execute import simulate
from glaciar.survey import Survey


def _tree():
    rng = np.random.default_rng(0)
    big = rng.normal(size=(600, 700)).astype(">f4")            # 1.7 MB, big-endian like FITS
    big[3, 4] = np.nan
    cat = np.zeros(3, dtype=[("x", "f8"), ("flag", "i2"), ("npix", "i8")])
    cat["x"] = [1.5, 2.5, np.inf]
    ref = FieldReference(segmap=rng.integers(0, 5, (600, 700)).astype(np.int32),
                         flux=np.array([1.0, np.nan]), mag=np.array([25.0, np.nan]), catalog=cat,
                         objects=ObjectBoxes.build(np.array([[0, 5, 0, 5], [10, 20, 30, 40]]),
                                                   np.array([[0, 6, 0, 6], [9, 21, 29, 41]]),
                                                   (600, 700)))
    return {"bases": {"f160w": big, "f125w": big[::-1].astype(np.float32)},
            "mask": big > 1.0, "reference": ref, "count": 12, "nothing": None,
            "noise": {"f160w": CorrelatedNoise.fit([1, 10, 100], [1.0, 1.4, 2.0], [5, 6, 7])},
            "bands": ("f160w", "f125w"), "method": "ivw", "small": np.arange(5, dtype=np.int64)}


def mapped_view(a) -> bool:
    """``a`` is a plain ndarray over a memory map (how the cache hands arrays out)."""
    return type(a) is np.ndarray and isinstance(a.base, np.memmap)


def _assert_same_measured(ctx, built):
    """The measured arrays of ``ctx`` equal those of the in-memory context ``built``."""
    for b in built.bands:
        np.testing.assert_array_equal(ctx.bases[b], built.bases[b])
        np.testing.assert_array_equal(ctx.rms[b], built.rms[b])
    for name in ("mask", "footprint", "depth", "detection_background"):
        np.testing.assert_array_equal(getattr(ctx, name), getattr(built, name))
    np.testing.assert_array_equal(ctx.reference.segmap, built.reference.segmap)
    assert ctx.measured_noise == built.measured_noise


def test_round_trip_values_types_and_maps(tmp_path):
    tree = _tree()
    path = fieldcache.save(tree, tmp_path / "ctx")
    got, maps = fieldcache.load(path)
    big = got["bases"]["f160w"]
    # Mapped (the map is the array's base and among ``maps``), handed out as a plain ndarray:
    # np.memmap's Python-level slicing costs every task window ~2 us.
    assert type(big) is np.ndarray and isinstance(big.base, np.memmap)
    assert any(m is big.base._mmap for m in maps)
    assert not big.flags.writeable and big.dtype.isnative
    assert big.dtype == np.float32
    np.testing.assert_array_equal(big, tree["bases"]["f160w"].astype(np.float32))   # NaN too
    np.testing.assert_array_equal(got["bases"]["f125w"], tree["bases"]["f125w"])
    np.testing.assert_array_equal(got["mask"], tree["mask"])
    ref, want = got["reference"], tree["reference"]
    assert isinstance(ref, FieldReference) and isinstance(ref.objects, ObjectBoxes)
    np.testing.assert_array_equal(ref.segmap, want.segmap)
    np.testing.assert_array_equal(ref.flux, want.flux)
    assert ref.catalog.dtype == want.catalog.dtype and np.array_equal(ref.catalog, want.catalog)
    for name in ("region", "need", "start", "ids"):
        np.testing.assert_array_equal(getattr(ref.objects, name), getattr(want.objects, name))
    assert (ref.objects.cell, ref.objects.ncx) == (want.objects.cell, want.objects.ncx)
    assert got["noise"] == tree["noise"]                  # frozen dataclass of tuples
    assert got["bands"] == ("f160w", "f125w") and got["method"] == "ivw"
    assert got["count"] == 12 and got["nothing"] is None
    small = got["small"]
    assert type(small) is np.ndarray and small.flags.writeable       # read into memory
    np.testing.assert_array_equal(small, np.arange(5))
    # one map per array of at least MMAP_MIN_BYTES: two bases and the segmap
    assert len(maps) == 3
    # no temporary directory left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ctx"]


def test_nothing_pickled(tmp_path):
    with pytest.raises(TypeError, match="Python objects"):
        fieldcache.save({"a": np.array([object()], dtype=object)}, tmp_path / "x")

    class Other:
        pass

    with pytest.raises(TypeError, match="cannot store"):
        fieldcache.save({"a": Other()}, tmp_path / "y")
    assert list(tmp_path.iterdir()) == []                 # nothing half-written stays
    path = fieldcache.save({"a": np.zeros(3)}, tmp_path / "z")
    index = (path / fieldcache.INDEX_NAME).read_text()
    (path / fieldcache.INDEX_NAME).write_text(index.replace('"npy"', '"dataclass": "os:system", "fields": {}, "x"'))
    with pytest.raises(ValueError, match="unknown class 'os:system'"):
        fieldcache.load(path)
    for name in os.listdir(path):
        if name.endswith(".npy"):
            with open(path / name, "rb") as fh:
                assert b"pickle" not in fh.read(256).lower()


def test_second_writer_keeps_the_first_copy(tmp_path):
    first = fieldcache.save({"a": np.arange(3)}, tmp_path / "c")
    fieldcache.save({"a": np.arange(4)}, tmp_path / "c")
    got, _ = fieldcache.load(first)
    np.testing.assert_array_equal(got["a"], np.arange(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c"]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status")
def test_released_pages_leave_the_resident_set(tmp_path):
    def rss_file():
        for line in open("/proc/self/status"):
            if line.startswith("RssFile:"):
                return int(line.split()[1]) * 1024
        raise AssertionError("no RssFile")

    n = 64 << 20
    path = fieldcache.save({"a": np.ones(n // 8)}, tmp_path / "c")
    got, maps = fieldcache.load(path)
    trimmer = fieldcache.Trimmer(maps, budget=16 << 20)
    patient = fieldcache.Trimmer(maps, budget=1 << 40)
    before = rss_file()
    assert float(got["a"].sum()) == n // 8                 # every page touched
    touched = rss_file()
    assert touched - before > 0.9 * n
    assert not patient()                                    # under its budget: kept
    assert trimmer() and trimmer.releases == 1              # over its budget: dropped
    assert rss_file() - before < 0.1 * n
    assert float(got["a"][::4096].sum()) == n // 8 // 4096  # still readable afterwards


# --------------------------------------------------------------------------
# The context of a field, through glaciar.fieldprep and glaciar.contexts
# --------------------------------------------------------------------------
def test_opened_context_equals_the_built_one(small_survey, tmp_path, monkeypatch, assert_same_outputs):
    from glaciar.engine.task import TaskSpec, run_task

    monkeypatch.setattr(fieldcache, "MMAP_MIN_BYTES", 1)     # map every array of the small field
    cfg = load_config(small_survey)
    survey = Survey.from_config(cfg)
    field = cfg.survey.fields[0]
    built = fieldprep.build_field_context(cfg, survey, field)
    mapped = contexts.save_field_context(built, tmp_path / "ctx")
    opened = contexts.open_field_context(cfg, survey, field, tmp_path / "ctx")
    for ctx in (mapped, opened):
        assert mapped_view(ctx.bases[cfg.survey.detection_band])
        assert ctx.footprint_count == int(built.footprint.sum())
        _assert_same_measured(ctx, built)
    for it in range(2):
        spec = TaskSpec(field=field, field_index=0, z_index=0, mag_index=0, iteration=it,
                        z=8.0, mag=26.0)
        want = run_task(built, spec, 3)
        assert_same_outputs(run_task(opened, spec, 3), want, "opened")
        assert_same_outputs(run_task(mapped, spec, 3), want, "mapped")


def test_tiled_context_gives_the_same_rows(small_survey, tmp_path, monkeypatch, assert_same_outputs):
    """A field whose maps exceed the resident budget is cached as tiles: same arrays, same rows
    (windowed and full-frame detection)."""
    from glaciar.engine.task import TaskSpec, run_task

    monkeypatch.setattr(fieldcache, "RESIDENT_BUDGET_BYTES", 0)
    monkeypatch.setattr(fieldcache, "MMAP_MIN_BYTES", 1)
    cfg = load_config(small_survey)
    survey = Survey.from_config(cfg)
    field = cfg.survey.fields[0]
    built = fieldprep.build_field_context(cfg, survey, field)
    tiled = contexts.save_field_context(built, tmp_path / "ctx")
    det = cfg.survey.detection_band
    assert isinstance(tiled.bases[det], fieldcache.TiledArray)
    assert isinstance(tiled.reference.segmap, fieldcache.TiledArray)
    assert isinstance(tiled.mask, fieldcache.TiledArray)
    assert mapped_view(tiled.depth)         # read at points only: row-major
    for b in built.bands:
        np.testing.assert_array_equal(np.asarray(tiled.bases[b]), built.bases[b])
        np.testing.assert_array_equal(np.asarray(tiled.rms[b]), built.rms[b])
    np.testing.assert_array_equal(np.asarray(tiled.reference.segmap), built.reference.segmap)
    for it, mode in ((0, "windowed"), (1, "windowed"), (0, "full")):
        spec = TaskSpec(field=field, field_index=0, z_index=0, mag_index=0, iteration=it,
                        z=8.0, mag=26.0)
        assert_same_outputs(run_task(tiled, spec, 3, mode=mode), run_task(built, spec, 3, mode=mode),
                            f"tiled {mode}")


@pytest.mark.parametrize("read", [True, False], ids=["preadv", "mapped"])
@pytest.mark.parametrize("shape,tile", [((300, 257), 128), ((128, 128), 128), ((1, 5), 16),
                                        ((37, 1), 8), ((200, 333), 64), ((9, 7), 1)])
def test_tiled_array_indexes_like_the_array(tmp_path, monkeypatch, shape, tile, read):
    """Any tiling, read with positional reads or through a memory map, gives what plain numpy
    indexing of the array gives (windows clipped as numpy clips them, points, rows)."""
    if read and not hasattr(os, "preadv"):
        pytest.skip("no os.preadv")
    monkeypatch.setattr(fieldcache, "READ_TILES", read)
    rng = np.random.default_rng(sum(shape))
    want = rng.normal(size=shape).astype(">f4")
    path = fieldcache.save({"a": fieldcache.Tiled(want, tile), "m": fieldcache.Tiled(want > 0, tile)},
                           tmp_path / "c")
    items, maps = fieldcache.load(path)
    a, m = items["a"], items["m"]
    want = want.astype(np.float32)
    assert a.shape == shape and a.dtype == np.float32 and a.ndim == 2 and len(a) == shape[0]
    assert (a.tiles is None) == read and (not maps) == read
    np.testing.assert_array_equal(np.asarray(a), want)
    np.testing.assert_array_equal(np.asarray(m), want > 0)
    if not read:
        # mapped: the tiles start at a 64 kB boundary of the file (page-aligned tiles)
        assert a.tiles.offset % fieldcache.TILE_ALIGN == 0 and not a.tiles.flags.writeable
    ny, nx = shape
    for _ in range(200):
        y0, y1 = np.sort(rng.integers(-ny - 3, ny + 3, 2))
        x0, x1 = np.sort(rng.integers(-nx - 3, nx + 3, 2))
        np.testing.assert_array_equal(a[y0:y1, x0:x1], want[y0:y1, x0:x1])
        np.testing.assert_array_equal(m[y0:y1, x0:x1], (want > 0)[y0:y1, x0:x1])
        np.testing.assert_array_equal(a[y0:, :x1], want[y0:, :x1])
        iy, ix = rng.integers(-ny, ny, (4, 3)), rng.integers(-nx, nx, 3)
        np.testing.assert_array_equal(a[iy, ix], want[iy, ix])
        i, j = int(rng.integers(-ny, ny)), int(rng.integers(-nx, nx))
        assert a[i, j] == want[i, j] and a[np.int64(i), j] == want[i, j]
        np.testing.assert_array_equal(a[i], want[i])
        np.testing.assert_array_equal(a[i, x0:x1], want[i, x0:x1])
        np.testing.assert_array_equal(a[y0:y1, j], want[y0:y1, j])
    np.testing.assert_array_equal(a[::2, ::-1], want[::2, ::-1])       # through the whole frame
    with pytest.raises(IndexError):
        a[np.array([ny]), np.array([0])]
    fieldcache.release(maps)


@pytest.mark.skipif(not hasattr(os, "preadv"), reason="no os.preadv")
def test_read_tiles_survive_pickle_and_fork_and_refuse_a_truncated_file(tmp_path):
    """A tiled array read from its file is sent to another process as its path and read by a
    forked child through the inherited descriptor (positional reads share no offset)."""
    import multiprocessing
    import pickle

    want = np.random.default_rng(5).normal(size=(150, 170)).astype(np.float32)
    path = fieldcache.save({"a": fieldcache.Tiled(want, 32)}, tmp_path / "c")
    a = fieldcache.load(path)[0]["a"]
    b = pickle.loads(pickle.dumps(a))
    assert b.tiles is None and b.path == a.path
    np.testing.assert_array_equal(b[10:100, 33:160], want[10:100, 33:160])
    ctx = multiprocessing.get_context("fork") if sys.platform.startswith("linux") else None
    if ctx is not None:
        a[0:5, 0:5]                                  # the parent read before the fork too
        with ctx.Pool(1) as pool:
            got = pool.apply(_window_sum, (a, 7, 140, 3, 150))
        assert got == float(want[7:140, 3:150].astype(np.float64).sum())
    name = a.path
    with open(name, "r+b") as fh:
        fh.truncate(os.path.getsize(name) - 4)
    with pytest.raises(ValueError, match="truncated"):
        fieldcache.TiledArray.open(name, (150, 170))


def _window_sum(a, y0, y1, x0, x1):
    return float(a[y0:y1, x0:x1].astype(np.float64).sum())


@pytest.mark.skipif(not (sys.platform.startswith("linux") and hasattr(os, "preadv")),
                    reason="reads /proc/self/statm; os.preadv")
def test_window_reads_leave_nothing_resident(tmp_path, monkeypatch):
    """Random windows of a tiled array read with positional reads add no file-backed resident
    pages (the page cache's folios are not mapped into the process), however many are read;
    the pixels equal numpy's."""
    monkeypatch.setattr(fieldcache, "READ_TILES", True)
    side = 2048
    want = np.random.default_rng(6).normal(size=(side, side)).astype(np.float32)   # 16 MB
    a = fieldcache.load(fieldcache.save({"a": fieldcache.Tiled(want)}, tmp_path / "c"))[0]["a"]
    rng = np.random.default_rng(7)
    before = fieldcache._file_resident_bytes()
    read = 0
    for y0, x0, h, w in zip(*rng.integers(0, side - 200, (2, 400)), *rng.integers(1, 200, (2, 400))):
        got = a[y0:y0 + h, x0:x0 + w]
        read += got.nbytes
        assert np.array_equal(got, want[y0:y0 + h, x0:x0 + w])
    grown = fieldcache._file_resident_bytes() - before
    assert read > 8 << 20 and grown < 1 << 20, (read, grown)


def test_spilled_build_equals_the_in_memory_one(small_survey, tmp_path, monkeypatch,
                                                assert_same_outputs):
    """A large field is measured with its finished arrays on disk (unnamed files): same arrays,
    same rows, and no file left in the scratch directory."""
    from glaciar.engine.task import TaskSpec, run_task

    cfg = load_config(small_survey)
    field = cfg.survey.fields[0]
    built = fieldprep.build_field_context(cfg, Survey.from_config(cfg), field)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    monkeypatch.setattr(fieldprep, "SPILL_MIN_BYTES", 0)
    monkeypatch.setattr(fieldcache, "SCRATCH_DIR", str(scratch))
    spilled = fieldprep.build_field_context(cfg, Survey.from_config(cfg), field)
    assert list(scratch.iterdir()) == []
    det = cfg.survey.detection_band
    assert isinstance(spilled.bases[det], np.memmap) and isinstance(spilled.depth, np.memmap)
    assert isinstance(spilled.reference.segmap, np.memmap)
    _assert_same_measured(spilled, built)
    spec = TaskSpec(field=field, field_index=0, z_index=0, mag_index=0, iteration=0, z=8.0, mag=26.0)
    assert_same_outputs(run_task(spilled, spec, 3), run_task(built, spec, 3), "spilled")


def test_run_keeps_its_cache_while_tasks_are_pending(small_survey, tmp_path):
    cfg = load_config(small_survey)
    out = tmp_path / "run"
    contexts.clear_contexts()
    stats = simulate(cfg, out, workers=1, progress=False, max_tasks=3)
    assert stats["n_run"] == 3
    entries = list((out / C.CONTEXT_DIRNAME).iterdir())
    assert len(entries) == 1 and fieldcache.exists(entries[0])
    assert entries[0] == contexts.context_dir(out, config_hash(cfg), cfg.survey.fields[0])
    # a changed configuration (more iterations: a resume may add them) gets a new cache;
    # the old one goes, and the finished run leaves none
    more = cfg.model_copy(update={"simulation": cfg.simulation.model_copy(
        update={"n_iterations": cfg.simulation.n_iterations + 1})})
    simulate(more, out, workers=1, progress=False, max_tasks=1)
    now = list((out / C.CONTEXT_DIRNAME).iterdir())
    assert len(now) == 1 and now != entries
    stats = simulate(more, out, workers=1, progress=False)
    assert stats["n_done_before"] + stats["n_run"] == stats["n_tasks"]
    assert not (out / C.CONTEXT_DIRNAME).exists()


def test_resume_maps_the_cache_instead_of_measuring_the_field(small_survey, tmp_path, monkeypatch):
    """An interrupted run's resume maps its field cache (the field is not measured again),
    and its manifest and rows equal an uninterrupted run's."""
    from glaciar.store import read_results
    from glaciar.rundir import read_manifest

    cfg = load_config(small_survey)
    contexts.clear_contexts()
    whole = tmp_path / "whole"
    simulate(cfg, whole, workers=1, progress=False)
    contexts.clear_contexts()
    out = tmp_path / "resumed"
    simulate(cfg, out, workers=1, progress=False, max_tasks=3)
    contexts.clear_contexts()                      # a new process: nothing kept in memory

    def refuse(*args, **kwargs):
        raise AssertionError("the field was measured again")

    monkeypatch.setattr(contexts, "build_field_context", refuse)
    stats = simulate(cfg, out, workers=1, progress=False)
    assert stats["n_done_before"] == 3 and stats["n_done_before"] + stats["n_run"] == stats["n_tasks"]
    assert read_manifest(out) == read_manifest(whole)
    key = [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]
    a = read_results(whole).sort_values(key, ignore_index=True)
    b = read_results(out).sort_values(key, ignore_index=True)
    assert len(a) > 0 and a.equals(b)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/statm")
def test_watching_thread_drops_pages_during_a_task(tmp_path):
    """Maps larger than the budget are watched from a thread: pages touched by a long task
    are dropped without the task returning; maps within the budget are not watched."""
    import time

    n = 64 << 20
    path = fieldcache.save({"a": np.ones(n // 8)}, tmp_path / "c")
    got, maps = fieldcache.load(path)
    assert not fieldcache.Trimmer(maps, budget=2 * n).watch()
    trimmer = fieldcache.Trimmer(maps, budget=16 << 20, period=0.01)
    assert trimmer.watch()
    try:
        assert float(got["a"].sum()) == n // 8              # every page touched
        deadline = time.monotonic() + 5.0
        while trimmer.releases == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert trimmer.releases >= 1
    finally:
        trimmer.unwatch()
    assert trimmer._watcher is None


def _resident_kb_by_file(directory) -> dict:
    """Resident kB of each file of ``directory`` mapped by this process (/proc/self/smaps)."""
    import re

    out, cur = {}, None
    with open("/proc/self/smaps") as fh:
        for line in fh:
            m = re.match(r"^[0-9a-f]+-[0-9a-f]+ \S+ \S+ \S+ \S+\s+(.*)$", line)
            if m:
                cur = m.group(1).strip()
            elif line.startswith("Rss:") and cur and cur.startswith(str(directory)):
                name = os.path.basename(cur)
                out[name] = out.get(name, 0) + int(line.split()[1])
    return out


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/smaps")
def test_a_task_touches_only_pages_under_its_windows(tmp_path):
    """On a 2000^2 demo field, a 5-source task leaves a small fraction of every mapped array
    resident (~13 % measured: 64 kB fault-around blocks under ~5 x 80 window rows): no
    per-task step reads a whole frame (one would leave that file ~100 % resident)."""
    import dataclasses

    from glaciar.demo import build_demo_survey
    from glaciar.engine.task import TaskSpec, run_task

    cfg = load_config(build_demo_survey(tmp_path / "s", shape=(2000, 2000), seed=3, n_galaxies=5,
                                        n_iterations=1, z_values=(8.0,), mag_values=(26.0,)))
    field = cfg.survey.fields[0]
    ctx = contexts.save_field_context(fieldprep.build_field_context(cfg, Survey.from_config(cfg), field),
                                 tmp_path / "ctx")
    sizes = {p.name: p.stat().st_size / 1024 for p in (tmp_path / "ctx").glob("*.npy")}
    spec = TaskSpec(field=field, field_index=0, z_index=0, mag_index=0, iteration=0, z=8.0, mag=26.0)
    run_task(ctx, spec, 1)                             # warm the template caches
    for seed in (2, 3):
        fieldcache.release(ctx._trimmer.maps)
        table = run_task(dataclasses.replace(ctx, n_galaxies=5), spec, seed)
        assert len(table) == 5
        got = _resident_kb_by_file(tmp_path / "ctx")
        assert got, "no mapped file resident"
        frac = {k: v / sizes[k] for k, v in got.items()}
        assert max(frac.values()) < 0.4, frac
        assert sum(got.values()) < 0.25 * sum(sizes[k] for k in got)


def test_unwritable_cache_keeps_the_field_in_memory(small_survey, tmp_path):
    cfg = load_config(small_survey)
    ctx = fieldprep.build_field_context(cfg, Survey.from_config(cfg), cfg.survey.fields[0])
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.warns(UserWarning, match="field cache not written"):
        same = contexts.save_field_context(ctx, blocker / "ctx")
    assert same is ctx and same._trimmer is None


def _child_trims(trimmer, array, queue):
    before = trimmer()                           # as _run_chunk, before its first task
    queue.put((before, float(array.sum()), trimmer(), trimmer.releases))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork and /proc/self/statm")
def test_forked_child_trims_with_its_own_lock(tmp_path):
    """A worker forked while the parent held the trimmer's lock still trims (own lock)."""
    import multiprocessing

    path = fieldcache.save({"a": np.ones((32 << 20) // 8)}, tmp_path / "c")
    got, maps = fieldcache.load(path)
    trimmer = fieldcache.Trimmer(maps, budget=4 << 20)
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    with trimmer._lock:                          # held at the fork
        child = ctx.Process(target=_child_trims, args=(trimmer, got["a"], queue))
        child.start()
    before, total, trimmed, releases = queue.get(timeout=60)
    child.join(60)
    assert child.exitcode == 0
    assert not before and total == (32 << 20) // 8 and trimmed and releases == 1
    assert trimmer.releases == 0                 # the parent's count is its own
