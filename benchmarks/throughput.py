"""Injection-recovery throughput beside its floor (issue 3, part 11).

Builds the embedded 4-band demo field (BoRG-like, correlated noise, F160W
detection at DETECT_THRESH 0.7, MINAREA 9, gauss_2.0_5x5) in a temporary
directory, runs one warm-up task, then times N tasks of ``n`` injected sources
through :func:`glaciar.engine.task.run_task` and prints, in CPU milliseconds
per injected source (``time.process_time``):

* the whole pipeline (draws, stamps, injection, detection, classification,
  photometry, selection), and the share spent in ``measure_injected``;
* the *floor* for the same injected scenes: one ``sep.extract`` of the
  detection windows tiled into one array (each source's last window from the
  windowed algorithm, at least 33 x 33), plus ``sep.sum_circle`` in every
  aperture and band on the tiled band windows.  Only the sep calls are timed
  (building the tiled arrays is not counted), so the floor is a lower bound;
* the full-frame alternative: one ``sep.extract`` of the whole injected
  detection image plus ``sep.sum_circle`` on the whole band images;
* ratios from the same run (the machine may be shared: absolute times are
  noisy, ratios much less), and the speed-up over GLACiAR's 18 ms per
  injected source.

Usage::

    python benchmarks/throughput.py [--size 1200] [--tasks 10] [--n 100] [--z 8] [--mag 26]
"""
from __future__ import annotations

import argparse
import inspect
import tempfile
import time

import numpy as np
import sep

import glaciar.engine.task as task_module
from glaciar.config import load_config
from glaciar.demo import build_demo_survey
from glaciar.engine.measure import measure_injected
from glaciar.engine.windows import pack_windows
from glaciar.run import build_field_context, plan_tasks
from glaciar.survey import Survey

GLACIAR_MS_PER_SOURCE = 18.0   # Carrasco et al. 2018 code on a BoRG field (issue 3)
MIN_WINDOW = 33


def _bind(args, kwargs):
    sig = inspect.signature(measure_injected)
    b = sig.bind(*args, **kwargs)
    b.apply_defaults()
    return b.arguments


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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1200, help="image side [pixels] (default 1200)")
    ap.add_argument("--tasks", type=int, default=10, help="timed tasks (default 10)")
    ap.add_argument("--n", type=int, default=100, help="injected sources per task (default 100)")
    ap.add_argument("--z", type=float, default=8.0, help="redshift of the injected sources (default 8)")
    ap.add_argument("--mag", type=float, default=26.0, help="F160W magnitude [AB] (default 26)")
    ap.add_argument("--seed", type=int, default=3, help="seed of the demo images (default 3)")
    ap.add_argument("--profile", action="store_true", help="also print a cProfile of the timed tasks")
    ap.add_argument("--sort", default="tottime", help="cProfile sort key (default tottime)")
    ap.add_argument("--top", type=int, default=25, help="cProfile rows printed (default 25)")
    ap.add_argument("--clean-style", default=None,
                    help="DetectionParams.clean_style (default: the configuration's, i.e. glaciar's default)")
    opt = ap.parse_args(argv)

    with tempfile.TemporaryDirectory(prefix="glaciar-throughput-") as tmp:
        t0 = time.perf_counter()
        path = build_demo_survey(tmp, shape=(opt.size, opt.size), seed=opt.seed, n_galaxies=opt.n,
                                 n_iterations=opt.tasks + 1, z_values=(opt.z,), mag_values=(opt.mag,))
        t_build = time.perf_counter() - t0
        cfg = load_config(path)
        t0 = time.process_time()
        if opt.clean_style is not None:
            import yaml
            raw = yaml.safe_load(open(path))
            raw.setdefault("detection", {})["CLEAN_STYLE"] = opt.clean_style
            with open(path, "w") as fh:
                yaml.safe_dump(raw, fh)
            cfg = load_config(path)
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

        task_module.measure_injected = recording
        try:
            task_module.run_task(ctx, specs[0], seed)                 # warm-up
            t_pipe = t_meas = t_floor = t_full = 0.0
            n_src = 0
            rounds, areas = [], []
            prof = None
            if opt.profile:
                import cProfile
                prof = cProfile.Profile()
            for spec in specs[1:opt.tasks + 1]:
                if prof is not None:
                    prof.enable()
                t = time.process_time()
                table = task_module.run_task(ctx, spec, seed)
                t_pipe += time.process_time() - t
                if prof is not None:
                    prof.disable()
                t_meas += rec["t_measure"]
                n_src += len(table)
                a = _bind(rec["args"], rec["kwargs"])
                # (an engine without diagnostics: the floor uses the minimum windows)
                windows = rec["diag"].get("window", np.zeros((len(table), 4), dtype=np.int64))
                f, g, win = floor_and_full(a, windows)
                t_floor += f
                t_full += g
                rounds.append(rec["diag"].get("rounds", 0))
                areas.append((win[:, 1] - win[:, 0]) * (win[:, 3] - win[:, 2]))
                rec.clear()
        finally:
            task_module.measure_injected = real

    ms = lambda t: 1e3 * t / n_src  # noqa: E731
    area = np.concatenate(areas)
    nb = len(ctx.bands)
    print(f"glaciar throughput: {opt.size}x{opt.size} px demo field, {nb} bands "
          f"({', '.join(ctx.bands)}; detection {ctx.detection_band}), {opt.tasks} tasks x {opt.n} sources "
          f"= {n_src} injected at z = {opt.z:g}, m = {opt.mag:g}")
    print(f"(demo build {t_build:.1f} s wall; field context {t_ctx:.2f} s CPU, once per field and worker)")
    print()
    rows = [
        ("pipeline: run_task, whole task", ms(t_pipe)),
        ("  of which measure_injected", ms(t_meas)),
        ("  of which draws, stamps, injection, selection", ms(t_pipe - t_meas)),
        ("floor: 1 tiled sep.extract + sum_circle", ms(t_floor)),
        (f"full frame: sep.extract {opt.size}^2 + sum_circle", ms(t_full)),
    ]
    print(f"{'':48s} {'ms CPU/source':>14s} {'sources/CPU-s':>14s}")
    for name, v in rows:
        print(f"{name:48s} {v:14.3f} {1e3 / v if v > 0 else float('inf'):14.0f}")
    print()
    print(f"{'ratio pipeline / floor':48s} {t_pipe / t_floor:14.2f}   (target <= 2)")
    print(f"{'ratio measure_injected / floor':48s} {t_meas / t_floor:14.2f}")
    print(f"{'ratio full frame / floor':48s} {t_full / t_floor:14.2f}")
    print(f"{'speed-up vs GLACiAR (18 ms/source), pipeline':48s} {GLACIAR_MS_PER_SOURCE / ms(t_pipe):14.1f}x  "
          f"(target >= 100x, i.e. <= 0.18 ms)")
    print(f"{'speed-up vs GLACiAR, measure_injected alone':48s} {GLACIAR_MS_PER_SOURCE / ms(t_meas):14.1f}x")
    print()
    print(f"detection windows (last round, >= {MIN_WINDOW}^2 for the floor): median {np.median(area):.0f} px, "
          f"mean {area.mean():.0f} px, 90 % {np.percentile(area, 90):.0f} px; "
          f"extraction rounds per task: {np.mean(rounds):.1f}")
    if opt.profile:
        import pstats
        pstats.Stats(prof).sort_stats(opt.sort).print_stats(opt.top)


if __name__ == "__main__":
    main()
