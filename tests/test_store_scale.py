"""The store at scale (issue 8, point 3): counts beside the rows, compaction, regions per field.

Most tests use tiny synthetic stores written with :func:`glaciar.store.write_task_table`
(no simulation); the resume tests simulate 4 tasks of 3 sources on the small survey.
"""
import json
import shutil
import warnings
from collections import Counter

import numpy as np
import pandas as pd
import pytest
import yaml

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.inference.fit import aggregate_cells
from glaciar.pipeline.inputs import fit_inputs
from glaciar.execute import simulate
from glaciar.store import (COMPACT_DIRNAME, task_key, StoreWarning, compact, finished_task_names,
                           read_current_counts, read_current_results, read_results, task_filename,
                           verified_task_names, write_task_table)
from glaciar.rundir import write_manifest
from glaciar.counting import STATUS_COLUMNS
from glaciar.tables import region_file, summary_table, write_regions

FIELDS = ("f a", "g")
ZS = (8.0, 9.0)
MAGS = (24.0, 25.5)
N_ITER = 3


def _task_rows(rng, field, z, mag, it, n=25):
    status = rng.choice(C.STATUS_CODES, size=n, p=[.45, .05, .05, .05, .1, .3])
    rec = np.isin(status, C.RECOVERED_STATUSES)
    return pd.DataFrame({
        C.COL_FIELD: field, C.COL_Z: z, C.COL_MAG: mag, C.COL_ITERATION: it,
        C.COL_SOURCE: np.arange(n),
        C.COL_X: rng.uniform(0, 100, n), C.COL_Y: rng.uniform(0, 100, n),
        C.COL_DEPTH: 26.6 + rng.uniform(0.0, 0.5, n),
        # A continuous covariate (as M_uv or mag_input with a spread of UV slopes).
        C.COL_MAG_INPUT: mag + rng.normal(0.0, 0.08, n),
        C.COL_STATUS: status, C.COL_RECOVERED: rec,
        C.COL_SELECTED: rec & (rng.uniform(size=n) < 0.7)})


def _synthetic_store(run_dir, seed=0, mag_column=C.COL_MAG_INPUT):
    """A store of 2 fields x 2 z x 2 mags x 3 iterations; returns all rows."""
    rng = np.random.default_rng(seed)
    frames = []
    for f in FIELDS:
        for z in ZS:
            for m in MAGS:
                for it in range(N_ITER):
                    t = _task_rows(rng, f, z, m, it)
                    write_task_table(run_dir, task_filename(f, z, m, it), t,
                                     key=task_key(f, z, m, it), mag_column=mag_column)
                    frames.append(t)
    write_manifest(run_dir, {"fields": list(FIELDS), "z_values": list(ZS),
                             "mag_values": list(MAGS), "n_iterations": N_ITER})
    return pd.concat(frames, ignore_index=True)


def _wanted():
    return {task_filename(f, z, m, it): task_key(f, z, m, it)
            for f in FIELDS for z in ZS for m in MAGS for it in range(N_ITER)}


def _sorted(df):
    keys = [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]
    return df.sort_values(keys).reset_index(drop=True)


def _independent_counts(rows):
    """{group key: [n, k_rec, k_sel, n per status...]} by a plain loop over sources."""
    out = {}
    for r in rows.itertuples(index=False):
        d = getattr(r, C.COL_DEPTH)
        key = (r.field, r.z, r.mag, r.iteration, round(r.mag_input * 100), int(d // 0.05))
        acc = out.setdefault(key, [0, 0, 0] + [0] * len(STATUS_COLUMNS))
        acc[0] += 1
        acc[1] += bool(r.recovered)
        acc[2] += bool(r.selected)
        acc[3 + list(STATUS_COLUMNS).index(int(r.status))] += 1
    return out


def test_counts_equal_an_independent_count_of_the_rows(tmp_path):
    rows = _synthetic_store(tmp_path)
    counts, mag_col = read_current_counts(tmp_path, merge_iterations=False)
    assert mag_col == C.COL_MAG_INPUT
    ref = _independent_counts(rows)
    got = {(r.field, r.z, r.mag, r.iteration, int(r.mag_key), int(r.depth_key)):
           [r.n, r.k_recovered, r.k_selected] + [getattr(r, c) for c in STATUS_COLUMNS.values()]
           for r in counts.itertuples(index=False)}
    assert got == ref
    # Sums and extremes per group against the rows.
    assert np.isclose(counts["sum_mag"].sum(), rows[C.COL_MAG_INPUT].sum(), rtol=1e-13)
    assert np.isclose(counts["sum_depth"].sum(), rows[C.COL_DEPTH].sum(), rtol=1e-13)
    assert counts["mag_min"].min() == rows[C.COL_MAG_INPUT].min()
    assert counts["depth_max"].max() == rows[C.COL_DEPTH].max()
    # Merged over iterations: the same totals, fewer groups.
    merged, _ = read_current_counts(tmp_path)
    assert C.COL_ITERATION not in merged.columns and len(merged) < len(counts)
    assert merged["n"].sum() == len(rows) and merged["k_selected"].sum() == rows["selected"].sum()


def test_fit_cells_from_counts_equal_aggregate_cells_of_the_rows(tmp_path):
    rows = _synthetic_store(tmp_path)
    data = fit_inputs(tmp_path, C.COL_MAG_INPUT, 0.01)
    assert data.from_counts
    a = aggregate_cells(rows, 0.01, None, C.COL_MAG_INPUT)
    b = data.cells(0.01, None, C.COL_MAG_INPUT)
    for name in ("n", "k_rec", "k_sel"):
        np.testing.assert_array_equal(getattr(b, name), getattr(a, name))
    # Means of the same sources, summed in another order.
    np.testing.assert_allclose(b.z, a.z, rtol=1e-14, atol=0)
    np.testing.assert_allclose(b.mag, a.mag, rtol=1e-14, atol=0)
    # Another resolution than the counts' key: the rows are read, exactly as before.
    rdata = fit_inputs(tmp_path, C.COL_MAG_INPUT, 0.02)
    assert not rdata.from_counts
    c = rdata.cells(0.02, None, C.COL_MAG_INPUT)
    np.testing.assert_array_equal(c.n, aggregate_cells(rows, 0.02, None, C.COL_MAG_INPUT).n)


def test_depth_aware_cells_from_counts_keep_every_source_and_the_mean_covariate(tmp_path):
    rows = _synthetic_store(tmp_path)
    ref = 26.85
    a = aggregate_cells(rows, 0.01, ref, C.COL_MAG_INPUT)
    b = fit_inputs(tmp_path, C.COL_MAG_INPUT, 0.01).cells(0.01, ref, C.COL_MAG_INPUT)
    assert b.n.sum() == a.n.sum() and b.k_rec.sum() == a.k_rec.sum()
    assert b.k_sel.sum() == a.k_sel.sum()
    # The mean covariate over all sources is exact; cells differ by at most a depth bin.
    assert np.isclose(np.sum(b.mag * b.n), np.sum(a.mag * a.n), rtol=1e-13)
    # A count group spans <= 0.01 + 0.05 mag of covariate: its cell is within that of the rows'.
    assert a.mag.min() - 0.06 <= b.mag.min() and b.mag.max() <= a.mag.max() + 0.06


def test_summary_from_counts_equals_summary_from_rows(tmp_path):
    rows = _synthetic_store(tmp_path)
    counts, _ = read_current_counts(tmp_path)
    for f in FIELDS:
        pd.testing.assert_frame_equal(summary_table(counts[counts[C.COL_FIELD] == f]),
                                      summary_table(rows[rows[C.COL_FIELD] == f]))
    pd.testing.assert_frame_equal(summary_table(counts), summary_table(rows))


def test_counts_follow_the_manifest_like_the_rows(tmp_path):
    _synthetic_store(tmp_path)
    write_manifest(tmp_path, {"fields": ["g"], "z_values": [8.0], "mag_values": list(MAGS),
                              "n_iterations": 2})
    with pytest.warns(StoreWarning, match="ignoring") as w_rows:
        rows = read_current_results(tmp_path)
    with pytest.warns(StoreWarning, match="ignoring") as w_counts:
        counts, _ = read_current_counts(tmp_path)
    assert str(w_rows[0].message) == str(w_counts[0].message)
    pd.testing.assert_frame_equal(summary_table(counts), summary_table(rows))


def test_compaction_keeps_every_row_and_count_once(tmp_path):
    rows = _synthetic_store(tmp_path)
    before, _ = read_current_counts(tmp_path)
    assert compact(tmp_path, min_tasks=100) == 0            # below the threshold: nothing
    assert compact(tmp_path) == len(_wanted())
    res = tmp_path / C.RESULTS_DIRNAME
    assert not list(res.glob("task_*.parquet"))
    parts = sorted((res / COMPACT_DIRNAME).rglob("part-*.parquet"))
    assert len(parts) == len(FIELDS) * len(ZS)                # one per (field, z)
    pd.testing.assert_frame_equal(_sorted(read_results(tmp_path)), _sorted(rows))
    after, _ = read_current_counts(tmp_path)
    pd.testing.assert_frame_equal(after, before)
    assert verified_task_names(tmp_path, _wanted()) == set(_wanted())
    assert finished_task_names(tmp_path) == set(_wanted())
    # Projection through parts.
    got = read_current_results(tmp_path, columns=[C.COL_X])
    assert list(got.columns) == [C.COL_X] and len(got) == len(rows)


def test_kill_between_part_rename_and_task_deletion_counts_once(tmp_path):
    rows = _synthetic_store(tmp_path)
    res = tmp_path / C.RESULTS_DIRNAME
    saved = {p.name: p.read_bytes() for p in res.glob("task_*.parquet")}
    compact(tmp_path)
    for name, data in saved.items():                          # the task files are back
        (res / name).write_bytes(data)
    # And a part of a compaction killed before its rename.
    part = next((res / COMPACT_DIRNAME).rglob("part-*.parquet"))
    (part.parent / f".{part.name}.x1.tmp").write_bytes(part.read_bytes()[:100])
    pd.testing.assert_frame_equal(_sorted(read_results(tmp_path)), _sorted(rows))
    counts, _ = read_current_counts(tmp_path, merge_iterations=False)
    assert counts["n"].sum() == len(rows)
    assert verified_task_names(tmp_path, _wanted()) == set(_wanted())
    compact(tmp_path)                     # the next compaction removes what the kill left
    assert not list(res.glob("task_*.parquet")) and not list(res.rglob(".part-*.tmp"))
    pd.testing.assert_frame_equal(_sorted(read_results(tmp_path)), _sorted(rows))


def test_truncated_part_is_reported_and_its_tasks_not_counted(tmp_path):
    _synthetic_store(tmp_path)
    compact(tmp_path)
    part = sorted((tmp_path / C.RESULTS_DIRNAME / COMPACT_DIRNAME).rglob("part-*.parquet"))[0]
    data = part.read_bytes()
    part.write_bytes(data[: len(data) // 2])
    with pytest.warns(StoreWarning, match=rf"{part.name}.*will be run again"):
        good = verified_task_names(tmp_path, _wanted(), quarantine=True)
    assert len(good) == len(_wanted()) - len(MAGS) * N_ITER
    # Set aside inside the run (results/corrupt/, its path below results/ kept in the name).
    aside = tmp_path / C.RESULTS_DIRNAME / "corrupt" / "__".join(
        part.relative_to(tmp_path / C.RESULTS_DIRNAME).parts)
    assert not part.exists() and aside.read_bytes() == data[: len(data) // 2]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        counts, _ = read_current_counts(tmp_path)           # the moved part is not met again
    assert counts["n"].sum() == 25 * len(good)


def test_store_without_counts_is_read_through_the_rows(tmp_path):
    rng = np.random.default_rng(3)
    t = _task_rows(rng, "f a", 8.0, 24.0, 0)
    write_task_table(tmp_path, task_filename("f a", 8.0, 24.0, 0), t,
                     key=task_key("f a", 8.0, 24.0, 0))          # format-2 file, no counts
    assert read_current_counts(tmp_path) is None
    data = fit_inputs(tmp_path, C.COL_MAG_INPUT, 0.01)
    assert not data.from_counts and data.n.sum() == len(t)


def test_regions_one_file_per_field_with_the_lines_of_every_task(tmp_path):
    rows = _synthetic_store(tmp_path)
    paths = write_regions(rows, tmp_path / "regions")
    assert len(paths) == len(FIELDS)
    for f in FIELDS:
        # Before: one region_file per task; now the field's file holds all their lines.
        expected = []
        for _, sub in rows[rows[C.COL_FIELD] == f].groupby(
                [C.COL_Z, C.COL_MAG, C.COL_ITERATION], sort=True):
            expected += region_file(sub).splitlines()[3:]
        mine = [p for p in paths if p.read_text().count("circle(") == len(expected)]
        text = [p.read_text() for p in mine]
        assert any(t.splitlines()[3:] == expected for t in text)


# --------------------------------------------------------------------------
# Resume through a real (tiny) simulation
# --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_cfg(small_survey, tmp_path_factory):
    d = yaml.safe_load(small_survey.read_text())
    base = small_survey.parent
    d["survey"]["image_dir"] = str(base / d["survey"]["image_dir"])
    for b in d["survey"]["bands"].values():
        b["psf"] = str(base / b["psf"])
    d["grid"] = {"z": {"values": [8.0, 9.0]}, "mag": {"values": [24.0]},
                 "magnitude_type": "apparent"}
    d["simulation"] = {"n_galaxies": 3, "n_iterations": 2, "seed": 5}
    p = tmp_path_factory.mktemp("tiny") / "c.yaml"
    p.write_text(yaml.safe_dump(d, sort_keys=False), encoding="utf-8")
    cfg = load_config(p)
    run = p.parent / "run"
    simulate(cfg, run, workers=1, progress=False)
    return cfg, run


def test_resume_after_a_kill_mid_compaction_redoes_nothing(tiny_cfg, tmp_path):
    cfg, src = tiny_cfg
    run = tmp_path / "run"
    shutil.copytree(src, run)
    ref = _sorted(read_results(run))
    res = run / C.RESULTS_DIRNAME
    saved = {p.name: p.read_bytes() for p in res.glob("task_*.parquet")}
    assert len(saved) == 4
    # Counts were written by simulate and agree with the rows.
    counts, mag_col = read_current_counts(run, merge_iterations=False)
    assert mag_col == C.COL_MAG_INPUT and counts["n"].sum() == len(ref)
    assert counts["k_selected"].sum() == ref[C.COL_SELECTED].sum()
    compact(run)
    for name, data in saved.items():
        (res / name).write_bytes(data)
    stats = simulate(cfg, run, workers=1, progress=False)
    assert stats["n_run"] == 0 and stats["n_done_before"] == 4
    pd.testing.assert_frame_equal(_sorted(read_results(run)), ref)


def test_truncated_part_and_task_file_are_redone_on_resume(tiny_cfg, tmp_path):
    cfg, src = tiny_cfg
    run = tmp_path / "run"
    shutil.copytree(src, run)
    ref = _sorted(read_results(run))
    compact(run)
    part = sorted((run / C.RESULTS_DIRNAME / COMPACT_DIRNAME).rglob("part-*.parquet"))[0]
    part.write_bytes(part.read_bytes()[:-30])
    with pytest.warns(StoreWarning, match=r"part-.*will be run again"):
        stats = simulate(cfg, run, workers=1, progress=False)
    assert stats["n_run"] == 2 and stats["n_done_before"] == 2      # one (field, z): 2 tasks
    # A cut task file is redone too.
    f = sorted((run / C.RESULTS_DIRNAME).glob("task_*.parquet"))[0]
    f.write_bytes(f.read_bytes()[:-10])
    with pytest.warns(StoreWarning, match=r"will be run again"):
        stats = simulate(cfg, run, workers=1, progress=False)
    assert stats["n_run"] == 1
    pd.testing.assert_frame_equal(_sorted(read_results(run)), ref)


def test_task_counts_equal_a_pandas_groupby_of_the_rows():
    """The numpy grouping behind the footer counts and histograms equals pandas' groupby
    (sorted keys, NaN keys their own group, NaN skipped in sums, all-NaN extremes NaN)."""
    from glaciar import counting as K

    rng = np.random.default_rng(0)
    for trial in range(12):
        n = int(rng.integers(1, 300))
        rows = pd.DataFrame({
            "field": rng.choice(["a", "b"], n).astype(object),
            "z": rng.choice([7.0, 8.0, np.nan] if trial % 2 else [7.0, 8.0], n),
            "mag": rng.choice([26.0, 27.5], n), "iteration": rng.integers(0, 3, n),
            "mag_input": np.where(rng.random(n) < 0.1, np.nan, rng.normal(26, 1, n)),
            "depth_local": np.where(rng.random(n) < 0.2, np.nan, rng.normal(27, 0.3, n)),
            "recovered": rng.random(n) < 0.5, "status": rng.integers(-3, 3, n).astype(np.int8),
            "mag_f160w": np.where(rng.random(n) < 0.2, np.inf, rng.normal(26, 1, n))})
        if trial % 3 == 0:      # one task's rows: constant identity columns (a NaN z too)
            rows = rows.assign(field="a", z=np.nan if trial % 2 else 7.0, mag=26.0, iteration=1)
        rows["selected"] = rows["recovered"] & (rng.random(n) < 0.5)
        got = K.task_counts(rows, "mag_input")
        keys = ["field", "z", "mag", "iteration", K.COUNT_MAG_KEY, K.COUNT_DEPTH_KEY]
        r = rows.assign(**{K.COUNT_MAG_KEY: np.round(rows["mag_input"] / K.COUNTS_MAG_RESOLUTION),
                           K.COUNT_DEPTH_KEY: np.floor(rows["depth_local"] / C.DEPTH_BIN_MAG)})
        gb = r.groupby(keys, sort=True, dropna=False)
        want = gb.agg(n=("recovered", "size"), k_recovered=("recovered", "sum"), k_selected=("selected", "sum"),
                      sum_mag=("mag_input", "sum"), mag_min=("mag_input", "min"),
                      depth_min=("depth_local", "min"), depth_max=("depth_local", "max")).reset_index()
        for c in keys:
            np.testing.assert_array_equal(got[c].to_numpy(), want[c].to_numpy(), err_msg=c)
        for c in ("n", "k_recovered", "k_selected"):
            np.testing.assert_array_equal(got[c].to_numpy(), want[c].to_numpy(), err_msg=c)
        for c in ("mag_min", "depth_min", "depth_max"):
            np.testing.assert_array_equal(got[c].to_numpy(), want[c].to_numpy(), err_msg=c)
        s = np.where(np.isnan(want["mag_min"]), np.nan, want["sum_mag"])
        np.testing.assert_allclose(got["sum_mag"].to_numpy(), s, rtol=1e-12)
        h = K.task_histogram(rows, "mag_f160w")
        assert h[K.COUNT_N].sum() == n and h[K.COUNT_K_SEL].sum() == rows["selected"].sum()
        ids = ["field", "z", "mag", "iteration"]
        np.testing.assert_array_equal(h.groupby(ids, dropna=False)[K.COUNT_N].sum().to_numpy(),
                                      rows.groupby(ids, dropna=False).size().to_numpy())
