"""Injection-recovery throughput beside its floor (issue 3, part 11).

Builds the embedded 4-band demo field (BoRG-like, correlated noise, F160W
detection at DETECT_THRESH 0.7, MINAREA 9, gauss_2.0_5x5) in a temporary
directory, runs ``--warmup`` untimed tasks (default 1), then times N tasks of ``n`` injected sources
through :func:`glaciar.engine.task.run_task` and prints, in CPU milliseconds
per injected source (``time.process_time``):

* the whole pipeline (draws, stamps, injection, detection, classification,
  photometry, selection), the share spent in ``measure_injected``, and the
  share spent drawing the injected sources' shot noise (``add_shot_noise``:
  its draws are fixed by the rows, and the floor draws none);
* the *floor* for the same injected scenes: one ``sep.extract`` of the
  detection windows tiled into one array (each source's last window from the
  windowed algorithm, at least 33 x 33), plus ``sep.sum_circle`` in every
  aperture and band on the tiled band windows.  Only the sep calls are timed
  (building the tiled arrays is not counted), so the floor is a lower bound;
* the full-frame alternative: one ``sep.extract`` of the whole injected
  detection image plus ``sep.sum_circle`` on the whole band images;
* ratios from the same run (the machine may be shared: absolute times are
  noisy, ratios much less).

No ratio to GLACiAR is printed here: a ratio must come from one run on one
machine, which ``benchmarks/vs_glaciar.py`` does (the original GLACiAR through
the peer harness and ``glaciar simulate`` on the same job, whole process).

``--save-tables DIR`` writes each timed task's per-source table as Parquet
(``m<mag>_task<k>.parquet``); ``--compare-tables DIR`` compares this run's
tables with such a directory, bit for bit (NaN equal to NaN), e.g. before and
after an engine change.

Usage::

    python benchmarks/throughput.py [--size 1200] [--tasks 10] [--n 100] [--z 8] [--mag 24 26 28] [--warmup 1] [--profile]
                                    [--save-tables DIR] [--compare-tables DIR]
"""
from __future__ import annotations

import argparse
import dataclasses
import inspect
import tempfile
import time

import numpy as np
import sep

import glaciar.engine.task as task_module
from glaciar.config import load_config
from glaciar.constants import STATUS_NOT_DETECTED
from glaciar.demo import build_demo_survey
from glaciar.engine.measure import measure_injected
from glaciar.engine.canvas import pack_windows
from glaciar.fieldprep import build_field_context
from glaciar.plan import plan_tasks
from glaciar.survey import Survey

MIN_WINDOW = 33


def _bind(args, kwargs):
    sig = inspect.signature(measure_injected)
    b = sig.bind(*args, **kwargs)
    b.apply_defaults()
    got = dict(b.arguments)
    setup = got.pop("setup", None)         # the field-constant inputs (MeasureSetup), flattened
    if setup is not None:
        got.update({f.name: getattr(setup, f.name) for f in dataclasses.fields(setup)})
    return got


def _sep_detect(data, err, mask, params):
    sep.set_extract_pixstack(int(max(data.size + 1024, 4096)))
    sep.set_sub_object_limit(int(params.sub_object_limit))
    t = time.process_time()
    sep.extract(data, float(params.detect_thresh), err=err, mask=mask, minarea=int(params.detect_minarea),
                filter_kernel=params.filter_kernel, filter_type=params.filter_type,
                deblend_nthresh=int(params.deblend_nthresh), deblend_cont=float(params.deblend_mincont),
                clean=bool(params.clean), clean_param=float(params.clean_param), segmentation_map=True)
    return time.process_time() - t


def _sum_circles(data, rms, mask, x, y, params, gain):
    t = time.process_time()
    for d in params.phot_apertures:
        sep.sum_circle(data, x, y, 0.5 * d, err=rms, mask=mask, gain=gain, subpix=0)
    return time.process_time() - t


def _windows_at_least(win, x, y, shape, side):
    """Each window grown to at least ``side`` pixels per axis around the source, inside the image."""
    ny, nx = shape
    win = win.copy()
    ix, iy = np.floor(x + 0.5).astype(np.int64), np.floor(y + 0.5).astype(np.int64)
    for ax, (c, n_ax) in enumerate(((iy, ny), (ix, nx))):
        lo, hi = win[:, 2 * ax], win[:, 2 * ax + 1]
        small = hi - lo < side
        lo[small] = np.clip(c[small] - side // 2, 0, max(n_ax - side, 0))
        hi[small] = np.minimum(lo[small] + side, n_ax)
    return win


def floor_and_full(a, windows):
    """CPU seconds of the floor and of the full-frame alternative for one task's scenes."""
    det, det_rms, params, mask = a["det_scene"], a["det_rms"], a["params"], a["mask"]
    x, y = np.asarray(a["x"], float), np.asarray(a["y"], float)
    win = _windows_at_least(windows, x, y, det.shape, MIN_WINDOW)
    gap = max(params.filter_halfwidth + 1, 2)
    oy, ox, shape = pack_windows(win[:, 1] - win[:, 0], win[:, 3] - win[:, 2], gap)
    sl = [(slice(oy[k], oy[k] + y1 - y0), slice(ox[k], ox[k] + x1 - x0), slice(y0, y1), slice(x0, x1))
          for k, (y0, y1, x0, x1) in enumerate(win.tolist())]
    cx, cy = x - win[:, 2] + ox, y - win[:, 0] + oy

    def tiled(scene, rms):
        data = np.zeros(shape)
        scene.paste_windows(data, win, oy, ox)
        err = np.ones(shape)
        bad = np.ones(shape, dtype=bool)
        for a0, a1, b0, b1 in sl:
            err[a0, a1] = rms[b0, b1]
            bad[a0, a1] = False if mask is None else mask[b0, b1]
        bad |= ~np.isfinite(data) | ~(np.isfinite(err) & (err > 0))
        data[bad], err[bad] = 0.0, 1.0
        return data, err, bad

    d, e, m = tiled(det, det_rms)
    t_floor = _sep_detect(d.astype(np.float32), e.astype(np.float32), m, params)
    for band, scene in a["band_scenes"].items():
        d, e, m = tiled(scene, a["band_rms"][band])
        t_floor += _sum_circles(d, e, m, cx, cy, params, a["gains"].get(band))

    def whole(scene, rms):
        data = scene.full()
        err = np.array(rms, dtype=np.float64)
        bad = ~np.isfinite(data) | ~(np.isfinite(err) & (err > 0))
        if mask is not None:
            bad |= mask
        data[bad], err[bad] = 0.0, 1.0
        return data, err, bad

    d, e, m = whole(det, det_rms)
    t_full = _sep_detect(d.astype(np.float32), e.astype(np.float32), m, params)
    for band, scene in a["band_scenes"].items():
        d, e, m = whole(scene, a["band_rms"][band])
        t_full += _sum_circles(d, e, m, x, y, params, a["gains"].get(band))
    return t_floor, t_full, win


def measure_mag(opt, mag, tmp):
    """Time ``opt.tasks`` tasks at one magnitude; returns a dict of CPU seconds and counts."""
    t0 = time.perf_counter()
    path = build_demo_survey(tmp, shape=(opt.size, opt.size), seed=opt.seed, n_galaxies=opt.n,
                             n_iterations=opt.tasks + opt.warmup, z_values=(opt.z,), mag_values=(mag,))
    t_build = time.perf_counter() - t0
    if opt.clean_style is not None:
        import yaml
        raw = yaml.safe_load(open(path))
        raw.setdefault("detection", {})["CLEAN_STYLE"] = opt.clean_style
        with open(path, "w") as fh:
            yaml.safe_dump(raw, fh)
    cfg = load_config(path)
    t0 = time.process_time()
    ctx = build_field_context(cfg, Survey.from_config(cfg), cfg.survey.fields[0])
    t_ctx = time.process_time() - t0
    specs = plan_tasks(cfg)
    seed = cfg.simulation.seed

    real = task_module.measure_injected
    rec = {}
    has_diag = "diagnostics" in inspect.signature(real).parameters

    def recording(*args, **kwargs):
        diag = {}
        if has_diag:
            kwargs = dict(kwargs, diagnostics=diag)
        t = time.process_time()
        out = real(*args, **kwargs)
        rec["t_measure"] = time.process_time() - t
        rec["args"], rec["kwargs"], rec["diag"] = args, kwargs, diag
        return out

    real_noise = task_module.add_shot_noise

    def noise_clock(*args, **kwargs):
        t = time.process_time()
        out = real_noise(*args, **kwargs)
        rec["t_noise"] = rec.get("t_noise", 0.0) + time.process_time() - t
        return out

    task_module.measure_injected = recording
    task_module.add_shot_noise = noise_clock
    r = dict(t_pipe=0.0, t_meas=0.0, t_noise=0.0, t_floor=0.0, t_full=0.0, n_src=0, n_det=0, rounds=[], areas=[],
             t_build=t_build, t_ctx=t_ctx, ctx=ctx, prof=None, tables=[])
    try:
        for spec in specs[:opt.warmup]:                           # warm-up (template cache)
            task_module.run_task(ctx, spec, seed)
        rec.clear()
        if opt.profile:
            import cProfile
            r["prof"] = cProfile.Profile()
        for spec in specs[opt.warmup:opt.warmup + opt.tasks]:
            if r["prof"] is not None:
                r["prof"].enable()
            t = time.process_time()
            table = task_module.run_task(ctx, spec, seed)
            r["t_pipe"] += time.process_time() - t
            if r["prof"] is not None:
                r["prof"].disable()
            r["t_meas"] += rec["t_measure"]
            r["t_noise"] += rec.get("t_noise", 0.0)
            r["tables"].append(table)
            r["n_src"] += len(table)
            r["n_det"] += int(np.sum(table["status"].to_numpy() != STATUS_NOT_DETECTED))
            a = _bind(rec["args"], rec["kwargs"])
            # (an engine without diagnostics: the floor uses the minimum windows)
            windows = rec["diag"].get("window", np.zeros((len(table), 4), dtype=np.int64))
            f, g, win = floor_and_full(a, windows)
            r["t_floor"] += f
            r["t_full"] += g
            r["rounds"].append(rec["diag"].get("rounds", 0))
            r["areas"].append((win[:, 1] - win[:, 0]) * (win[:, 3] - win[:, 2]))
            rec.clear()
    finally:
        task_module.measure_injected = real
        task_module.add_shot_noise = real_noise
    return r


def table_path(directory, mag: float, k: int):
    from pathlib import Path
    return Path(directory) / f"m{mag:g}_task{k}.parquet"


def save_tables(directory, rows) -> None:
    """Each timed task's per-source table, as Parquet (float bits kept)."""
    from pathlib import Path
    Path(directory).mkdir(parents=True, exist_ok=True)
    for mag, r in rows:
        for k, table in enumerate(r["tables"]):
            table.to_parquet(table_path(directory, mag, k), index=False)


def same_bits(a, b) -> bool:
    """Two columns equal bit for bit (floats by their bytes, so NaN == NaN)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype.kind in "fc":
        return a.tobytes() == b.tobytes()
    return bool(np.all(a == b))


def compare_tables(directory, rows) -> bool:
    """Print whether this run's tables equal those saved in ``directory``; True if all do."""
    import pandas as pd
    n_same = n_all = 0
    diffs = []
    for mag, r in rows:
        for k, table in enumerate(r["tables"]):
            n_all += 1
            path = table_path(directory, mag, k)
            if not path.exists():
                diffs.append(f"{path.name}: missing")
                continue
            old = pd.read_parquet(path)
            if list(old.columns) != list(table.columns):
                diffs.append(f"{path.name}: columns differ")
                continue
            bad = [c for c in table.columns if not same_bits(old[c].to_numpy(), table[c].to_numpy())]
            if bad:
                diffs.append(f"{path.name}: {', '.join(bad[:5])}{' ...' if len(bad) > 5 else ''}")
            else:
                n_same += 1
    print(f"tables vs {directory}: {n_same} of {n_all} task tables bit-identical"
          + ("" if not diffs else "; differ: " + "; ".join(diffs[:10])))
    return n_same == n_all


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1200, help="image side [pixels] (default 1200)")
    ap.add_argument("--tasks", type=int, default=10, help="timed tasks per magnitude (default 10)")
    ap.add_argument("--n", type=int, default=100, help="injected sources per task (default 100)")
    ap.add_argument("--z", type=float, default=8.0, help="redshift of the injected sources (default 8)")
    ap.add_argument("--mag", type=float, nargs="+", default=[24.0, 26.0, 28.0],
                    help="F160W magnitudes [AB], one row each (default 24 26 28)")
    ap.add_argument("--seed", type=int, default=3, help="seed of the demo images (default 3)")
    ap.add_argument("--warmup", type=int, default=1,
                    help="untimed tasks first (default 1); the template cache fills over the first "
                         "~6 tasks of the demo, so larger values give the steady state of a long run")
    ap.add_argument("--profile", action="store_true", help="also print a cProfile of the timed tasks")
    ap.add_argument("--sort", default="tottime", help="cProfile sort key (default tottime)")
    ap.add_argument("--top", type=int, default=25, help="cProfile rows printed (default 25)")
    ap.add_argument("--clean-style", default=None,
                    help="DetectionParams.clean_style (default: the configuration's, i.e. glaciar's default)")
    ap.add_argument("--save-tables", default=None, metavar="DIR",
                    help="write each timed task's per-source table to DIR (Parquet)")
    ap.add_argument("--compare-tables", default=None, metavar="DIR",
                    help="compare each timed task's table with those saved in DIR, bit for bit")
    opt = ap.parse_args(argv)

    rows = []
    for mag in opt.mag:
        with tempfile.TemporaryDirectory(prefix="glaciar-throughput-") as tmp:
            rows.append((mag, measure_mag(opt, mag, tmp)))
    ctx = rows[0][1]["ctx"]
    print(f"glaciar throughput: {opt.size}x{opt.size} px demo field, {len(ctx.bands)} bands "
          f"({', '.join(ctx.bands)}; detection {ctx.detection_band}), {opt.tasks} tasks x {opt.n} sources "
          f"per magnitude at z = {opt.z:g}, after {opt.warmup} untimed task(s)")
    print(f"(field context {rows[0][1]['t_ctx']:.2f} s CPU, once per field and worker, not in the per-source "
          f"figures; ms = CPU milliseconds per injected source, ratios from this run)")
    print()
    hdr = (f"{'m':>5s} {'detected':>8s} {'pipeline':>9s} {'measure':>8s} {'rest':>7s} {'noise':>7s} {'floor':>7s} "
           f"{'full':>7s} {'pipe/floor':>10s} {'meas/floor':>10s} {'rounds':>6s} "
           f"{'median win':>10s}")
    print(hdr)
    for mag, r in rows:
        ms = lambda t: 1e3 * t / r["n_src"]  # noqa: E731
        area = np.concatenate(r["areas"])
        print(f"{mag:5.1f} {r['n_det'] / r['n_src']:8.0%} {ms(r['t_pipe']):9.3f} {ms(r['t_meas']):8.3f} "
              f"{ms(r['t_pipe'] - r['t_meas']):7.3f} {ms(r['t_noise']):7.3f} {ms(r['t_floor']):7.3f} "
              f"{ms(r['t_full']):7.3f} "
              f"{r['t_pipe'] / r['t_floor']:10.2f} {r['t_meas'] / r['t_floor']:10.2f} "
              f"{np.mean(r['rounds']):6.1f} "
              f"{np.median(area):10.0f}")
    print()
    print("pipeline: run_task (draws, stamps, injection, detection, classification, photometry, selection);")
    print("measure: measure_injected alone; rest = pipeline - measure; noise: the shot-noise draws (part of rest;")
    print("0 without gains); floor: 1 tiled sep.extract of the last")
    print(f"windows (>= {MIN_WINDOW}^2) + sum_circle per aperture and band; full: sep.extract of the whole image "
          f"+ sum_circle;")
    print("target (issues 11, 24): pipe/floor <= 2 (<= 3 at m = 26); the ratio to GLACiAR: "
          "benchmarks/vs_glaciar.py (same job, same machine).")
    if opt.save_tables:
        save_tables(opt.save_tables, rows)
    if opt.compare_tables:
        compare_tables(opt.compare_tables, rows)
    if opt.profile:
        import pstats
        for mag, r in rows:
            print(f"\n---- cProfile, m = {mag:g}")
            pstats.Stats(r["prof"]).sort_stats(opt.sort).print_stats(opt.top)


if __name__ == "__main__":
    main()
