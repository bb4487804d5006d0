"""glaciar.counting on a task's column arrays (no DataFrame): the footer counts and histograms.

A run's tasks hand their rows to the store as a dict of arrays
(:func:`glaciar.engine.task.task_columns`); the counts and histograms made from it must be
pandas' groupby of the same rows (sorted keys, NaN keys their own group, last).
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from glaciar import constants as C
from glaciar import counting as K


def _rows(rng, n: int) -> dict:
    mag = np.where(rng.random(n) < 0.1, np.nan, rng.normal(26, 1, n))
    mag[: min(n, 3)] = [-0.001, 0.001, -0.0][: min(n, 3)]        # keys -0.0 and 0.0: one group
    rec = rng.random(n) < 0.5
    return {"field": np.full(n, "F01", dtype=object), "z": np.full(n, 9.6), "mag": np.full(n, 26.0),
            "iteration": np.full(n, 2, dtype=np.int64), "mag_input": mag,
            "depth_local": np.where(rng.random(n) < 0.2, np.nan, rng.normal(27, 0.3, n)),
            "status": rng.integers(-3, 3, n).astype(np.int8), "recovered": rec,
            "selected": rec & (rng.random(n) < 0.5),
            "mag_auto_f160w": np.where(rng.random(n) < 0.2, np.inf, rng.normal(26, 1, n))}


def test_counts_and_histograms_of_column_arrays_are_a_pandas_groupby():
    rng = np.random.default_rng(5)
    # a task's rows (numpy grouping) and many rows (pandas' hashing above a size)
    for n in (1, 100, 40_000):
        cols = _rows(rng, n)
        df = pd.DataFrame(cols)
        got = K.task_count_arrays(cols, C.COL_MAG_INPUT)
        keys = ["field", "z", "mag", "iteration", K.COUNT_MAG_KEY, K.COUNT_DEPTH_KEY]
        r = df.assign(**{K.COUNT_MAG_KEY: np.round(df["mag_input"] / K.COUNTS_MAG_RESOLUTION) + 0.0,
                         K.COUNT_DEPTH_KEY: np.floor(df["depth_local"] / C.DEPTH_BIN_MAG)})
        want = r.groupby(keys, sort=True, dropna=False).agg(
            n=("recovered", "size"), k_recovered=("recovered", "sum"),
            k_selected=("selected", "sum"), mag_min=("mag_input", "min"),
            depth_max=("depth_local", "max")).reset_index()
        assert list(got)[:len(keys)] == keys
        for c in keys[1:] + ["n", "k_recovered", "k_selected", "mag_min", "depth_max"]:
            np.testing.assert_array_equal(got[c], want[c].to_numpy(), err_msg=f"{n} {c}")
        np.testing.assert_array_equal(got["field"].astype(str), want["field"].astype(str))
        st = K.STATUS_COLUMNS[1]
        assert got[st].sum() == np.count_nonzero(cols["status"] == 1)

        h = K.task_histogram_arrays(cols, "mag_auto_f160w")
        b = np.where(cols["recovered"], K.mobs_lattice_index(cols["mag_auto_f160w"]),
                     K.MOBS_BIN_FAINT)
        hk = df.assign(**{K.HIST_MIN_KEY: np.round(df["mag_input"] / K.COUNTS_MAG_RESOLUTION) + 0.0,
                          K.HIST_MOBS_BIN: b})
        hw = hk.groupby([K.HIST_MIN_KEY, K.HIST_MOBS_BIN], sort=True, dropna=False).agg(
            n=("recovered", "size"), k_selected=("selected", "sum")).reset_index()
        for c in (K.HIST_MIN_KEY, K.HIST_MOBS_BIN, "n", "k_selected"):
            np.testing.assert_array_equal(h[c], hw[c].to_numpy(), err_msg=f"{n} {c}")


def test_column_arrays_and_their_dataframe_give_the_same_counts():
    cols = _rows(np.random.default_rng(8), 100)
    for make in (K.task_count_arrays, K.task_histogram_arrays):
        col = C.COL_MAG_INPUT if make is K.task_count_arrays else "mag_auto_f160w"
        a, b = make(cols, col), make(pd.DataFrame(cols), col)
        assert list(a) == list(b)
        for c in a:
            np.testing.assert_array_equal(a[c], b[c], err_msg=c)
            assert a[c].dtype == b[c].dtype, c
