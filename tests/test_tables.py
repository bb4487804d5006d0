import numpy as np
import pandas as pd
from astropy.table import Table

from glaciar import constants as C
from glaciar.counting import STATUS_COLUMNS
from glaciar.tables import region_file, summary_table, write_summaries


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
