"""The ``glaciar`` command: demo, init, simulate, report, fit, next.

Every sub-command turns expected failures (bad config, missing file, mismatched
store, bad option value) into a one-line message on stderr and exit status 2
(set GLACIAR_DEBUG=1 to see the traceback instead).  SIGINT and SIGTERM stop a
run cleanly (one line, exit 130 / 143); the same command resumes it.
"""
from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

from . import __version__
from . import constants as C

__all__ = ["main"]


def _cmd_init(args) -> int:
    from .config import template_yaml
    from .store import atomic_write_text

    path = Path(args.path)
    if path.exists() and not args.force:
        raise FileExistsError(f"{path}: exists; use --force to overwrite")
    atomic_write_text(path, template_yaml())
    print(f"wrote {path}")
    return 0


def _load(config_path):
    from .config import check_files, load_config

    cfg = load_config(config_path)
    check_files(cfg)
    for w in getattr(cfg, "warnings", ()) or ():
        print(f"warning: {w}", file=sys.stderr)
    return cfg


def _check_out_dir(out: Path, option: str = "--out") -> Path:
    """Refuse an output path that exists and is not a directory (before anything is written)."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{option} {out}: exists and is not a directory")
    return out


def _cmd_simulate(args) -> int:
    from .run import default_workers, simulate

    out = Path(args.out) if args.out else Path(args.config).resolve().parent / "glaciar-run"
    _check_out_dir(out)
    cfg = _load(args.config)
    executor = None
    if args.scheduler:
        from dask.distributed import Client  # optional extra: pip install glaciar[dask]
        executor = Client(args.scheduler).get_executor()
    workers = args.workers if args.workers is not None else default_workers()
    stats = simulate(cfg, out, workers=workers, seed=args.seed, executor=executor,
                     progress=not args.quiet, mode=args.mode)
    print(f"{stats['n_run']} tasks run ({stats['n_done_before']} already done of {stats['n_tasks']}), "
          f"{stats['n_sources']} sources, {stats['wall_seconds']:.1f} s wall, "
          f"{1e3 * stats['cpu_seconds'] / max(stats['n_sources'], 1):.3f} ms CPU per source")
    _report(out, regions=cfg.output.regions)
    print(f"results in {out}")
    return 0


def _report(run_dir: Path, regions: bool = False) -> list[Path]:
    from .plots import plot_summary_maps
    from .store import (StoreWarning, read_current_counts, read_current_results, read_manifest,
                        store_columns)
    from .tables import summary_table, write_regions, write_summaries

    # What fit uses too: the tasks the run's configuration lists now; their stored counts
    # (footers only), or the rows of a store written before counts.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", StoreWarning)
        got = read_current_counts(run_dir)
        have = store_columns(run_dir)
        rows = got[0] if got is not None else read_current_results(run_dir, columns=[
            c for c in (C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_STATUS, C.COL_RECOVERED,
                        C.COL_SELECTED) if c in have])
    _print_warnings(caught)
    manifest = read_manifest(run_dir) or {}
    out_dir = run_dir / C.SUMMARY_DIRNAME
    meta = {k: manifest[k] for k in ("config_hash", "seed", "detection_band", "selection") if k in manifest}
    paths = write_summaries(rows, out_dir, meta)
    mag_label = "M_UV" if manifest.get("magnitude_type") == "absolute" else \
        f"m ({manifest.get('detection_band', 'detection band')}, AB)"
    for field, sub in rows.groupby(C.COL_FIELD):
        paths += plot_summary_maps(summary_table(sub), out_dir, str(field), mag_label)
    if regions:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", StoreWarning)     # printed above
            src = read_current_results(run_dir, columns=[
                c for c in (C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE,
                            C.COL_X, C.COL_Y, C.COL_STATUS) if c in have])
        paths += write_regions(src, out_dir / "regions")
    return paths


def _cmd_report(args) -> int:
    paths = _report(Path(args.run_dir), regions=args.regions)
    if args.html:
        from .report import write_html_report
        paths.append(write_html_report(Path(args.run_dir)))
    for p in paths:
        print(p)
    return 0


def _print_warnings(caught) -> None:
    """Each warning as one line on stderr (no source line, no repeats)."""
    seen = set()
    for w in caught:
        msg = str(w.message)
        if msg not in seen:
            seen.add(msg)
            print(f"warning: {msg}", file=sys.stderr)


def _fit(run_dir, **kwargs) -> Path:
    import json

    from .pipeline import format_summary, run_fit

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            path = run_fit(run_dir, **kwargs)
        finally:
            _print_warnings(caught)
    summary = json.loads((Path(run_dir) / "fit" / "summary.json").read_text())
    print(format_summary(summary), end="")
    return path


def _cmd_fit(args) -> int:
    cosmology = None
    if args.cosmology:
        from .galaxy.population import get_cosmology
        cosmology = get_cosmology(args.cosmology)
    path = _fit(args.run_dir, model=args.model, per_field=args.per_field, seed=args.seed,
                progress=not args.quiet, cosmology=cosmology, area_arcmin2=args.area_arcmin2,
                max_steps=args.max_steps, depth=args.depth)
    print(f"wrote {path}")
    return 0


def _cmd_next(args) -> int:
    import numpy as np

    from .inference import SelectionFunction, propose_cells
    from .store import read_manifest

    run_dir = Path(args.run_dir)
    sf = SelectionFunction.read(run_dir / C.SELECTION_FUNCTION_NAME, field=args.field)
    manifest = read_manifest(run_dir) or {}
    zv = np.asarray(manifest.get("z_values", []), float)
    mv = np.asarray(manifest.get("mag_values", []), float)
    if zv.size < 2 or mv.size < 2:
        raise ValueError(f"{run_dir}: manifest has no z/mag grid to refine")
    # Propose on a grid twice as fine as the one simulated, inside its range.
    zg = np.linspace(zv.min(), zv.max(), 2 * zv.size - 1)
    mg = np.linspace(mv.min(), mv.max(), 2 * mv.size - 1)
    cells = propose_cells(sf, zg, mg, args.n)
    print("# z mag width_68 median_CS")
    for row in cells:
        print(f"{row['z']:.3f} {row['mag']:.3f} {row['width']:.4f} {row['median']:.4f}")
    return 0


def _cmd_demo(args) -> int:
    from .demo import build_demo_survey
    from .run import default_workers, simulate

    out = _check_out_dir(Path(args.out))
    t0 = time.perf_counter()
    cfg_path = build_demo_survey(out / "survey", seed=args.seed)
    print(f"demo survey written: {cfg_path} ({time.perf_counter() - t0:.1f} s)")
    cfg = _load(cfg_path)
    run_dir = out / "run"
    workers = args.workers if args.workers is not None else default_workers()
    stats = simulate(cfg, run_dir, workers=workers, progress=not args.quiet)
    print(f"simulated {stats['n_sources']} sources in {stats['wall_seconds']:.1f} s")
    for p in _report(run_dir, regions=False):
        print(p)
    if not args.no_fit:
        path = _fit(run_dir, progress=not args.quiet)
        print(f"selection function: {path}")
    print(f"demo finished in {time.perf_counter() - t0:.1f} s; results in {run_dir}")
    return 0


def _finite_positive(text):
    """argparse type: a finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return v


def _int_at_least(minimum: int):
    """argparse type: an integer >= ``minimum``."""
    def parse(text):
        try:
            v = int(text, 10)
        except ValueError:
            v = None
        if v is None or v < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}")
        return v
    parse.__name__ = f"integer >= {minimum}"
    return parse


_positive_int = _int_at_least(1)
_non_negative_int = _int_at_least(0)


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line: ``glaciar: error: --workers: ...`` (exit 2)."""

    def error(self, message):
        if message.startswith("argument "):
            message = message[len("argument "):]
        message = " ".join(message.split())
        self.exit(2, f"glaciar: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="glaciar", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"glaciar {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("demo", help="build the embedded demo survey and run simulate → report → fit")
    s.add_argument("--out", default="glaciar-demo")
    s.add_argument("--workers", type=_positive_int, default=None)
    s.add_argument("--seed", type=_non_negative_int, default=2018)
    s.add_argument("--no-fit", action="store_true")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_cmd_demo)

    s = sub.add_parser("init", help="write a commented configuration template")
    s.add_argument("path", nargs="?", default="glaciar.yaml")
    s.add_argument("--force", action="store_true")
    s.set_defaults(func=_cmd_init)

    s = sub.add_parser("simulate", help="run (or resume) the injection-recovery simulation")
    s.add_argument("config")
    s.add_argument("--out", default=None, help="run directory (default: glaciar-run beside the config)")
    s.add_argument("--workers", type=_positive_int, default=None,
                   help="worker processes, >= 1 (default: all CPUs)")
    s.add_argument("--seed", type=_non_negative_int, default=None,
                   help="override simulation.seed (an integer >= 0)")
    s.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://host:8786")
    s.add_argument("--mode", choices=["windowed", "full"], default="windowed")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_cmd_simulate)

    s = sub.add_parser("report", help="summary tables (ECSV) and plots of a run")
    s.add_argument("run_dir")
    s.add_argument("--regions", action="store_true", help="also write DS9 region files")
    s.add_argument("--html", action="store_true",
                   help="also write RUN_DIR/report.html, one self-contained page (glaciar.report)")
    s.set_defaults(func=_cmd_report)

    s = sub.add_parser("fit", help="fit C(m, z) and S(z, m) with emcee; write selection_function.fits")
    s.add_argument("run_dir")
    s.add_argument("--model", default="auto", choices=["auto", "logistic", "erf", "fleming", "sas"],
                   help="completeness step (auto: chosen by PSIS-LOO; sas: flexible monotone)")
    s.add_argument("--max-steps", type=_positive_int, default=None,
                   help="cap on each chain's steps in this call (a re-run extends unconverged chains)")
    s.add_argument("--depth", default="auto", choices=["auto", "on", "off"],
                   help="depth-aware completeness C(m - local depth, z) (auto: when depth varies)")
    s.add_argument("--per-field", action="store_true")
    s.add_argument("--seed", type=_non_negative_int, default=0)
    s.add_argument("--area-arcmin2", type=_finite_positive, default=None,
                   help="survey area for V_eff (default: the footprint area in the run manifest)")
    s.add_argument("--cosmology", default=None, help="astropy realisation for V_eff (default Planck18)")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=_cmd_fit)

    s = sub.add_parser("next", help="(z, m) cells where the fitted selection is least certain")
    s.add_argument("run_dir")
    s.add_argument("-n", type=_positive_int, default=5, help="number of cells (>= 1)")
    s.add_argument("--field", default=None, help="which field's fit, for per-field files")
    s.set_defaults(func=_cmd_next)
    return p


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings as one line each (``warning: ...``), without the source line."""
    print(f"warning: {message}", file=file or sys.stderr)


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that it unwinds like Ctrl-C."""


def _raise_terminated(signum, frame):
    raise _Terminated()


def main(argv=None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:          # --help, --version, or a one-line usage error
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    show = warnings.showwarning
    warnings.showwarning = _show_warning
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt as exc:
        how, code = ("terminated (SIGTERM)", 128 + signal.SIGTERM) if isinstance(exc, _Terminated) \
            else ("interrupted", 130)
        print(f"glaciar {args.command}: {how}; finished tasks are kept, run the same command "
              "to resume", file=sys.stderr)
        return code
    except (ValueError, FileNotFoundError, FileExistsError, RuntimeError, OSError, KeyError) as exc:
        if os.environ.get("GLACIAR_DEBUG"):
            raise
        print(f"glaciar {args.command}: error: {exc}", file=sys.stderr)
        return 2
    finally:
        warnings.showwarning = show
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
