"""The store at the paper's scale: fit and report from counts, beside today's reading path.

Targets (issue 8): a synthetic store of the BoRG set-up (71 fields x 15 z x 20 m x 100
iterations = 2.13 M tasks, 100 sources each = 213 M sources) fitted with the real
``glaciar fit`` code path (:func:`glaciar.pipeline.fit.run_fit`) in <= 60 s and <= 2 GB
peak RSS; ``glaciar report`` on 1e4 tasks in <= 10 s.

The synthetic stores hold counts, not pixels: counts are drawn directly from a known
depth-aware logistic surface, C = 0.9 / (1 + exp((m - (d - 27.4) - m50(z)) / 0.25)) with
m50(z) = 26.8 - 0.15 (z - 8), and S = a z window (logistic edges at z = 6.9 and 10.6,
width 0.15), and written in the layout ``glaciar simulate`` leaves after compaction: one
part per (field, z) (:func:`glaciar.store.write_part`) whose footer holds its 2000 task
keys and their counts (per task: 100 sources spread over the field's depth bins of 0.05
mag; each field has its own depth, 27.1-27.7 mag, with 0.2 mag of spread).  The parts'
row tables are empty (213 M rows of pixels-derived columns are what the counts replace;
fit and report read no row).

"Today" is the reading path before counts (every task file read; all columns for the
report, the fit's 7 columns by projection), measured in the same run on a store of
``--today-tasks`` task files of 100 rows x 89 columns (the columns of a 4-band run) and
scaled linearly to the task counts above; the memory figure is the rows' in-memory
size scaled the same way.

Each part's footer also holds its tasks' histograms of the measured detection-band
magnitude (:func:`glaciar.counting.task_histogram` columns; m_obs = m + 0.05 + 0.3 N(0, 1)
for the recovered sources), from which ``run_fit``'s LF products build the photometric
transfer matrices (:func:`glaciar.pipeline.selection_file.add_lf_products`, timed apart
inside the fit; V_eff(M_UV) is skipped: the manifest records no injection SED).  Today's
transfer matrices read the rows' measured magnitudes: the "today" figure is the fit's
projected row read, scaled.

The fit's process first reads the counts once on its own (to time reading apart from
``run_fit``, which reads them again); its peak RSS covers both.  Each measurement runs
in a fresh subprocess (wall time with ``time.perf_counter``, peak
RSS from ``resource.getrusage(RUSAGE_SELF).ru_maxrss``).  The machine is shared (2
cores, other jobs running): compare ratios from one run rather than absolute seconds.

Run: ``python benchmarks/store.py [--fields 71 --iterations 100 --today-tasks 300]``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np
import pandas as pd

from glaciar import constants as C
from glaciar import counting as K
from glaciar import rundir
from glaciar import store as S
from glaciar.counting import STATUS_COLUMNS

Z_VALUES = np.round(np.linspace(6.5, 11.5, 15), 4)
MAG_VALUES = np.round(24.0 + 0.25 * np.arange(20), 4)
N_PER_TASK = 100
DEPTH_SPREAD = 0.2          # [mag] within a field
DEPTH_REF = 27.4
OBS_COLUMN = C.band_column("mag", "f160w")     #: the measured detection-band magnitude


def _c(m_rel, z):
    return 0.9 / (1.0 + np.exp((m_rel - (26.8 - 0.15 * (z - 8.0))) / 0.25))


def _s(z):
    return 1.0 / (1.0 + np.exp(-(z - 6.9) / 0.15)) / (1.0 + np.exp((z - 10.6) / 0.15))


def _field_depth(fi, n_fields):
    return 27.1 + 0.6 * fi / max(1, n_fields - 1)


def _manifest(fields, n_iter):
    edges = {}
    for fi, f in enumerate(fields):
        d0 = _field_depth(fi, len(fields))
        e = np.round(np.arange(np.floor(d0 / 0.05) * 0.05, d0 + DEPTH_SPREAD + 0.05, 0.05), 4)
        edges[f] = {"bin_edges_mag": e.tolist(), "area_arcmin2": [4.0 / (len(e) - 1)] * (len(e) - 1)}
    return {"store_format": C.STORE_FORMAT, "fields": fields, "z_values": Z_VALUES.tolist(),
            "mag_values": MAG_VALUES.tolist(), "n_iterations": n_iter,
            "magnitude_type": "apparent", "detection_band": "f160w",
            "area_arcmin2": {f: 4.0 for f in fields}, "depth_area": edges}


def _task_histograms(rng, field, z, mags, its, k_rec, k_sel) -> pd.DataFrame:
    """Per-task m_obs histograms (:func:`glaciar.counting.task_histogram` columns) of tasks whose
    recovered and selected totals are ``k_rec``, ``k_sel``: m_obs = m + 0.05 + 0.3 N(0, 1)."""
    from glaciar.counting import MOBS_BIN_FAINT, mobs_lattice_index

    n_t = len(mags)
    t = np.repeat(np.arange(n_t), N_PER_TASK)
    j = np.tile(np.arange(N_PER_TASK), n_t)
    rec = j < k_rec[t]
    sel = j < k_sel[t]                      # selected sources are recovered ones
    m_obs = mags[t] + 0.05 + 0.3 * rng.standard_normal(t.size)
    b = np.where(rec, mobs_lattice_index(m_obs), MOBS_BIN_FAINT).astype(np.int64)
    code = t * 1024 + np.where(b == MOBS_BIN_FAINT, 1023, b)   # lattice bins < 1023 here
    u, inv = np.unique(code, return_inverse=True)
    tu, bu = u // 1024, u % 1024
    return pd.DataFrame({
        C.COL_FIELD: field, C.COL_Z: z, C.COL_MAG: mags[tu], C.COL_ITERATION: its[tu],
        K.HIST_MIN_KEY: np.round(mags[tu] / K.COUNTS_MAG_RESOLUTION),
        K.HIST_MOBS_BIN: np.where(bu == 1023, MOBS_BIN_FAINT, bu).astype(np.int32),
        K.COUNT_N: np.bincount(inv), K.COUNT_K_REC: np.bincount(inv, weights=rec).astype(np.int64),
        K.COUNT_K_SEL: np.bincount(inv, weights=sel).astype(np.int64)})


def write_counts_store(run_dir: Path, n_fields: int, n_iter: int, seed: int = 1) -> int:
    """A compacted store of counts and m_obs histograms (no rows) drawn from the known
    surface; returns tasks."""
    import pyarrow as pa

    rng = np.random.default_rng(seed)
    fields = [f"borg_{i:03d}" for i in range(n_fields)]
    empty = pa.table({C.COL_FIELD: pa.array([], pa.string())})
    n_tasks = 0
    for fi, f in enumerate(fields):
        d0 = _field_depth(fi, n_fields)
        dkeys = np.arange(np.floor(d0 / C.DEPTH_BIN_MAG), np.floor((d0 + DEPTH_SPREAD) /
                                                                   C.DEPTH_BIN_MAG) + 1)
        p = np.full(len(dkeys), 1.0 / len(dkeys))
        for z in Z_VALUES:
            mm, it = np.meshgrid(MAG_VALUES, np.arange(n_iter), indexing="ij")
            mm, it = mm.ravel(), it.ravel()
            n = rng.multinomial(N_PER_TASK, p, size=len(mm))          # (tasks, depth bins)
            t_idx, b_idx = np.nonzero(n)
            nn = n[t_idx, b_idx]
            dmean = (dkeys[b_idx] + 0.5) * C.DEPTH_BIN_MAG
            m = mm[t_idx]
            k_rec = rng.binomial(nn, _c(m - (dmean - DEPTH_REF), z))
            k_sel = rng.binomial(k_rec, _s(z))
            counts = pd.DataFrame({
                C.COL_FIELD: f, C.COL_Z: float(z), C.COL_MAG: m, C.COL_ITERATION: it[t_idx],
                K.COUNT_MAG_KEY: np.round(m / K.COUNTS_MAG_RESOLUTION),
                K.COUNT_DEPTH_KEY: dkeys[b_idx].astype(float),
                K.COUNT_N: nn, K.COUNT_K_REC: k_rec, K.COUNT_K_SEL: k_sel})
            for code, col in STATUS_COLUMNS.items():
                counts[col] = (k_rec if code == C.STATUS_ISOLATED else
                               nn - k_rec if code == C.STATUS_NOT_DETECTED else 0)
            counts[K.COUNT_SUM_MAG] = m * nn
            counts[K.COUNT_MAG_MIN] = m
            counts[K.COUNT_MAG_MAX] = m
            counts[K.COUNT_SUM_DEPTH] = dmean * nn
            counts[K.COUNT_DEPTH_MIN] = dkeys[b_idx] * C.DEPTH_BIN_MAG
            counts[K.COUNT_DEPTH_MAX] = (dkeys[b_idx] + 1) * C.DEPTH_BIN_MAG
            tasks = [[S.task_filename(f, float(z), float(a), int(b)),
                      S.task_key(f, float(z), float(a), int(b)), N_PER_TASK]
                     for a, b in zip(mm, it)]
            k_rec_t = np.bincount(t_idx, weights=k_rec, minlength=len(mm)).astype(np.int64)
            k_sel_t = np.bincount(t_idx, weights=k_sel, minlength=len(mm)).astype(np.int64)
            hist = _task_histograms(rng, f, float(z), mm, it, k_rec_t, k_sel_t)
            S.write_part(run_dir, f, float(z), empty, tasks, counts, C.COL_MAG_INPUT,
                         hist=hist, obs_column=OBS_COLUMN)
            n_tasks += len(tasks)
    rundir.write_manifest(run_dir, _manifest(fields, n_iter))
    return n_tasks


def write_rows_store(run_dir: Path, n_tasks: int, with_counts: bool, seed: int = 2) -> None:
    """``n_tasks`` loose task files of 100 rows x ~89 columns (a 4-band run's width)."""
    rng = np.random.default_rng(seed)
    bands = ("f160w", "f098m", "f125w", "f606w")
    extra = [C.band_column(q, b) for b in bands for q in
             ("mag_in", "mag_in_stamp", "flux_in", "flux_iso", "fluxerr_iso", "flux_auto",
              "fluxerr_auto", "flux_aper0", "fluxerr_aper0", "flux_aper1", "fluxerr_aper1",
              "mag", "magerr", "sn", "maglim")]
    zs, ms = Z_VALUES[:5], MAG_VALUES[:6]
    it_n = int(np.ceil(n_tasks / (len(zs) * len(ms))))
    done = 0
    for z in zs:
        for m in ms:
            for it in range(it_n):
                if done == n_tasks:
                    break
                n = N_PER_TASK
                st = rng.choice([0, -3], n)
                rec = st == 0
                t = pd.DataFrame({C.COL_FIELD: "borg_000", C.COL_Z: float(z), C.COL_MAG: float(m),
                                  C.COL_ITERATION: it, C.COL_TASK_SEED: 7, C.COL_SOURCE: np.arange(n),
                                  C.COL_X: rng.uniform(0, 1e3, n), C.COL_Y: rng.uniform(0, 1e3, n),
                                  C.COL_DEPTH: 27.1 + rng.uniform(0, 0.2, n),
                                  C.COL_MAG_INPUT: float(m), C.COL_M_UV: -20.0 + rng.normal(0, .1, n),
                                  C.COL_STATUS: st, C.COL_RECOVERED: rec,
                                  C.COL_SELECTED: rec & (rng.uniform(size=n) < .7)})
                for col in extra:
                    t[col] = rng.normal(size=n)
                S.write_task_table(run_dir, S.task_filename("borg_000", z, m, it), t,
                                   key=S.task_key("borg_000", z, m, it),
                                   mag_column=C.COL_MAG_INPUT if with_counts else None)
                done += 1
    rundir.write_manifest(run_dir, {"fields": ["borg_000"], "z_values": zs.tolist(),
                               "mag_values": ms.tolist(), "n_iterations": it_n,
                               "magnitude_type": "apparent"})


def depth_effect(n: int = 200_000, seed: int = 0) -> None:
    """The depth-aware approximation of counts, measured on the fit (benchmarks/fit.py's data).

    Per-source flags from benchmarks/fit.py's known depth-aware surfaces (continuous
    mag_input, two depths with 0.1 mag scatter); cells from the rows
    (:func:`aggregate_cells`, per-source relative magnitude) against cells from the counts
    (:func:`glaciar.counting.task_counts` grouped as stored, placed by group mean); both fitted
    with the same seed; the shift of each parameter's posterior median in posterior sds.
    """
    sys.path.insert(0, str(Path(__file__).parent))
    from fit import make

    from glaciar.inference import SurfaceModel, aggregate_cells, fit_surfaces
    from glaciar.pipeline.inputs import cells_from_counts

    df = make(n, np.random.default_rng(seed))
    df[C.COL_FIELD] = np.where(df[C.COL_DEPTH] < 28.7, "shallow", "deep")
    df[C.COL_MAG] = np.round(df[C.COL_MAG_INPUT] / 0.25) * 0.25
    df[C.COL_ITERATION] = 0
    df[C.COL_STATUS] = np.where(df[C.COL_RECOVERED], 0, -3)
    ref = round(float(np.median(df[C.COL_DEPTH])), 2)
    a = aggregate_cells(df, 0.01, ref)
    g = S._merge_counts(K.task_counts(df, C.COL_MAG_INPUT))
    b = cells_from_counts(g[C.COL_Z], g[K.COUNT_SUM_MAG] / g[K.COUNT_N],
                          g[K.COUNT_SUM_DEPTH] / g[K.COUNT_N], g[K.COUNT_N], g[K.COUNT_K_REC],
                          g[K.COUNT_K_SEL], 0.01, ref)
    out = []
    for cells in (a, b):
        mdl = SurfaceModel.for_data(a.z, a.mag, depth_ref=ref)
        res = fit_surfaces(cells, mdl, seed=0)
        d = res.draws(2000)
        out.append((np.median(d, axis=0), np.std(d, axis=0), mdl.param_names))
    shift = (out[1][0] - out[0][0]) / out[0][1]
    print(f"depth-aware approximation: {n} sources, {len(a)} cells from rows, {len(b)} from "
          f"counts ({len(g)} count groups)")
    for name, sh in zip(out[0][2], shift):
        print(f"  {name:16s} median shift {sh:+.3f} posterior sd")
    print(f"  largest |shift| {np.max(np.abs(shift)):.3f} sd")


def _measure(code: str) -> dict:
    """Run ``code`` in a fresh interpreter; it sets ``out`` (a dict); add wall s and peak RSS."""
    prog = textwrap.dedent(f"""
        import json, resource, time, warnings
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        out = {{}}
        {textwrap.indent(textwrap.dedent(code), '        ').strip()}
        out["wall_s"] = time.perf_counter() - t0
        out["rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(json.dumps(out))
    """)
    res = subprocess.run([sys.executable, "-c", prog], capture_output=True, text=True, check=False)
    if res.returncode:
        raise RuntimeError(res.stderr[-3000:])
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fields", type=int, default=71)
    ap.add_argument("--iterations", type=int, default=100)
    ap.add_argument("--today-tasks", type=int, default=300)
    ap.add_argument("--report-tasks", type=int, default=10_000)
    ap.add_argument("--max-steps", type=int, default=None)
    ap.add_argument("--depth-effect", action="store_true",
                    help="only measure the depth-aware approximation of counts on the fit")
    args = ap.parse_args(argv)
    if args.depth_effect:
        depth_effect()
        return
    root = Path(tempfile.mkdtemp(prefix="glaciar-store-bench-"))
    paper_tasks = args.fields * len(Z_VALUES) * len(MAG_VALUES) * args.iterations

    t0 = time.perf_counter()
    big = root / "paper"
    n_big = write_counts_store(big, args.fields, args.iterations)
    print(f"synthetic store: {n_big} tasks ({n_big * N_PER_TASK / 1e6:.0f} M sources) in "
          f"{len(S._part_files(big))} parts, written in {time.perf_counter() - t0:.0f} s; "
          f"{sum(p.stat().st_size for p in S._part_files(big)) / 2**20:.0f} MiB")
    # Report store: 1e4 tasks (5 fields x 15 z x 20 m x iterations).
    rep = root / "report"
    rep_iter = max(1, round(args.report_tasks / (5 * len(Z_VALUES) * len(MAG_VALUES))))
    n_rep = write_counts_store(rep, 5, rep_iter, seed=3)
    today_rows = root / "today_rows"
    write_rows_store(today_rows, args.today_tasks, with_counts=False)
    today_counts = root / "today_counts"
    write_rows_store(today_counts, args.today_tasks, with_counts=True)

    steps = "" if args.max_steps is None else f", max_steps={args.max_steps}"
    read = _measure(f"""
        from glaciar.store import read_current_counts
        c, _ = read_current_counts({str(big)!r})
        out["groups"] = len(c)
    """)
    fit = _measure(f"""
        from glaciar.inference.sampling import SamplerSettings
        from glaciar.pipeline.fit import run_fit
        from glaciar.pipeline.inputs import fit_inputs
        import glaciar.pipeline.fit as sfm   # the add_lf_products run_fit calls
        # The transfer matrices come from the parts' m_obs histograms (no rows here): timed.
        lf = sfm.add_lf_products

        def timed(run_dir, manifest, fits, **kw):
            t = time.perf_counter()
            lf(run_dir, manifest, fits, **kw)
            out["transfer_s"] = time.perf_counter() - t
            out["n_transfer"] = sum(f.transfer_matrix is not None for f in fits)
            out["transfer_sources"] = max(int(f.transfer_matrix.counts[0].sum()) for f in fits
                                          if f.transfer_matrix is not None)
        sfm.add_lf_products = timed
        t = time.perf_counter()
        d = fit_inputs({str(big)!r}, "mag_input", 0.01)
        cells = d.cells(0.01, {DEPTH_REF}, "mag_input")
        out["read_s"] = time.perf_counter() - t
        out["cells"] = len(cells)
        t = time.perf_counter()
        run_fit({str(big)!r}, model="logistic", plots=False,
                sampler=SamplerSettings(seed=0{steps}))
        out["run_fit_s"] = time.perf_counter() - t
        s = json.load(open({str(big / 'fit' / 'summary.json')!r}))["fits"]["all"]
        out["sampler_s"] = s["wall_time_s"]
        out["n_sources"] = s["n_sources"]
        out["converged"] = s["converged"]
        out["m50_0"] = s["parameters"].get("m50_0", {{}}).get("median")
    """)
    hist = _measure(f"""
        from glaciar.store import read_current_histograms
        h, _ = read_current_histograms({str(big)!r})
        out["groups"] = len(h)
    """)
    report = _measure(f"""
        from glaciar.cli import main
        assert main(["report", {str(rep)!r}]) == 0
    """)
    today_read = _measure(f"""
        from glaciar.store import read_current_results
        from glaciar.pipeline.inputs import read_columns
        t = time.perf_counter()
        rows = read_current_results({str(today_rows)!r})
        out["report_read_s"] = time.perf_counter() - t
        out["bytes_per_row"] = rows.memory_usage(deep=True).sum() / len(rows)
        del rows
        t = time.perf_counter()
        df = read_columns({str(today_rows)!r}, ["field", "z", "mag", "mag_input", "recovered",
                                                "selected", "depth_local"])
        out["fit_read_s"] = time.perf_counter() - t
        out["fit_bytes_per_row"] = df.memory_usage(deep=True).sum() / len(df)
    """)
    today_report = _measure(f"""
        from glaciar.store import read_current_results
        from glaciar.tables import summary_table
        t = time.perf_counter()
        rows = read_current_results({str(today_rows)!r})
        summary_table(rows)
        out["s"] = time.perf_counter() - t
    """)
    counts_same = _measure(f"""
        from glaciar.store import read_current_counts
        t = time.perf_counter()
        read_current_counts({str(today_counts)!r})
        out["s"] = time.perf_counter() - t
    """)
    nt = args.today_tasks
    per_task_fit = today_read["fit_read_s"] / nt
    per_task_rep = today_report["s"] / nt
    print()
    print(f"machine loaded (2 cores shared with other jobs); one run; today = rows read per task "
          f"file, measured on {nt} task files of {N_PER_TASK} rows x 89 columns and scaled")
    print(f"{'':38s} {'counts (this branch)':>24s} {'today (rows, scaled)':>24s}")
    print(f"{'fit (run_fit), ' + str(n_big) + ' tasks [s]':38s} {fit['run_fit_s']:24.1f} "
          f"{per_task_fit * n_big:24.0f}  (reading alone)")
    print(f"{'  reading counts + cells [s]':38s} {fit['read_s']:24.1f}")
    print(f"{'  sampler (MAP + emcee) [s]':38s} {fit['sampler_s']:24.1f}")
    print(f"{'  rest: PPC, file grids, V_eff... [s]':38s} "
          f"{fit['run_fit_s'] - fit['read_s'] - fit['sampler_s']:24.1f}")
    print(f"{'  process wall incl. imports [s]':38s} {fit['wall_s'] - fit['read_s']:24.1f}")
    print(f"{'  peak RSS [MB]':38s} {fit['rss_mb']:24.0f} "
          f"{today_read['fit_bytes_per_row'] * N_PER_TASK * n_big / 2**20:24.0f}  (fit's 7 columns in memory)")
    print(f"{'  reading counts alone [s] / RSS [MB]':38s} {read['wall_s']:17.1f} / {read['rss_mb']:4.0f}"
          f"   ({read['groups']} merged groups; {fit['cells']} cells)")
    print(f"{'  transfer matrices (histograms) [s]':38s} {fit['transfer_s']:24.1f} "
          f"{per_task_fit * n_big:24.0f}  (reading rows alone; {fit['n_transfer']} matrices, "
          f"{fit['transfer_sources']} sources)")
    print(f"{'  reading histograms alone [s] / RSS [MB]':38s} {hist['wall_s']:17.1f} / "
          f"{hist['rss_mb']:4.0f}   ({hist['groups']} merged histogram rows)")
    print(f"{'report, ' + str(n_rep) + ' tasks: wall [s]':38s} {report['wall_s']:24.1f} "
          f"{per_task_rep * n_rep:24.1f}  (read + summary only)")
    print(f"{'  peak RSS [MB]':38s} {report['rss_mb']:24.0f} "
          f"{today_read['bytes_per_row'] * N_PER_TASK * n_rep / 2**20:24.0f}")
    print(f"{'same ' + str(nt) + ' loose files: read [s]':38s} {counts_same['s']:24.2f} "
          f"{today_read['report_read_s']:24.2f}  (ratio {today_read['report_read_s'] / counts_same['s']:.1f}x)")
    print(f"fit: {fit['n_sources']} sources, converged={fit['converged']}, m50_0 median "
          f"{fit['m50_0']} (truth 26.8 at z = 8 with depth_ref {DEPTH_REF})")
    print(f"targets: fit <= 60 s and <= 2048 MB: "
          f"{fit['wall_s'] - fit['read_s'] <= 60 and fit['rss_mb'] <= 2048}; "
          f"report <= 10 s: {report['wall_s'] <= 10}")
    print(f"(stores under {root}; delete when done)")


if __name__ == "__main__":
    main()
