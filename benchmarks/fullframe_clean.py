"""Full-frame sep CLEAN: sep's own (quadratic) against glaciar's emulation (issue 11).

The field set-up's reference extraction (``clean_style="region"``, the
default) runs sep once on the whole detection image with CLEAN on.  sep's CLEAN
compares every object with every earlier one; glaciar's
(:func:`glaciar.engine.segmentation.sep_extract_clean`) extracts with CLEAN off
and applies the same CLEAN in linear time.  For square crops of the detection
band of a demo survey (background-subtracted, sanitized, detection RMS: what
the reference extraction hands sep) this prints per side:

* pre-CLEAN objects (sep without CLEAN);
* seconds of sep without CLEAN, sep with CLEAN (skipped above ``--sep-max``),
  the emulation (which includes its own sep call without CLEAN), and their ratio;
* peak RSS increase of each call [MB]: the kernel's high-water mark of the
  process (reset just before the call) minus the resident memory before it
  (inputs already loaded); outputs count (the segmentation map is 4 bytes per
  pixel);
* whether the emulation's catalogue and segmentation equal sep's (every field,
  ``np.array_equal``).

Each measurement (method and side) runs in its own child process.  The crossover
``EMULATED_CLEAN_MIN_OBJECTS`` was chosen where the two times meet.

Usage::

    python benchmarks/fullframe_clean.py [--config demo.yaml] [--sides 2000,4000,8000]
        [--sep-max 8000] [--workdir DIR]
    python benchmarks/fullframe_clean.py --config /path/s16000/demo.yaml --sides 16000 --sep-max 0

Without ``--config`` a demo survey of the largest side is generated in
``--workdir`` (seed 3; ~60 s and ~1.3 GB at 8000^2).  Mind the memory at 16000^2:
the band alone is ~1 GB per float32 array.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _child import spawn

MB = 1024.0 ** 2


def _status_bytes(key: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return 1024.0 * float(line.split()[1])
    raise RuntimeError(f"no {key} in /proc/self/status")


class _PeakRSS:
    """Peak resident memory [bytes] of a block above the level at entry.

    The kernel's high-water mark (``VmHWM``, reset to the current RSS on entry
    through ``/proc/self/clear_refs``) sees allocations inside C code too
    (``ru_maxrss`` would also carry the parent's peak across fork + exec).
    """

    def __enter__(self):
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        self.base = _status_bytes("VmRSS")
        return self

    def __exit__(self, *exc):
        self.peak = _status_bytes("VmHWM")
        self.increase = self.peak - self.base


# --------------------------------------------------------------------------
# Inputs: the detection band as the reference extraction sees it
# --------------------------------------------------------------------------
def _write_inputs(config: str, sides: list[int], out: Path) -> None:
    """Crops of the sanitized detection band, its detection RMS and no-data mask, as .npy."""
    from glaciar.config import load_config
    from glaciar.engine.detect import detection_rms, sanitize
    from glaciar.fieldprep import detection_params, band_pixels
    from glaciar.survey import Survey

    cfg = load_config(config)
    survey = Survey(cfg)
    field = list(survey.fields)[0]
    params = detection_params(cfg)
    fp = survey.footprint(field)
    base, rms, _ = band_pixels(survey, field, cfg.survey.detection_band, fp, params)
    data, err, nodata = sanitize(base, rms, ~fp)
    del base, rms
    err = detection_rms(err, nodata, params)
    for s in sides:
        if s > data.shape[0] or s > data.shape[1]:
            raise SystemExit(f"--sides: {s} is larger than the survey's image {data.shape}")
        for name, arr in (("data", data), ("err", err), ("nodata", nodata)):
            np.save(out / f"{name}_{s}.npy", np.ascontiguousarray(arr[:s, :s]))


# --------------------------------------------------------------------------
# Child: one side, every method
# --------------------------------------------------------------------------
def _child(opt) -> dict:
    """One side, one method (``--method``), in a fresh process: time and peak RSS increase."""
    from glaciar.config import load_config
    from glaciar.engine.detect import sep_extract
    from glaciar.engine.segmentation import sep_extract_clean
    from glaciar.fieldprep import detection_params

    params = detection_params(load_config(opt.config))
    d = Path(opt.inputs)
    data, err, nodata = (np.load(d / f"{n}_{opt.side}.npy") for n in ("data", "err", "nodata"))
    with _PeakRSS() as m:
        t0 = time.perf_counter()
        if opt.method == "emulation":
            cat, seg = sep_extract_clean(data, err, nodata, params, min_objects=0)
        else:
            cat, seg = sep_extract(data, err, nodata, params, opt.method == "sep")
        dt = time.perf_counter() - t0
    out = {f"{opt.method}_s": dt, f"{opt.method}_rss_mb": m.increase / MB,
           f"{opt.method}_process_peak_mb": m.peak / MB}
    if opt.method == "noclean":
        out["objects"] = len(cat)
    elif opt.method == "emulation":
        np.save(d / f"emu_cat_{opt.side}.npy", cat)
        np.save(d / f"emu_seg_{opt.side}.npy", seg)
    else:
        ce, se = np.load(d / f"emu_cat_{opt.side}.npy"), np.load(d / f"emu_seg_{opt.side}.npy")
        out["identical"] = bool(ce.dtype == cat.dtype and np.array_equal(ce, cat) and np.array_equal(se, seg))
    return out


def _spawn(args: list[str]) -> dict:
    """Run this script as a child with ``args``; return the JSON it prints last."""
    return spawn(__file__, args)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", help="demo survey config (default: generate one in --workdir)")
    ap.add_argument("--sides", default="2000,4000,8000", help="crop sides [pixels] (default 2000,4000,8000)")
    ap.add_argument("--sep-max", type=int, default=8000,
                    help="largest side on which sep's own CLEAN runs (default 8000; 16000: ~30 min+)")
    ap.add_argument("--workdir", help="where a generated survey and the crops go (default: a temp dir)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--side", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--inputs", help=argparse.SUPPRESS)
    ap.add_argument("--method", choices=("noclean", "emulation", "sep"), help=argparse.SUPPRESS)
    opt = ap.parse_args(argv)
    if opt.child:
        print(json.dumps(_child(opt)))
        return 0
    sides = sorted(int(s) for s in opt.sides.split(","))
    with tempfile.TemporaryDirectory(dir=opt.workdir) as tmp:
        tmp = Path(tmp)
        config = opt.config
        if config is None:
            from glaciar.demo import build_demo_survey

            side = sides[-1]
            print(f"generating a {side}^2 demo survey ...", flush=True)
            config = str(build_demo_survey(tmp / "survey", shape=(side, side), seed=3, n_galaxies=100,
                                           n_iterations=30, z_values=(8.0,), mag_values=(26.0,)))
        _write_inputs(config, sides, tmp)
        rows = []
        for s in sides:
            r = {"side": s}
            for method in ("noclean", "emulation", "sep"):
                if method == "sep" and s > opt.sep_max:
                    continue
                r.update(_spawn(["--child", "--config", config, "--side", str(s), "--inputs", str(tmp),
                                 "--method", method]))
            rows.append(r)
            print(f"  {s}^2 done: {r}", flush=True)
    print(f"\n{'side':>6s} {'objects':>8s} {'sep noCLEAN s':>14s} {'sep CLEAN s':>12s} {'emulation s':>12s} "
          f"{'emu/sep':>8s} {'dRSS MB: noCLEAN':>17s} {'sep CLEAN':>10s} {'emulation':>10s} {'identical':>10s}")
    for r in rows:
        sc = r.get("sep_s")
        sep_s = "skipped" if sc is None else f"{sc:.2f}"
        ratio = "-" if sc is None else f"{r['emulation_s'] / sc:.2f}"
        sep_rss = "-" if sc is None else f"{r['sep_rss_mb']:.0f}"
        same = "-" if "identical" not in r else ("yes" if r["identical"] else "NO")
        print(f"{r['side']:>6d} {r['objects']:>8d} {r['noclean_s']:>14.2f} {sep_s:>12s} "
              f"{r['emulation_s']:>12.2f} {ratio:>8s} {r['noclean_rss_mb']:>17.0f} {sep_rss:>10s} "
              f"{r['emulation_rss_mb']:>10.0f} {same:>10s}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
