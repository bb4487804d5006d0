import warnings

import numpy as np
import pandas as pd
import pytest
from astropy.table import Table

from glaciar import constants as C
from glaciar.counting import MOBS_BIN_BRIGHT, MOBS_BIN_FAINT, STATUS_COLUMNS, mobs_lattice_index
from glaciar.inference import SelectionFunction, SurfaceModel
from glaciar.pipeline import selection_file
from glaciar.rundir import write_manifest
from glaciar.store import (COMPACT_DIRNAME, StoreWarning, compact, read_current_histograms,
                           task_filename, task_key, verified_task_names, write_task_table)
from glaciar.tables import (region_file, slice_edges, summary_table, transfer_from_histograms,
                            transfer_matrix, write_summaries)


def _rows(seed=0, n=2000):
    rng = np.random.default_rng(seed)
    status = rng.choice(np.array(C.STATUS_CODES), size=n)
    rec = np.isin(status, C.RECOVERED_STATUSES)
    return pd.DataFrame({
        C.COL_FIELD: rng.choice(["a", "b"], size=n),
        C.COL_Z: rng.choice([9.0, 10.0], size=n),
        C.COL_MAG: rng.choice([25.0, 26.0, 27.0], size=n),
        C.COL_ITERATION: rng.integers(0, 3, size=n),
        C.COL_X: rng.uniform(0, 100, n), C.COL_Y: rng.uniform(0, 100, n),
        C.COL_STATUS: status, C.COL_RECOVERED: rec,
        C.COL_SELECTED: rec & (rng.uniform(size=n) < 0.5),
    })


def test_summary_counts_match_direct_count():
    rows = _rows()
    s = summary_table(rows)
    for _, r in s.iterrows():
        sub = rows[(rows.z == r.z) & (rows.mag == r.mag)]
        assert r.n_input == len(sub)
        for code, col in STATUS_COLUMNS.items():
            assert r[col] == np.sum(sub.status == code)
        assert r.n_recovered == r.n_status_0 + r.n_status_1 + r.n_status_2
        assert r.n_recovered + r.n_status_m1 + r.n_status_m2 + r.n_status_m3 == r.n_input
        assert r.n_selected == sub.selected.sum()
        assert np.isclose(r.completeness, sub.recovered.mean())
        assert np.isclose(r.selection, sub.selected.sum() / sub.recovered.sum())
        assert np.isclose(r.selection_total, r.completeness * r.selection)


def test_summary_selection_nan_when_nothing_recovered():
    rows = pd.DataFrame({C.COL_Z: [9.0] * 3, C.COL_MAG: [28.0] * 3, C.COL_STATUS: [-3, -3, -2],
                         C.COL_RECOVERED: [False] * 3, C.COL_SELECTED: [False] * 3})
    s = summary_table(rows)
    assert s.completeness.iloc[0] == 0 and np.isnan(s.selection.iloc[0])


def test_write_summaries_roundtrip(tmp_path):
    rows = _rows(1)
    paths = write_summaries(rows, tmp_path, {"seed": 5})
    assert sorted(p.name for p in paths) == ["summary_a.ecsv", "summary_all.ecsv", "summary_b.ecsv"]
    t = Table.read(tmp_path / "summary_a.ecsv")
    direct = summary_table(rows[rows.field == "a"])
    np.testing.assert_array_equal(t["n_input"], direct.n_input)
    assert t.meta["seed"] == 5 and t.meta["field"] == "a"


def test_region_file_is_one_based_and_coloured():
    rows = pd.DataFrame({C.COL_X: [0.0], C.COL_Y: [9.5], C.COL_STATUS: [-3], C.COL_Z: [9.0], C.COL_MAG: [26.0]})
    txt = region_file(rows)
    assert "circle(1.000,10.500," in txt and "color=red" in txt


# ------------------------------------------------------------------------------
# Region files of fields whose names differ only where a file name cannot (issue 10)
# ------------------------------------------------------------------------------
def test_region_files_do_not_collide(tmp_path):
    from glaciar.tables import write_regions

    keys = [("a b", 8.0), ("a_b", 8.0), ("a_b", 8.00004), ("par α", 8.0)]
    rows = pd.DataFrame({C.COL_FIELD: [k[0] for k in keys], C.COL_Z: [k[1] for k in keys],
                         C.COL_MAG: 24.0, C.COL_ITERATION: 0, C.COL_X: 1.0, C.COL_Y: 2.0,
                         C.COL_STATUS: C.STATUS_ISOLATED})
    paths = write_regions(rows, tmp_path)
    # One file per field: "a b" and "a_b" do not share one; "a_b" holds both of its tasks.
    assert len(set(paths)) == 3 and all(p.is_file() for p in paths)
    assert sorted(p.read_text().count("circle(") for p in paths) == [1, 1, 2]


# ------------------------------------------------------------------------------
# The photometric transfer function p(m_obs | m_in, z): glaciar.tables.transfer_matrix, the file.
# ------------------------------------------------------------------------------
def _synthetic(n=400, delta=0.3, seed=1):
    """Sources on a (z, m_in) grid; recovered with probability 0.75, m_obs = m_in + delta."""
    rng = np.random.default_rng(seed)
    z = np.repeat([7.0, 8.0], 3 * n)
    m_in = np.tile(np.repeat([25.0, 26.0, 27.0], n), 2)
    rec = rng.random(z.size) < 0.75
    sel = rec & (rng.random(z.size) < 0.5)
    return z, m_in, m_in + delta, rec, sel


def test_rows_sum_to_one_and_known_shift_lands_on_the_shifted_bin():
    z, m_in, m_obs, rec, sel = _synthetic(delta=0.3)
    edges = np.arange(23.0, 29.01, 0.2)
    tm = transfer_matrix(z, m_in, m_obs, rec, sel, m_obs_edges=edges, n_draws=50, seed=3)
    np.testing.assert_allclose(tm.matrix.sum(axis=-1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.nansum(tm.draws, axis=-1), 1.0, rtol=0, atol=1e-9)
    assert tm.m_obs_edges[0] == -np.inf and tm.m_obs_edges[-1] == np.inf
    np.testing.assert_allclose(slice_edges([7.0, 8.0], 0.25), [6.5, 7.5, 8.5])
    np.testing.assert_allclose(tm.z_mean, [7.0, 8.0])
    for k, flag in enumerate((rec, sel)):
        for i, zi in enumerate((7.0, 8.0)):
            for j, mj in enumerate((25.0, 26.0, 27.0)):
                cell = (z == zi) & (m_in == mj)
                row = tm.counts[k, i, j]
                # Not recovered / not selected in entry 0; every other source in the one bin
                # holding m_in + 0.3 (independent: np.digitize on the finite edges).
                b = np.digitize(mj + 0.3, edges)          # index into [-inf, e0, ..., +inf] bins
                assert row[0] == np.sum(cell & ~flag)
                assert row[1 + b] == np.sum(cell & flag)
                assert row.sum() == cell.sum()


def test_non_positive_flux_goes_to_the_faintest_bin_and_outside_sources_are_dropped():
    z = np.array([7.0, 7.0, 7.0, 9.9])
    m_in = np.array([26.0, 26.0, 26.0, 26.0])
    m_obs = np.array([np.nan, 40.0, 26.1, 26.0])
    rec = np.array([True, True, True, True])
    tm = transfer_matrix(z, m_in, m_obs, rec, rec, z_edges=[6.5, 7.5], m_in_edges=[25.5, 26.5],
                         m_obs_edges=[25.0, 26.0, 27.0], n_draws=4)
    assert tm.counts[0, 0, 0].tolist() == [0, 0, 0, 1, 2]     # missed, <25, 25-26, 26-27, >=27
    assert tm.counts.sum() == 2 * 3


def test_draws_spread_matches_the_multinomial_expectation():
    rng = np.random.default_rng(5)
    n = 400
    p = np.array([0.25, 0.05, 0.4, 0.3])          # missed, three m_obs bins
    entry = rng.choice(4, size=n, p=p)
    rec = entry > 0
    m_obs = np.array([np.nan, 25.5, 26.5, 27.5])[entry]
    tm = transfer_matrix(np.full(n, 7.0), np.full(n, 26.0), m_obs, rec, np.zeros(n, bool),
                         m_obs_edges=[25.0, 26.0, 27.0, 28.0], n_draws=4000, seed=7)
    counts = tm.counts[0, 0, 0]
    phat = counts / n
    d = tm.draws[:, 0, 0, 0]
    # Dirichlet(counts + alpha): mean (n_k + alpha) / A, var = m (1 - m) / (A + 1), A = n + K alpha.
    a = counts + tm.alpha
    mean = a / a.sum()
    sd = np.sqrt(mean * (1 - mean) / (a.sum() + 1))
    np.testing.assert_allclose(d.mean(axis=0), mean, atol=4 * sd.max() / np.sqrt(4000))
    np.testing.assert_allclose(d.std(axis=0), sd, rtol=0.06)
    # ... which is the multinomial (binomial per entry) sd of the estimate, sqrt(p (1 - p) / n).
    occupied = counts > 0
    np.testing.assert_allclose(d.std(axis=0)[occupied], np.sqrt(phat * (1 - phat) / n)[occupied],
                               rtol=0.08)
    # Same seed, same draws.
    again = transfer_matrix(np.full(n, 7.0), np.full(n, 26.0), m_obs, rec, np.zeros(n, bool),
                            m_obs_edges=[25.0, 26.0, 27.0, 28.0], n_draws=4000, seed=7)
    np.testing.assert_array_equal(again.draws, tm.draws)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="selected source must be recovered"):
        transfer_matrix([7.0], [26.0], [26.0], [False], [True])
    with pytest.raises(ValueError, match="m_obs_edges"):
        transfer_matrix([7.0], [26.0], [26.0], [True], [True], m_obs_edges=[27.0, 26.0])


def test_file_round_trip_is_exact(tmp_path):
    z, m_in, m_obs, rec, sel = _synthetic(n=50)
    tm = transfer_matrix(z, m_in, m_obs, rec, sel, n_draws=20, seed=2)
    mdl = SurfaceModel.for_data(np.array([7.0, 8.0]), np.array([25.0, 27.0]))
    sf = SelectionFunction(mdl, mdl.sample_prior(3, np.random.default_rng(0)),
                           meta={"area_arcmin2": 2.0})
    sf.transfer_matrix = tm
    path = tmp_path / "sf.fits"
    sf.write(path)
    back = SelectionFunction.read(path).transfer_matrix
    for name in ("z_edges", "z_mean", "m_in_edges", "m_obs_edges", "counts", "matrix"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tm, name), err_msg=name)
    np.testing.assert_array_equal(back.draws, tm.draws.astype(np.float32))
    assert back.kinds == tm.kinds and back.alpha == tm.alpha
    one = SelectionFunction.read(path).transfer(8.2, kind="selected")
    np.testing.assert_array_equal(one.matrix, tm.matrix[1, 1])
    assert (one.z_lo, one.z_hi) == (7.5, 8.5)
    with pytest.raises(ValueError, match="outside the slices"):
        SelectionFunction.read(path).transfer(9.0)


def test_glaciar_fit_products_from_a_run(small_run):
    """add_lf_products on a simulated run: counts against an independent histogram of its rows."""
    import json

    from glaciar import constants as C
    from glaciar.store import read_current_histograms, read_current_results

    cfg, run = small_run
    # The simulated run stores m_obs histograms: the matrices below come from them, not rows.
    assert read_current_histograms(run) is not None
    manifest = json.loads((run / C.MANIFEST_NAME).read_text())
    rows = read_current_results(run)
    mdl = SurfaceModel.for_data(rows[C.COL_Z], rows[C.COL_MAG_INPUT])
    sf = SelectionFunction(mdl, mdl.sample_prior(4, np.random.default_rng(0)),
                           meta={"area_arcmin2": 1.0}, field="all",
                           domain={"z": (8.0, 10.4), "mag": (24.0, 27.5)})
    selection_file.add_lf_products(run, manifest, [sf], seed=3)
    assert sf.sed.beta_mean == cfg.source.beta_mean and sf.sed.igm == cfg.source.igm
    assert sf.sed.detection_filter.name.endswith(cfg.survey.detection_band.lower())
    tm = sf.transfer_matrix
    det = C.band_column(C.OBS_MAG_QUANTITY, cfg.survey.detection_band)
    for k, flag in enumerate((C.COL_RECOVERED, C.COL_SELECTED)):
        for i, zi in enumerate(sorted(rows[C.COL_Z].unique())):
            for j, mj in enumerate(sorted(rows[C.COL_MAG_INPUT].round(6).unique())):
                cell = rows[(rows[C.COL_Z] == zi) & (rows[C.COL_MAG_INPUT].round(6) == mj)]
                hit = cell[cell[flag].astype(bool)]
                mobs = hit[det].fillna(np.inf).to_numpy(float)
                want = np.histogram(mobs, bins=tm.m_obs_edges)[0]
                want[-1] += np.sum(mobs == np.inf)        # histogram leaves out +inf itself
                assert tm.counts[k, i, j, 0] == len(cell) - len(hit)
                np.testing.assert_array_equal(tm.counts[k, i, j, 1:], want)


# ------------------------------------------------------------------------------
# Transfer matrices from per-task histograms of the measured magnitude (issue 8, point 3).
#
# Expected counts are computed here with np.histogram on the rows (independent of the
# histogram code); the store is a tiny synthetic one written with write_task_table.
# ------------------------------------------------------------------------------
OBS = C.band_column(C.OBS_MAG_QUANTITY, "f160w")
FIELDS = ("a", "b")
ZS = (7.0, 8.0)
MAGS = (25.0, 26.5)
N_ITER = 3


def _hist_rows(rng, field, z, mag, it, n=30):
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
        t = _hist_rows(rng, f, z, m, it)
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
