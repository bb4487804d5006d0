"""The original GLACiAR and glaciar on the same job, on this machine (issue 24, point 3).

Both programs run the same injection-recovery job, one after the other, each as
one child process with one worker: GLACiAR (Carrasco et al. 2018, the public
code, unmodified in its logic) through the peer harness, glaciar through
``glaciar simulate`` on the very ``parameters.yaml`` the harness writes for
GLACiAR (glaciar reads GLACiAR's parameter file as it is:
``glaciar.config.glaciar_compat``) and the same staged images.  Printed, from
this one run (never from constants measured elsewhere):

* whole-process CPU per injected source of each program (user + system CPU of
  the child and everything it ran and waited for: GLACiAR's SExtractor calls,
  imports, set-up, stamp builds, writing), and the ratio GLACiAR / glaciar;
* with two job sizes, the marginal CPU per source (difference of the two jobs'
  CPU over the difference of their sources: the fixed costs cancel) and its ratio;
* peak RSS of each (the largest process of the child's tree, ``ru_maxrss`` from
  ``os.wait4``) and the wall time; and what was resident at the child's sampled peak
  (``/proc/<pid>/status`` every :data:`RSS_SAMPLE_PERIOD` s: anonymous memory and
  file-backed pages -- code of the libraries, memory-mapped field caches -- and when in
  the run it came; Linux only, the child itself, not its own children);
* the load average before and after each child: on a shared machine CPU time
  still compares, wall time does not.

The job is the harness's ``config.yaml`` (4-band 1200x1200 WFC3-like field,
z = 9.6-11.0 in 8 bins, m = 24.0-28.0 in 21 bins, 100 galaxies per
iteration, 3 iterations: 50 400 sources, ~19 min of GLACiAR CPU on an idle
2-core machine, the harness's README says) with the number of redshift bins and
iterations overridden: the default is 2 z bins (9.6, 9.8) x 21 mags x 100
galaxies x 1 and 2 iterations, i.e. jobs of 4 200 and 8 400 sources (~2 and
~3.5 min of GLACiAR CPU, ~10 s and ~15 s of glaciar's).  ``--z-bins 8
--iterations 3`` runs the harness's full job.

``--stages`` then runs glaciar once more on the largest job with its stages
wrapped (:class:`StageClock`) and prints the whole process's CPU by stage
(set-up, draws, stamps, injection, extraction, photometry, classification,
selection, writing, imports, configuration).

Set-up of the peer (once; see the harness's README.md)::

    HARNESS=<project's shared dir>/peers/glaciar     # holds run_glaciar.py, config.yaml, field/
    GLACIAR_VENV=/tmp/peer/venv $HARNESS/setup_env.sh          # prints: export GLACIAR_PY=...
    # the original code, from a clone or mirror of github.com/danielacarrasco/GLACiAR:
    GLACIAR_GIT=/path/to/GLACiAR.git $HARNESS/export_glaciar.sh /tmp/peer/glaciar_src
    export GLACIAR_HARNESS=$HARNESS GLACIAR_SRC=/tmp/peer/glaciar_src GLACIAR_PY=/tmp/peer/venv/bin/python

Usage (from the repository's root, with glaciar importable)::

    python benchmarks/vs_glaciar.py [--harness DIR] [--z-bins 2] [--iterations 1 2]
                                    [--scratch DIR] [--keep] [--glaciar-only] [--stages]

Without the peer set up it says what is missing and exits with status 2.
Both children run with OMP/OpenBLAS/MKL threads = 1 (one worker each).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

#: GLACiAR steps z and m by a hard-coded 0.2 (the harness's README, "Inputs ...").
GLACIAR_STEP = 0.2
SINGLE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: How often :func:`run_measured` samples the child's resident set [s].
RSS_SAMPLE_PERIOD = 0.02

SETUP_HELP = """\
vs_glaciar: the GLACiAR peer is not set up ({what}).
Set it up once (the harness's README.md says more):
  HARNESS=<shared dir>/peers/glaciar
  GLACIAR_VENV=/tmp/peer/venv $HARNESS/setup_env.sh        # prints GLACIAR_PY
  GLACIAR_GIT=<clone of github.com/danielacarrasco/GLACiAR> $HARNESS/export_glaciar.sh /tmp/peer/glaciar_src
  export GLACIAR_HARNESS=$HARNESS GLACIAR_SRC=/tmp/peer/glaciar_src GLACIAR_PY=/tmp/peer/venv/bin/python
or run with --glaciar-only."""


def peer_paths(opt) -> tuple[Path, Path, str]:
    """(harness dir, GLACiAR source tree, peer Python); exits 2 naming what is missing."""
    harness = opt.harness or os.environ.get("GLACIAR_HARNESS")
    if not harness:
        default = Path(__file__).resolve().parents[1].parent / "shared" / "peers" / "glaciar"
        harness = str(default)
    harness = Path(harness)
    missing = None
    if not (harness / "run_glaciar.py").is_file():
        missing = f"no run_glaciar.py in {harness}: pass --harness or set GLACIAR_HARNESS"
    elif not (harness / "field" / "field.json").is_file():
        missing = f"no field in {harness / 'field'}: run the harness's run.sh once (it builds it)"
    src = os.environ.get("GLACIAR_SRC", "")
    py = os.environ.get("GLACIAR_PY", "")
    if missing is None and not (src and Path(src, "completeness.py").is_file()):
        missing = f"GLACIAR_SRC={src or '(unset)'} holds no completeness.py"
    if opt.glaciar_only:
        py = ""
    elif missing is None and not (py and shutil.which(py)):
        missing = f"GLACIAR_PY={py or '(unset)'} is not an executable Python"
    if missing is None and py:
        probe = subprocess.run([py, "-c", "import numpy, scipy, astropy, yaml, pysysp"],
                               capture_output=True, text=True)
        if probe.returncode != 0:
            missing = f"GLACIAR_PY={py} lacks the peer's packages (run setup_env.sh)"
    if missing is None and py and not (shutil.which("source-extractor") or shutil.which("sex")
                                or os.environ.get("SEX_BIN")):
        missing = "SExtractor not found (apt-get install source-extractor, or set SEX_BIN)"
    if missing is not None:
        print(SETUP_HELP.format(what=missing), file=sys.stderr)
        sys.exit(2)
    return harness, Path(src), py


def job_config(harness: Path, z_bins: int, iterations: int) -> dict:
    """The harness's config.yaml with ``z_bins`` redshifts from its min_z and ``iterations``."""
    cfg = yaml.safe_load((harness / "config.yaml").read_text())
    cfg["z_bins"] = int(z_bins)
    cfg["max_z"] = round(float(cfg["min_z"]) + GLACIAR_STEP * (int(z_bins) - 1), 6)
    cfg["n_iterations"] = int(iterations)
    return cfg


def n_sources(cfg: dict) -> int:
    return int(cfg["z_bins"]) * int(cfg["mag_bins"]) * int(cfg["n_iterations"]) * int(cfg["n_galaxies"])


def status_mb(pid: int) -> dict | None:
    """``VmRSS``, ``RssAnon``, ``RssFile``, ``RssShmem`` [MB] of a process (None: gone, or not
    Linux)."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            text = fh.read()
    except OSError:
        return None
    out = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "RssAnon", "RssFile", "RssShmem"):
            out[key] = int(value.split()[0]) / 1024.0
    return out if "VmRSS" in out else None


class RssSampler:
    """Samples a process's resident set from a thread; keeps the sample of the largest VmRSS
    and when it came (``peak``: the status fields and ``t`` [s] from the start)."""

    def __init__(self, pid: int, period: float = RSS_SAMPLE_PERIOD):
        import threading

        self.pid, self.period, self.peak = pid, period, None
        self._stop = threading.Event()
        self._t0 = time.perf_counter()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            s = status_mb(self.pid)
            if s is not None and (self.peak is None or s["VmRSS"] > self.peak["VmRSS"]):
                self.peak = dict(s, t=time.perf_counter() - self._t0)
            if self._stop.wait(self.period):
                return

    def stop(self) -> dict | None:
        self._stop.set()
        self._thread.join()
        return self.peak


def run_measured(cmd: list[str], env: dict, log: Path) -> dict:
    """Run ``cmd``; its CPU (user + sys, waited-for descendants included), peak RSS (and the
    child's sampled peak: :class:`RssSampler`) and wall time."""
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    with open(log, "wb") as fh:
        proc = subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT)
        sampler = RssSampler(proc.pid)
        # The sampler reads /proc/<pid> until the child is reaped: wait4 then frees the pid.
        _, status, ru = os.wait4(proc.pid, 0)
        rss_peak = sampler.stop()
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        tail = log.read_text(errors="replace")[-3000:]
        raise RuntimeError(f"{' '.join(map(str, cmd[:3]))} ... exited {proc.returncode}; end of {log}:\n{tail}")
    return {"cpu_s": ru.ru_utime + ru.ru_stime, "user_s": ru.ru_utime, "sys_s": ru.ru_stime,
            "maxrss_mb": ru.ru_maxrss / 1024.0, "wall_s": wall, "rss_peak": rss_peak,
            "load": (load0, os.getloadavg()[0])}


def rss_note(meas: dict) -> str:
    """What was resident at the child's sampled peak, e.g. ``(anon 312 + file 96 MB at 81 s of
    154 s)``; empty without samples."""
    p = meas.get("rss_peak")
    if not p or "RssAnon" not in p:
        return ""
    return (f" (sampled peak {p['VmRSS']:.0f} MB: anon {p['RssAnon']:.0f} + file "
            f"{p.get('RssFile', 0.0) + p.get('RssShmem', 0.0):.0f} MB, at {p['t']:.0f} s of "
            f"{meas['wall_s']:.0f} s)")


def child_env(extra: dict | None = None) -> dict:
    env = dict(os.environ, MPLBACKEND="Agg", **SINGLE_THREAD)
    env.update(extra or {})
    return env


def stage_inputs(harness: Path, src: Path, cfg: dict, work: Path) -> Path:
    """Lay out GLACiAR's inputs as the harness does, without running GLACiAR.

    ``work/glaciar/`` holds the original tree and its parameters.yaml (the original
    file with ``cfg``'s keys over it, the harness's ``field`` and ``harness`` keys
    dropped), ``work/list.txt`` the field name, ``work/data/`` the unzipped images.
    """
    import gzip

    gdir, ddir = work / "glaciar", work / "data"
    for d in (gdir, ddir):
        if d.exists():
            shutil.rmtree(d)
    shutil.copytree(src, gdir, ignore=shutil.ignore_patterns(".git"))
    ddir.mkdir(parents=True)
    own = {k: v for k, v in cfg.items() if k not in ("field", "harness")}
    field = str(cfg.get("field", "F01"))
    params = yaml.safe_load((gdir / "parameters.yaml").read_text())
    params.update(own)
    params["path_to_images"] = str(ddir) + "/"
    params["list_of_fields"] = str(work / "list.txt")
    (work / "list.txt").write_text(field + "\n")
    (gdir / "parameters.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    for f in sorted((harness / "field").glob(f"{params['image_name']}{field}_*.fits*")):
        name = f.name[:-3] if f.name.endswith(".gz") else f.name
        with (gzip.open(f, "rb") if f.name.endswith(".gz") else open(f, "rb")) as fi, \
                open(ddir / name, "wb") as fo:
            shutil.copyfileobj(fi, fo)
    return gdir / "parameters.yaml"


def stage_peer_job(harness: Path, src: Path, py: str, cfg: dict, job_dir: Path, run: bool) -> dict:
    """Run GLACiAR through the harness on ``cfg`` (or, with ``run`` False, only stage its inputs).

    Returns the measurement (None without ``run``), the staged parameters.yaml and the number
    of sources GLACiAR injected.
    """
    job_dir.mkdir(parents=True, exist_ok=True)
    cfg_path = job_dir / "config.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    work = job_dir / "peer_work"
    env = child_env({"GLACIAR_SRC": str(src), "GLACIAR_WORK": str(work)})
    results = job_dir / "peer_results"
    cmd = [py, str(harness / "run_glaciar.py"), "--config", str(cfg_path),
           "--field-dir", str(harness / "field"), "--results", str(results)]
    if not run:
        params = stage_inputs(harness, src, cfg, work)
        return {"meas": None, "params": params, "n": n_sources(cfg)}
    meas = run_measured(cmd, env, job_dir / "peer.log")
    timing = json.loads((results / "timing.json").read_text())
    if timing.get("status") != "ok":
        raise RuntimeError(f"GLACiAR run failed: {timing.get('status')} (see {results / 'timing.json'})")
    meas["n"] = int(timing["n_iterations_run"]) * int(cfg["n_galaxies"])
    meas["stamp_s"] = float(timing.get("stamp_time_total_s") or 0.0)
    meas["sextractor_s"] = float(timing.get("sextractor_time_total_s") or 0.0)
    return {"meas": meas, "params": work / "glaciar" / "parameters.yaml", "n": meas["n"]}


def run_glaciar(params: Path, job_dir: Path) -> dict:
    """``glaciar simulate`` on GLACiAR's staged parameters.yaml, 1 worker, in a child process."""
    out = job_dir / "glaciar_run"
    if out.exists():
        shutil.rmtree(out)
    cmd = [sys.executable, "-m", "glaciar", "simulate", str(params), "--out", str(out),
           "--workers", "1", "--quiet"]
    log = job_dir / "glaciar.log"
    meas = run_measured(cmd, child_env(), log)
    text = log.read_text(errors="replace")
    m = re.search(r"tasks run \(.*?\), (\d+) sources, .*?\(([\d.]+) s set-up\)", text)
    if m is None:
        raise RuntimeError(f"no summary line in {log}")
    meas["n"], meas["setup_wall_s"] = int(m.group(1)), float(m.group(2))
    return meas


def _maxrss_mb() -> float:
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class StageClock:
    """Exclusive CPU time (``time.process_time``) per stage of wrapped functions.

    A wrapped call's time goes to its stage minus the time of wrapped calls inside
    it (which go to theirs), so the stages add up to the instrumented part of the
    process.  The wrappers cost ~1 us a call (a few thousand calls per task).
    """

    def __init__(self):
        self.cpu: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.rss_growth: dict[str, float] = {}      # MB by which the peak RSS grew in a stage
        self._peak = _maxrss_mb()
        self._stack: list[list] = []          # [stage, CPU of wrapped calls inside it]

    def add(self, stage: str, dt: float) -> None:
        self.cpu[stage] = self.cpu.get(stage, 0.0) + dt
        self.calls[stage] = self.calls.get(stage, 0) + 1
        peak = _maxrss_mb()
        if peak > self._peak:
            self.rss_growth[stage] = self.rss_growth.get(stage, 0.0) + peak - self._peak
            self._peak = peak

    def wrap(self, stage: str, fn):
        import functools

        @functools.wraps(fn)
        def timed(*a, **k):
            own = stage
            outer = self._stack[-1][0] if self._stack else ""
            if outer.startswith(DEFER_TO) and not stage.startswith(outer.split(":")[0]):
                own = outer          # e.g. sep.extract inside the set-up stays set-up
            t0 = time.process_time()
            self._stack.append([own, 0.0])
            try:
                return fn(*a, **k)
            finally:
                dt = time.process_time() - t0
                inner = self._stack.pop()[1]
                self.add(own, dt - inner)
                if self._stack:
                    self._stack[-1][1] += dt
        return timed

    def patch(self, owner, name: str, stage: str) -> None:
        """Wrap ``owner.name`` (a module's function or a class's method) in place."""
        fn = owner.__dict__.get(name) if isinstance(owner, type) else getattr(owner, name, None)
        if fn is None:
            raise RuntimeError(f"stage profile: {getattr(owner, '__name__', owner)}.{name} is gone "
                               "(glaciar changed: update STAGES in benchmarks/vs_glaciar.py)")
        setattr(owner, name, self.wrap(stage, fn))


#: Stages whose nested calls of other kinds (sep.extract, photometry, ...) stay theirs.
DEFER_TO = ("set-up", "writing")
#: (module, attribute[, class], stage): where each stage's functions are looked up at call
#: time.  Names imported with ``from x import f`` are patched in the importing module.
STAGES = [
    ("glaciar.config", "load_config", None, "config: read and validate"),
    ("glaciar.config", "check_files", None, "config: read and validate"),
    ("glaciar.execute", "open_run", None, "set-up: input checks, fingerprints, manifest"),
    ("glaciar.manifest", "check_inputs", None, "set-up: input checks, fingerprints, manifest"),
    ("glaciar.manifest", "detection_z_limit", None, "set-up: detection z limit, placement check"),
    ("glaciar.manifest", "placement_preflight", None, "set-up: detection z limit, placement check"),
    ("glaciar.fieldprep", "field_settings", None, "set-up: settings, PSFs, templates"),
    ("glaciar.manifest", "field_settings", None, "set-up: settings, PSFs, templates"),
    ("glaciar.fieldprep", "band_pixels", None, "set-up: read images, background"),
    ("glaciar.fieldprep", "reference_extraction", None, "set-up: reference extraction"),
    ("glaciar.fieldprep", "correlated_noise", None, "set-up: empty apertures (noise record)"),
    ("glaciar.fieldprep", "field_depth", None, "set-up: depth map"),
    ("glaciar.contexts", "field_depth_area", None, "set-up: depth map"),
    ("glaciar.contexts", "field_noise_record", None, "set-up: empty apertures (noise record)"),
    ("glaciar.execute", "prepare_context_cache", None, "writing: field cache"),
    ("glaciar.engine.task", "task_rng", None, "draws (spectra, shapes, sizes, positions)"),
    ("glaciar.engine.task", "draw_task_sources", None, "draws (spectra, shapes, sizes, positions)"),
    ("glaciar.engine.task", "draw_positions", None, "draws (spectra, shapes, sizes, positions)"),
    ("glaciar.galaxy.templates", "stamp", "TemplateCache", "stamps (render, convolve, cache)"),
    ("glaciar.engine.scene", "__init__", "Scene", "injection (scenes, canvases, band windows)"),
    ("glaciar.engine.context", "detection_scene", "FieldContext",
     "injection (scenes, canvases, band windows)"),
    ("glaciar.engine.canvas", "__init__", "Canvas", "injection (scenes, canvases, band windows)"),
    ("glaciar.engine.canvas", "band", "Canvas", "injection (scenes, canvases, band windows)"),
    ("glaciar.engine.task", "measure_injected", None,
     "extraction: windows, exactness checks, CLEAN"),
    ("sep", "extract", None, "extraction: sep.extract"),
    ("glaciar.engine.measure", "_finish", None, "photometry (ISO, AUTO, apertures, template AUTO)"),
    ("glaciar.engine.measure", "classify", None, "classification"),
    ("glaciar.engine.measure", "footprint_overlap", None, "classification"),
    ("glaciar.engine.selection", "__call__", "Selection", "selection"),
    # The injected stamps' shot noise (bands with a gain) is drawn inside task_columns.
    ("glaciar.engine.task", "add_shot_noise", None, "injection: shot noise (stamps' pixel draws)"),
    ("glaciar.engine.task", "apply_selection", None, "selection"),
    ("glaciar.execute", "task_columns", None, "per-task table (fluxes, columns)"),
    ("glaciar.execute", "write_task_table", None, "writing: task files"),
    ("glaciar.execute", "compact", None, "writing: compaction"),
    ("glaciar.execute", "finish_context_cache", None, "writing: field cache"),
    ("glaciar.cli", "_report", None, "writing: summaries (report tables, PNG maps)"),
]


def stages_child(params: str, out: str) -> None:
    """In this process: import glaciar, wrap the stages, run ``glaciar simulate``; print JSON."""
    import importlib

    c0 = time.process_time()
    rss0 = _maxrss_mb()
    clock = StageClock()
    clock.rss_growth["interpreter start-up"] = rss0
    import glaciar.cli
    for mod in {m for m, *_ in STAGES}:
        importlib.import_module(mod)
    import glaciar.report  # noqa: F401  (imported by the summaries at the end)
    import glaciar.plots  # noqa: F401
    clock.add("imports (glaciar, numpy, scipy, astropy, pandas, matplotlib)", time.process_time() - c0)
    for mod, name, cls, stage in STAGES:
        owner = importlib.import_module(mod)
        clock.patch(getattr(owner, cls) if cls else owner, name, stage)
    import contextlib
    import io
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        rc = glaciar.cli.main(["simulate", params, "--out", out, "--workers", "1", "--quiet"])
    if rc:
        raise SystemExit(f"glaciar simulate exited {rc}")
    import resource
    ru = resource.getrusage(resource.RUSAGE_SELF)
    print(json.dumps({"cpu": clock.cpu, "calls": clock.calls, "total": ru.ru_utime + ru.ru_stime,
                      "rss_growth": clock.rss_growth, "maxrss": ru.ru_maxrss / 1024.0}))


def stage_table(job_dir: Path, params: Path, n: int) -> list[str]:
    """Run :func:`stages_child` in a new process on one job; the lines of its table."""
    out = job_dir / "glaciar_stages_run"
    if out.exists():
        shutil.rmtree(out)
    proc = subprocess.run([sys.executable, __file__, "--stages-child", str(params), str(out)],
                          env=child_env(), capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"stage profile failed:\n{proc.stderr[-3000:]}")
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    total = r["total"]
    rows = sorted(r["cpu"].items(), key=lambda kv: -kv[1])
    rest = total - sum(r["cpu"].values())
    lines = [f"glaciar simulate, {n} sources, 1 worker, stages instrumented: whole-process CPU "
             f"{total:.2f} s = {1e3 * total / n:.3f} ms per source; exclusive CPU by stage",
             f"{'stage':<56s} {'CPU s':>7s} {'ms/source':>9s} {'share':>6s}"]
    for stage, t in rows + [("interpreter start-up and the rest", rest)]:
        lines.append(f"{stage:<56s} {t:7.2f} {1e3 * t / n:9.3f} {t / total:6.1%}")
    grow = sorted(r["rss_growth"].items(), key=lambda kv: -kv[1])
    lines.append(f"peak RSS {r['maxrss']:.0f} MB, reached by steps in: "
                 + ", ".join(f"{k} +{v:.0f}" for k, v in grow if v >= 1.0) + " (MB)")
    return lines


def fmt_row(label, a, b, unit, ratio=True, digits=1):
    r = f"{a / b:8.1f}x" if ratio and b else f"{'':9s}"
    return f"{label:<40s} {a:>10.{digits}f} {b:>10.{digits}f} {r}  {unit}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--harness", default=None,
                    help="the peer harness directory (default: $GLACIAR_HARNESS, else "
                         "<repository>/../shared/peers/glaciar)")
    ap.add_argument("--z-bins", type=int, default=2, help="redshift bins from the config's min_z, step 0.2 "
                                                         "(default 2: z = 9.6, 9.8; the config has 8)")
    ap.add_argument("--iterations", type=int, nargs="+", default=[1, 2],
                    help="n_iterations of each job size (default 1 2; the config has 3)")
    ap.add_argument("--scratch", default=None, help="scratch directory (default: a new temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the scratch directory (GLACiAR writes "
                                                         "~70 MB of catalogues per 100 iterations)")
    ap.add_argument("--stages", action="store_true",
                    help="also profile glaciar's whole process by stage on the largest job "
                         "(another run, in a new process)")
    ap.add_argument("--stages-child", nargs=2, metavar=("PARAMS", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--glaciar-only", action="store_true",
                    help="stage the inputs with the harness but time glaciar alone (no ratio)")
    opt = ap.parse_args(argv)
    if opt.stages_child:
        stages_child(*opt.stages_child)
        return

    harness, src, py = peer_paths(opt)
    scratch = Path(opt.scratch) if opt.scratch else Path(tempfile.mkdtemp(prefix="glaciar-vs-peer-"))
    scratch.mkdir(parents=True, exist_ok=True)
    rows, stages = [], []
    try:
        for it in opt.iterations:
            cfg = job_config(harness, opt.z_bins, it)
            job = scratch / f"job_{n_sources(cfg)}"
            print(f"[vs_glaciar] job {n_sources(cfg)} sources: z_bins {cfg['z_bins']} "
                  f"({cfg['min_z']}-{cfg['max_z']}), mag_bins {cfg['mag_bins']}, n_iterations {it}, "
                  f"n_galaxies {cfg['n_galaxies']}", flush=True)
            peer = stage_peer_job(harness, src, py, cfg, job, run=not opt.glaciar_only)
            if peer["meas"] is not None:
                p = peer["meas"]
                print(f"[vs_glaciar]   GLACiAR: {p['cpu_s']:.1f} s CPU, {p['wall_s']:.1f} s wall, "
                      f"{p['maxrss_mb']:.0f} MB{rss_note(p)}", flush=True)
            g = run_glaciar(peer["params"], job)
            print(f"[vs_glaciar]   glaciar: {g['cpu_s']:.1f} s CPU, {g['wall_s']:.1f} s wall, "
                  f"{g['maxrss_mb']:.0f} MB{rss_note(g)}", flush=True)
            if g["n"] != peer["n"]:
                raise RuntimeError(f"glaciar injected {g['n']} sources, GLACiAR {peer['n']}: not the same job")
            rows.append((peer["n"], peer["meas"], g))
        if opt.stages:
            stages = stage_table(job, peer["params"], peer["n"])
    finally:
        if not opt.keep:
            shutil.rmtree(scratch, ignore_errors=True)

    print()
    print(f"GLACiAR (harness {harness.name}/, source {src}) vs glaciar, same job, 1 worker, this machine "
          f"({os.cpu_count()} CPUs); CPU = user + system of the whole process tree")
    print(f"{'':40s} {'GLACiAR':>10s} {'glaciar':>10s} {'ratio':>9s}")
    for n, p, g in rows:
        if p is None:
            print(f"{f'{n} sources: CPU per source':<40s} {'-':>10s} {1e3 * g['cpu_s'] / n:>10.2f}"
                  f" {'':9s}  ms")
            print(f"{f'{n} sources: peak RSS':<40s} {'-':>10s} {g['maxrss_mb']:>10.0f}"
                  f" {'':9s}  MB{rss_note(g)}")
            continue
        print(fmt_row(f"{n} sources: CPU per source", 1e3 * p["cpu_s"] / n, 1e3 * g["cpu_s"] / n, "ms",
                      digits=2))
        print(fmt_row(f"{n} sources: whole-process CPU", p["cpu_s"], g["cpu_s"], "s"))
        print(fmt_row(f"{n} sources: wall time", p["wall_s"], g["wall_s"], "s"))
        print(fmt_row(f"{n} sources: peak RSS", p["maxrss_mb"], g["maxrss_mb"], "MB", digits=0))
        if rss_note(g):
            print(f"{'':40s} glaciar{rss_note(g)}")
    if len(rows) >= 2:
        (n0, p0, g0), (n1, p1, g1) = rows[0], rows[-1]
        dn = n1 - n0
        if dn > 0:
            gm = 1e3 * (g1["cpu_s"] - g0["cpu_s"]) / dn
            if p0 is not None:
                pm = 1e3 * (p1["cpu_s"] - p0["cpu_s"]) / dn
                print(fmt_row(f"marginal CPU per source ({n0}->{n1})", pm, gm, "ms", digits=2))
            else:
                print(f"{f'marginal CPU per source ({n0}->{n1})':<40s} {'-':>10s} {gm:>10.2f}"
                      f" {'':9s}  ms")
            print(f"{'fixed cost (intercept)':<40s} "
                  + (f"{p0['cpu_s'] - n0 * pm / 1e3:>10.1f}" if p0 is not None else f"{'-':>10s}")
                  + f" {g0['cpu_s'] - n0 * gm / 1e3:>10.1f} {'':9s}  s")
    loads = [x for _, p, g in rows for m in (p, g) if m is not None for x in m["load"]]
    print(f"load average (1 min) before/after the children: {min(loads):.2f}-{max(loads):.2f} on "
          f"{os.cpu_count()} CPUs" + ("  -> the machine was LOADED: compare CPU, not wall"
                                      if max(loads) > 1.5 else ""))
    for n, p, g in rows:
        if p is not None:
            print(f"GLACiAR {n}: stamp builds {p['stamp_s']:.1f} s, SExtractor {p['sextractor_s']:.1f} s "
                  f"(harness timing.json, wall); glaciar {n}: set-up {g['setup_wall_s']:.1f} s wall")
    if stages:
        print()
        print("\n".join(stages))
    if opt.keep:
        print(f"scratch kept in {scratch}")


if __name__ == "__main__":
    main()
