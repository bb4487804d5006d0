"""Peak memory and time of each step of a field's set-up (glaciar.fieldprep.build_field_context).

Usage::

    python benchmarks/setup_memory.py --size 8000 [--dir DIR] [--clean] [--save] [--spill] [--whole-frame]
    python benchmarks/setup_memory.py --config survey.yaml [--field NAME] [--clean] [--save]

``--size N`` writes the demo survey at N x N pixels into ``DIR`` (default a temporary
directory, removed at the end; an existing ``DIR/demo.yaml`` is reused) and measures
its field; ``--config`` measures a field of any survey (its files are only read).
CLEAN is turned off in the measured configuration unless ``--clean`` is given: sep's
CLEAN of the full-frame reference extraction is quadratic in the number of objects
(~30 min at 16000^2) and would hide everything else (benchmarks/scaling.py --no-clean
does the same).  ``--save`` also writes the context's cache (what a run does next,
glaciar.contexts.save_field_context) into a temporary directory.

Each step's peak is the kernel's high-water mark of the resident set (VmHWM of
/proc/self/status), reset at the start of the step (``echo 5 > /proc/self/clear_refs``),
so it includes file pages the step maps (FITS reads, spilled arrays).  Printed per
step: wall and CPU (user + system) seconds, peak RSS [MB], the peak above the RSS
the step started from [MB], that excess per image pixel [bytes/pixel] (at 16000^2
one float32 image is 4 B/px = 1 GB), and the resident set at the step's end,
anonymous / file-backed [MB].  The process must run alone on a quiet machine for the
seconds to mean anything; the memory figures do not depend on the load.

Measured (demo survey, 4 bands, CLEAN off; a shared, loaded 2-core machine):
8000^2 peak 3591 MB (58.8 B/px) before the bounded set-up, 1203 MB (19.7 B/px) after,
CPU 54.5 s -> 40.7 s in the same run conditions; 16000^2 (/work/scratch/s16000) peak
3743 MB (15.3 B/px), 174 s wall.  What remains is the full-frame sep extraction of the
reference (its float32 image, RMS and no-data copies and the segmentation, ~13 B/px,
the floor) and a band's image, noise map and background (~12 B/px).
Issue 24 (16000^2, CLEAN off, same field): peak 4565 -> 3791 MB; the empty apertures
+3946 -> +1538 MB above the step's start (annuli read by row blocks, candidates gathered by
chunks), the depth map +2017 -> +1059 MB, the detection band's pixels +2930 -> +2035 MB
(its background map made after its image and RMS are spilled); the reference extraction,
+3567 MB (14.6 B/px), is the peak.  ``--spill`` measures a small field as a spilled large
one (its bytes per pixel still carry the fixed tile buffers, ~150 MB).
Issue 24, part 2 (16000^2, field reused, old and new code side by side; CLEAN off / on): each
band's pixels 2403-2473 -> 1490-1707 MB (noise map read before the image and again after the
image is spilled); set-up peak 3738 / 3862 MB, the whole-frame reference extraction.
Issue 24, part 3 (16000^2, same field, one session; CLEAN off / on): a spilled field's
reference is extracted by row strips (glaciar.fieldprep.REFERENCE_BY_STRIPS, on; the split
regions' replay packed into few pages): reference step 3756 / 3878 -> 1793 / 1776 MB,
set-up peak 3756 / 3878 -> 1823 / 1810 MB, reference CPU 48 / 100 -> 122 / 225 s.
``--whole-frame`` runs sep on the whole frame instead (the old path).
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

MB = 1024.0 ** 2


def _status_kb(key: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return float(line.split()[1])
    raise RuntimeError(f"no {key} in /proc/self/status (Linux only)")


def _cpu_seconds() -> float:
    """User + system CPU time of this process [s]."""
    t = os.times()
    return t.user + t.system


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")


class StepProbe:
    """Records (step, seconds, peak RSS, RSS at the step's start) at each step's end."""

    def __init__(self):
        self.rows: list[tuple] = []
        self.start()

    def start(self) -> None:
        _reset_peak()
        self._rss0 = _status_kb("VmRSS") * 1024.0
        self._t0 = time.perf_counter()
        self._cpu0 = _cpu_seconds()

    def __call__(self, step: str) -> None:
        peak = _status_kb("VmHWM") * 1024.0
        anon, files = (_status_kb(k) * 1024.0 for k in ("RssAnon", "RssFile"))
        self.rows.append((step, time.perf_counter() - self._t0, _cpu_seconds() - self._cpu0, peak,
                          self._rss0, anon, files))
        self.start()


def _config(opt, tmp: Path):
    """The measured Config (CLEAN off unless --clean), built without changing any file."""
    import yaml

    from glaciar.config import config_from_dict

    if opt.config is None:
        from glaciar.demo import build_demo_survey

        out = Path(opt.dir) if opt.dir else tmp / "survey"
        path = out / "demo.yaml"
        if not path.is_file():
            t0 = time.perf_counter()
            build_demo_survey(out, shape=(opt.size, opt.size), seed=3, n_galaxies=100,
                              n_iterations=30, z_values=(8.0,), mag_values=(26.0,))
            print(f"# generated {path} in {time.perf_counter() - t0:.0f} s", flush=True)
    else:
        path = Path(opt.config)
    data = yaml.safe_load(path.read_text())
    if not opt.clean:
        data.setdefault("detection", {})["CLEAN"] = False
    return config_from_dict(data, base_dir=path.resolve().parent)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--size", type=int, help="generate the demo survey at SIZE x SIZE pixels")
    src.add_argument("--config", help="survey configuration (YAML) to measure")
    ap.add_argument("--dir", help="where --size writes (or finds) its survey")
    ap.add_argument("--field", help="field to measure (default the first)")
    ap.add_argument("--clean", action="store_true", help="keep CLEAN as configured")
    ap.add_argument("--save", action="store_true", help="also write the context's cache")
    ap.add_argument("--spill", action="store_true",
                    help="spill finished arrays to disk whatever the field's size (as a field over "
                         "fieldprep.SPILL_MIN_BYTES is): a small field's bytes per pixel then "
                         "stand for a large one's")
    ap.add_argument("--whole-frame", action="store_true",
                    help="reference extraction by sep on the whole frame, not by row strips "
                         "(glaciar.fieldprep.REFERENCE_BY_STRIPS off)")
    opt = ap.parse_args(argv)

    from glaciar import fieldprep
    from glaciar.contexts import save_field_context
    from glaciar.survey import Survey

    tmp = Path(tempfile.mkdtemp(prefix="glaciar-setupmem-"))
    try:
        cfg = _config(opt, tmp)
        survey = Survey.from_config(cfg)
        field = opt.field or cfg.survey.fields[0]
        ny, nx = survey.shape(field)
        npix = float(ny * nx)
        if opt.spill:
            fieldprep.SPILL_MIN_BYTES = 0
        if opt.whole_frame:
            fieldprep.REFERENCE_BY_STRIPS = False
        probe = StepProbe()
        fieldprep.SETUP_STEP_HOOKS.append(probe)
        t0 = time.perf_counter()
        try:
            ctx = fieldprep.build_field_context(cfg, survey, field)
            if opt.save:
                probe.start()
                ctx = save_field_context(ctx, tmp / "context")
                probe("save_field_context")
        finally:
            fieldprep.SETUP_STEP_HOOKS.remove(probe)
        total = time.perf_counter() - t0
        peak = max(r[3] for r in probe.rows)
        print(f"# field {field}: {ny} x {nx} px, {len(cfg.survey.bands)} bands, "
              f"CLEAN {'on' if cfg.detection.clean else 'off'}, "
              f"{len(ctx.reference.flux)} reference objects")
        print(f"{'step':32s} {'seconds':>8s} {'CPU s':>7s} {'peak MB':>9s} {'+MB':>8s} {'B/px':>6s} "
              f"{'end anon/file MB':>17s}")
        for step, sec, cpu, hwm, rss0, anon, files in probe.rows:
            extra = max(hwm - rss0, 0.0)
            print(f"{step:32s} {sec:8.1f} {cpu:7.1f} {hwm / MB:9.0f} {extra / MB:8.0f} "
                  f"{extra / npix:6.1f} {anon / MB:8.0f}/{files / MB:<8.0f}")
        cpu = sum(r[2] for r in probe.rows)
        print(f"{'total':32s} {total:8.1f} {cpu:7.1f} {peak / MB:9.0f} {'':8s} {peak / npix:6.1f}")
        sys.stdout.flush()
        del ctx
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
