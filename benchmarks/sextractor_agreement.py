"""glaciar against the SExtractor binary on sources injected into a BoRG-like field.

Builds the demo survey (``glaciar.demo``: a drizzled-like 4-band BoRG pointing,
F160W detection), draws the same injected sources glaciar's tasks draw
(z = 8, several magnitudes around the completeness drop), and measures every
task twice on identical injected images:

* ``glaciar``: the windowed sep engine (``mode="windowed"``) with each
  ``clean_style``: ``sextractor`` (default: SExtractor's incremental CLEAN,
  absorbed pixels handed to the absorber), ``sep-merge`` (sep's CLEAN
  decisions, absorbed pixels handed over) and ``sep`` (sep's CLEAN: absorbed
  pixels left unlabelled);
* ``SExtractor``: the ``source-extractor`` binary on the full frame in
  dual-image mode (``mode="source-extractor"``; its reference segmentation of
  the original image from SExtractor too), classified by the same glaciar code.

Printed per setting: agreement of the recovered flags (status 0, 1, 2) and of
the six statuses, the flips in each direction, the median |delta FLUX_ISO| /
FLUX_ISO (detection band) of sources both detect, and the time ratio
glaciar / SExtractor (whole tasks, one run); then recovered fractions per
magnitude.  glaciar's correlated-noise error model is switched off (SExtractor
has none), so both S/N are FLUX_ISO / FLUXERR_ISO with the same RMS map.

Usage::

    python benchmarks/sextractor_agreement.py                  # ~1000 sources, ~2-4 min
    python benchmarks/sextractor_agreement.py --n-galaxies 50  # quicker

Needs ``source-extractor`` (or ``sex``) on the PATH.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from glaciar import constants as C  # noqa: E402
from glaciar.config import load_config  # noqa: E402
from glaciar.demo import build_demo_survey  # noqa: E402
from glaciar.engine.measure import reference_extraction  # noqa: E402
from glaciar.engine.sextractor_backend import find_sextractor  # noqa: E402
from glaciar.engine.task import run_task  # noqa: E402
from glaciar.fieldprep import build_field_context  # noqa: E402
from glaciar.plan import plan_tasks
from glaciar.survey import Survey  # noqa: E402


def _tasks(ctx, specs, seed, mode):
    rows, t0 = [], time.perf_counter()
    for spec in specs:
        rows.append(run_task(ctx, spec, seed, mode=mode))
    return rows, time.perf_counter() - t0


def _compare(tg, ts, det):
    sg = np.concatenate([t[C.COL_STATUS].to_numpy() for t in tg])
    ss = np.concatenate([t[C.COL_STATUS].to_numpy() for t in ts])
    rg = np.isin(sg, C.RECOVERED_STATUSES)
    rs = np.isin(ss, C.RECOVERED_STATUSES)
    fg = np.concatenate([t[C.band_column("flux_iso", det)].to_numpy() for t in tg])
    fs = np.concatenate([t[C.band_column("flux_iso", det)].to_numpy() for t in ts])
    both = np.isfinite(fg) & np.isfinite(fs) & (fs != 0)
    dflux = np.abs(fg[both] - fs[both]) / np.abs(fs[both])
    return dict(n=sg.size, rec=np.mean(rg == rs), stat=np.mean(sg == ss), g_only=int(np.sum(rg & ~rs)),
                s_only=int(np.sum(rs & ~rg)), dflux=float(np.median(dflux)) if dflux.size else np.nan,
                dflux_n=int(both.sum()), rg=rg, rs=rs, sg=sg, ss=ss)


def _m50(mags, rec):
    """Magnitude where the recovered fraction per input magnitude first falls through 0.5
    (linear interpolation between grid magnitudes; NaN if it never does)."""
    ms = np.array(sorted(set(np.round(mags, 4))))
    f = np.array([rec[np.isclose(mags, m)].mean() for m in ms])
    for k in range(1, ms.size):
        if f[k - 1] >= 0.5 > f[k]:
            return float(ms[k - 1] + (f[k - 1] - 0.5) / (f[k - 1] - f[k]) * (ms[k] - ms[k - 1]))
    return float("nan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="survey directory (default: a temporary one)")
    ap.add_argument("--shape", type=int, default=1000, help="field side [pixels] (default 1000)")
    ap.add_argument("--n-galaxies", type=int, default=100, help="sources per task (default 100)")
    ap.add_argument("--iterations", type=int, default=2, help="iterations per magnitude (default 2)")
    ap.add_argument("--mags", type=float, nargs="+", default=[25.0, 25.5, 26.0, 26.5, 27.0],
                    help="F160W input magnitudes (default 25.0 ... 27.0)")
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--deblend-mincont", type=float, default=None,
                    help="DEBLEND_MINCONT for both (default: the survey's; 1 switches deblending off, "
                         "whose random pixel hand-out differs between any two programs)")
    ap.add_argument("--threshold-rms", choices=["pixel", "filtered"], default="filtered",
                    help="glaciar's threshold_rms (default filtered: SExtractor's threshold with a filter "
                         "and a weight map)")
    ap.add_argument("--styles", nargs="+", default=["region", "sextractor", "sep-merge", "sep"],
                    help="glaciar clean_style values to compare with CLEAN on")
    args = ap.parse_args(argv)
    exe = find_sextractor()
    if exe is None:
        sys.exit("source-extractor (or sex) not found on the PATH: apt-get install source-extractor")
    tmp = None
    out = Path(args.out) if args.out else Path(tmp := tempfile.mkdtemp(prefix="glaciar-sexbench-"))
    cfg_path = out / "demo.yaml"
    if not cfg_path.exists():
        build_demo_survey(out, shape=(args.shape, args.shape), n_galaxies=args.n_galaxies,
                          n_iterations=args.iterations, z_values=(8.0,), mag_values=tuple(args.mags))
    cfg = load_config(cfg_path)
    survey = Survey.from_config(cfg)
    field = cfg.survey.fields[0]
    ctx0 = build_field_context(cfg, survey, field)
    ctx0 = dataclasses.replace(ctx0, noise_models={})
    dp = dataclasses.replace(ctx0.detection_params, threshold_rms=args.threshold_rms)
    if args.deblend_mincont is not None:
        dp = dataclasses.replace(dp, deblend_mincont=args.deblend_mincont)
    ctx0 = dataclasses.replace(ctx0, detection_params=dp)
    specs = [s for s in plan_tasks(cfg) if s.field == field]
    det = ctx0.detection_band
    base, rms, zp = ctx0.bases[det], ctx0.rms[det], ctx0.zeropoints[det]
    import subprocess
    ver = subprocess.run([exe, "-v"], capture_output=True, text=True).stdout.strip()
    dp = ctx0.detection_params
    print(f"field {field} {ctx0.shape[0]}x{ctx0.shape[1]}, {len(specs)} tasks x {ctx0.n_galaxies} sources, "
          f"z = 8, F160W mags {', '.join(f'{m:g}' for m in args.mags)}; DETECT_THRESH {dp.detect_thresh:g}, "
          f"DETECT_MINAREA {dp.detect_minarea}, DEBLEND_NTHRESH {dp.deblend_nthresh}, "
          f"DEBLEND_MINCONT {dp.deblend_mincont:g}, CLEAN_PARAM {dp.clean_param:g}; glaciar threshold_rms "
          f"{dp.threshold_rms}; {ver}")
    settings = [("on", st) for st in args.styles] + [("off", "sextractor")]
    # warm the template cache, so that no timing below pays for rendering
    _tasks(ctx0, specs, args.seed, "windowed")
    header = (f"{'CLEAN':>5} {'glaciar clean_style':>24} {'N':>5} {'recovered =':>11} {'status =':>9} "
              f"{'glaciar only':>12} {'SExtr. only':>11} {'med |dISO|/ISO':>14} {'t glaciar/t SExtr':>17}")
    lines, curves, per_style = [], {}, {}
    se_cache = {}
    for clean_name, style in settings:
        params = dataclasses.replace(ctx0.detection_params, clean=(clean_name == "on"), clean_style=style)
        ref_sep = reference_extraction(base, rms, params, zp, mask=ctx0.mask)
        ctx_g = dataclasses.replace(ctx0, detection_params=params, reference=ref_sep)
        tg, time_g = _tasks(ctx_g, specs, args.seed, "windowed")
        if clean_name not in se_cache:
            ref_se = reference_extraction(base, rms, params, zp, mask=ctx0.mask, backend="source-extractor")
            ctx_s = dataclasses.replace(ctx0, detection_params=params, reference=ref_se)
            se_cache[clean_name] = _tasks(ctx_s, specs, args.seed, "source-extractor")
        ts, time_s = se_cache[clean_name]
        r = _compare(tg, ts, det)
        what = style if clean_name == "on" else "-"
        lines.append(f"{clean_name:>5} {what:>24} {r['n']:5d} {100 * r['rec']:10.2f}% {100 * r['stat']:8.2f}% "
                     f"{r['g_only']:12d} {r['s_only']:11d} {100 * r['dflux']:13.3f}% {time_g / time_s:17.2f}")
        mags = np.concatenate([t[C.COL_MAG].to_numpy() for t in tg])
        curves[(clean_name, what)] = (mags, r["rg"], r["rs"])
        per_style[(clean_name, what)] = tg
    if tmp:
        import shutil
        shutil.rmtree(tmp, ignore_errors=True)
    print(header)
    print("\n".join(lines))
    print("\nrecovered fraction per input magnitude (glaciar / SExtractor)")
    ms = sorted(set(np.round(next(iter(curves.values()))[0], 4)))
    print(f"{'CLEAN':>5} {'glaciar clean_style':>24} " + " ".join(f"{m:>13g}" for m in ms))
    for (clean_name, what), (mags, rg, rs) in curves.items():
        cells = []
        for m in ms:
            sel = np.isclose(mags, m)
            cells.append(f"{rg[sel].mean():.3f}/{rs[sel].mean():.3f}")
        print(f"{clean_name:>5} {what:>24} " + " ".join(f"{c:>13}" for c in cells))
    print("\nm50 (recovered fraction 0.5, interpolated) glaciar / SExtractor [mag]")
    for (clean_name, what), (mags, rg, rs) in curves.items():
        print(f"{clean_name:>5} {what:>24}  {_m50(mags, rg):7.3f} / {_m50(mags, rs):7.3f}")
    if ("on", "sep") in per_style:
        # glaciar's CLEAN styles against plain sep's CLEAN (clean_style "sep" reproduces a
        # full-frame sep.extract: tests/engine/test_measure.py)
        print("\nagainst clean_style 'sep' (plain sep's CLEAN on the full frame), CLEAN on")
        for (clean_name, what), tg in per_style.items():
            if clean_name != "on" or what == "sep":
                continue
            r = _compare(tg, per_style[("on", "sep")], det)
            mags = curves[(clean_name, what)][0]
            print(f"{what:>24}: recovered flags equal {100 * r['rec']:.2f} % ({r['g_only']} only {what}, "
                  f"{r['s_only']} only sep), median |dISO|/ISO {100 * r['dflux']:.3f} %, m50 "
                  f"{_m50(mags, r['rg']):.3f} vs {_m50(mags, r['rs']):.3f}")


if __name__ == "__main__":
    main()
