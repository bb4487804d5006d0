"""Transfer matrices from per-task histograms of the measured magnitude (issue 8, point 3).

Expected counts are computed here with np.histogram on the rows (independent of the
histogram code); the store is a tiny synthetic one written with write_task_table.
"""
import warnings

import numpy as np
import pandas as pd
import pytest

from glaciar import constants as C
from glaciar.pipeline import selection_file
from glaciar.store import (COMPACT_DIRNAME, StoreWarning, compact, read_current_histograms,
                           task_filename, task_key, verified_task_names, write_task_table)
from glaciar.rundir import write_manifest
from glaciar.counting import MOBS_BIN_BRIGHT, MOBS_BIN_FAINT, mobs_lattice_index
from glaciar.tables import transfer_from_histograms, transfer_matrix

OBS = C.band_column(C.OBS_MAG_QUANTITY, "f160w")
FIELDS = ("a", "b")
ZS = (7.0, 8.0)
MAGS = (25.0, 26.5)
N_ITER = 3


def _rows(rng, field, z, mag, it, n=30):
    rec = rng.random(n) < 0.7
    m_obs = mag + rng.normal(0.1, 0.4, n)
    m_obs[rng.random(n) < 0.1] = np.nan            # flux <= 0
    m_obs[:2] = [np.inf, 25.0]                       # +inf, and a value exactly on an edge
    return pd.DataFrame({C.COL_FIELD: field, C.COL_Z: z, C.COL_MAG: mag, C.COL_ITERATION: it,
                         C.COL_MAG_INPUT: np.full(n, mag), OBS: m_obs, C.COL_RECOVERED: rec,
                         C.COL_SELECTED: rec & (rng.random(n) < 0.6),
                         C.COL_STATUS: np.where(rec, 0, -3)})


def _store(run_dir, seed=0, hist=True):
    """2 fields x 2 z x 2 mags x 3 iterations: half compacted, half loose; manifest drops it 2."""
    rng = np.random.default_rng(seed)
    frames = []
    tasks = [(f, z, m, it) for f in FIELDS for z in ZS for m in MAGS for it in range(N_ITER)]
    for i, (f, z, m, it) in enumerate(tasks):
        t = _rows(rng, f, z, m, it)
        write_task_table(run_dir, task_filename(f, z, m, it), t, key=task_key(f, z, m, it),
                         mag_column=C.COL_MAG_INPUT, obs_column=OBS if hist else None)
        frames.append(t)
        if i == len(tasks) // 2:
            compact(run_dir)
    write_manifest(run_dir, {"fields": list(FIELDS), "z_values": list(ZS),
                             "mag_values": list(MAGS), "n_iterations": N_ITER - 1,
                             "detection_band": "f160w"})
    rows = pd.concat(frames, ignore_index=True)
    return rows[rows[C.COL_ITERATION] < N_ITER - 1]


def _expected(rows, z_edges, m_edges, inner):
    """Counts by np.histogram on the rows: entry 0 missed, then (-inf, e0), ..., [eK, +inf)."""
    oe = np.concatenate([[-np.inf], inner, [np.inf]])
    out = np.zeros((2, len(z_edges) - 1, len(m_edges) - 1, len(oe)), np.int64)
    for k, flag in enumerate((C.COL_RECOVERED, C.COL_SELECTED)):
        for i in range(len(z_edges) - 1):
            for j in range(len(m_edges) - 1):
                cell = rows[(rows[C.COL_Z] >= z_edges[i]) & (rows[C.COL_Z] < z_edges[i + 1])
                            & (rows[C.COL_MAG_INPUT] >= m_edges[j])
                            & (rows[C.COL_MAG_INPUT] < m_edges[j + 1])]
                hit = cell[cell[flag]]
                mobs = hit[OBS].fillna(np.inf).to_numpy(float)
                h = np.histogram(mobs[np.isfinite(mobs)], bins=oe)[0]
                h[-1] += np.sum(mobs == np.inf)            # open ends, counted by hand
                h[0] += np.sum(mobs == -np.inf)
                out[k, i, j, 0] = len(cell) - len(hit)
                out[k, i, j, 1:] = h
    return out


def _from_hist(h, **kw):
    return transfer_from_histograms(h[C.COL_Z], h["m_in_key"], h["mobs_bin"], h["n"],
                                    h["k_recovered"], h["k_selected"], **kw)


def test_histograms_rebuild_the_row_counts_exactly_through_compaction(tmp_path):
    rows = _store(tmp_path)
    assert list((tmp_path / "results" / COMPACT_DIRNAME).rglob("part-*.parquet"))
    assert list((tmp_path / "results").glob("task_*.parquet"))      # and loose ones
    hist, col = read_current_histograms(tmp_path)
    assert col == OBS
    assert hist["n"].sum() == len(rows)                               # nothing double counted
    ze, me = [6.5, 7.5, 8.5], [24.0, 25.75, 27.0]
    inner = np.round(np.arange(23.0, 28.01, 0.2), 6)
    tm = _from_hist(hist, z_edges=ze, m_in_edges=me, m_obs_edges=inner, n_draws=7, seed=[4, 1])
    np.testing.assert_array_equal(tm.counts, _expected(rows, ze, me, inner))
    # Coarser lattice-aligned edges (unions of lattice bins) and the defaults: same as the rows.
    for kw in ({"m_obs_edges": [24.0, 25.0, 26.6, 27.2]}, {}):
        tm = _from_hist(hist, n_draws=7, seed=[4, 1], **kw)
        ref = transfer_matrix(rows[C.COL_Z], rows[C.COL_MAG_INPUT], rows[OBS],
                              rows[C.COL_RECOVERED], rows[C.COL_SELECTED], n_draws=7,
                              seed=[4, 1], **kw)
        np.testing.assert_array_equal(tm.counts, _expected(rows, tm.z_edges, tm.m_in_edges,
                                                           tm.m_obs_edges[1:-1]))
        for name in ("z_edges", "m_in_edges", "m_obs_edges", "counts", "draws"):
            np.testing.assert_array_equal(getattr(tm, name), getattr(ref, name), err_msg=name)
        np.testing.assert_allclose(tm.z_mean, ZS, rtol=0, atol=1e-12)
    # One field only (as a per-field fit selects it).
    one = hist[hist[C.COL_FIELD] == "b"]
    tm = _from_hist(one, z_edges=ze, m_in_edges=me, m_obs_edges=inner)
    np.testing.assert_array_equal(tm.counts, _expected(rows[rows[C.COL_FIELD] == "b"], ze, me,
                                                       inner))


def test_lattice_index_matches_the_rounded_edges():
    rng = np.random.default_rng(3)
    edges_b = np.arange(-20, 200)
    edges = np.round(edges_b * C.TRANSFER_MOBS_STEP, 6)
    # Random values and every edge itself (and its float neighbours).
    m = np.concatenate([rng.uniform(-3.0, 39.0, 5000), edges, np.nextafter(edges, -np.inf),
                        np.nextafter(edges, np.inf)])
    m = m[(m >= edges[0]) & (m < edges[-1])]
    want = edges_b[np.searchsorted(edges, m, side="right") - 1]
    np.testing.assert_array_equal(mobs_lattice_index(m), want)
    np.testing.assert_array_equal(mobs_lattice_index([np.nan, np.inf, -np.inf]),
                                  [MOBS_BIN_FAINT, MOBS_BIN_FAINT, MOBS_BIN_BRIGHT])


def test_off_lattice_edges_and_bad_counts_are_refused():
    args = ([7.0], [2600.0], [130], [5], [3], [2])
    with pytest.raises(ValueError, match="multiples of 0.2"):
        transfer_from_histograms(*args, m_obs_edges=[25.0, 25.3])
    with pytest.raises(ValueError, match="selected source must be recovered"):
        transfer_from_histograms([7.0], [2600.0], [130], [5], [2], [3])


def test_store_without_histograms_falls_back_to_rows(tmp_path, monkeypatch):
    _store(tmp_path, hist=False)
    assert read_current_histograms(tmp_path) is None


def test_lf_products_read_no_row_when_histograms_exist(tmp_path, monkeypatch):
    rows = _store(tmp_path)
    import glaciar.pipeline.inputs as inputs

    def no_rows(*a, **k):
        raise AssertionError("rows read")
    monkeypatch.setattr(inputs, "read_columns", no_rows)
    monkeypatch.setattr(selection_file, "injection_sed", lambda *a: None)

    class Fit:                      # the attributes add_lf_products uses
        magnitude_type = "apparent"
        sed = veff_muv = transfer_matrix = None
        fit_info = {}

        def __init__(self, field):
            self.field = field
    fits = [Fit("a"), Fit("all")]
    selection_file.add_lf_products(tmp_path, {"fields": list(FIELDS), "detection_band": "f160w"},
                                   fits, seed=5)
    for fit, sub in ((fits[0], rows[rows[C.COL_FIELD] == "a"]), (fits[1], rows)):
        tm = fit.transfer_matrix
        np.testing.assert_array_equal(tm.counts, _expected(sub, tm.z_edges, tm.m_in_edges,
                                                           tm.m_obs_edges[1:-1]))


def test_unreadable_histogram_metadata_is_redone_and_not_read(tmp_path):
    _store(tmp_path)
    loose = sorted((tmp_path / "results").glob("task_*.parquet"))
    bad = loose[0]
    data = bytearray(bad.read_bytes())
    at = data.rfind(b"glaciar.mobs_hist\x18")
    start = at + len(b"glaciar.mobs_hist\x18") + 2           # after the 2-byte varint length
    data[start:start + 16] = b"\x01" * 16                     # same length: the footer stays valid
    bad.write_bytes(bytes(data))
    wanted = {f.name: task_key(*_key_of(f)) for f in loose}
    with pytest.warns(StoreWarning, match="unreadable glaciar.mobs_hist metadata"):
        good = verified_task_names(tmp_path, wanted)
    assert good == set(wanted) - {bad.name}
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        assert read_current_histograms(tmp_path) is None      # fall back to the rows
    assert any("reading rows instead" in str(w.message) for w in got)


def _key_of(path):
    import pyarrow.parquet as pq
    import json

    f, z, m, it = json.loads(pq.read_metadata(path).metadata[b"glaciar.task"])
    return f, float(z), float(m), it
