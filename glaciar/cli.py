"""The ``glaciar`` command: demo, init, simulate, status, report, fit, next, catalog, lf, export.

Every sub-command turns expected failures (bad config, missing file, mismatched
store, bad option value) into a one-line message on stderr and exit status 2
(set GLACIAR_DEBUG=1 to see the traceback instead).  SIGINT and SIGTERM stop a
run cleanly (one line, exit 130 / 143); the same command resumes it.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

from .version import __version__
from . import constants as C

__all__ = ["main"]


def _cmd_init(args) -> int:
    from .config import template_yaml
    from .rundir import atomic_write_text

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
    from .execute import simulate
    from .workers import default_workers, process_cpu_seconds

    out = Path(args.out) if args.out else Path(args.config).resolve().parent / "glaciar-run"
    _check_out_dir(out)
    cfg = _load(args.config)
    executor = None
    if args.scheduler:
        from dask.distributed import Client  # optional extra: pip install glaciar[dask]
        executor = Client(args.scheduler).get_executor()
    workers = args.workers if args.workers is not None else default_workers()
    if args.cells:
        cfg = _with_cells_option(cfg, args.cells)
    if args.adaptive:
        if args.shard is not None:
            raise ValueError("--shard: not with --adaptive (its rounds fit the whole run between "
                             "steps); run the shards, then `glaciar simulate --adaptive` unsharded")
        return _simulate_adaptive(args, cfg, out, workers, executor)
    stats = simulate(cfg, out, workers=workers, seed=args.seed, executor=executor,
                     progress=not args.quiet, mode=args.mode, shard=args.shard)
    # Whole process: this command since it started (imports, config, checks, field set-up),
    # its reaped pool workers, and a Dask cluster's workers during their chunks.
    cpu = process_cpu_seconds() + stats["remote_cpu_seconds"]
    n = max(stats["n_sources"], 1)
    print(f"{stats['n_run']} tasks run ({stats['n_done_before']} already done of {stats['n_tasks']}), "
          f"{stats['n_sources']} sources, {stats['wall_seconds']:.1f} s wall "
          f"({stats['setup_seconds']:.1f} s set-up), {1e3 * cpu / n:.3f} ms CPU per source "
          f"(whole process, all workers, set-up included; {1e3 * stats['cpu_seconds'] / n:.3f} "
          "inside the tasks)")
    if args.shard is not None:
        # The summary is the whole run's, written once: after every shard has finished.
        k, n = args.shard
        print(f"shard {k}/{n} finished; `glaciar status {out}` shows the others; once all are "
              f"done, `glaciar report {out}` writes the summary")
        return 0
    from .memory import release_memory
    release_memory()        # the tasks' memory goes before the summaries' comes
    _print_noise(out)
    _report(out, regions=cfg.output.regions)
    print(f"results in {out}")
    return 0


def _cmd_status(args) -> int:
    from .shards import format_status, run_status

    run_dir = Path(args.run_dir)
    print(format_status(run_dir, run_status(run_dir)), end="")
    return 0


def _shard_option(text):
    """argparse type: ``K/N`` (:func:`glaciar.shards.parse_shard`)."""
    from .shards import parse_shard

    try:
        return parse_shard(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _print_noise(out: Path) -> None:
    """Each field's noise factors (map scale, r(N)) as the run's manifest records them."""
    from .fieldprep import noise_summary
    from .rundir import read_manifest

    for line in noise_summary((read_manifest(out) or {}).get("noise")):
        print(line)


def _with_cells_option(cfg, path):
    """``cfg`` plus the cells of the ``--cells`` file; errors name the file."""
    from .config import ConfigError
    from .config.common import At
    from .config.models import read_cells_file
    from .pipeline.adaptive import with_cells

    if not Path(path).is_file():
        raise ConfigError(f"--cells {path}: file not found")
    try:
        return with_cells(cfg, read_cells_file(Path(path)), source_name=f"--cells {path}")
    except At as exc:
        raise ConfigError(f"--cells {path}: {exc.message}") from None


def _simulate_adaptive(args, cfg, out: Path, workers: int, executor) -> int:
    from .pipeline.adaptive import AdaptiveSettings, design_sources, run_adaptive

    # Sources of the design: tasks (iterations of every cell) x n_galaxies.
    design = design_sources(cfg)
    budget = args.budget if args.budget is not None else 3 * design
    round_size = args.round_size if args.round_size is not None else max(
        cfg.simulation.n_galaxies * len(cfg.survey.fields), design // 10)
    settings = AdaptiveSettings(args.target_sd, budget, round_size, max_steps=args.max_steps)
    with _warnings_as_lines():
        rounds = run_adaptive(cfg, out, settings, workers=workers, seed=args.seed,
                              executor=executor, progress=not args.quiet, mode=args.mode)
    last = rounds[-1]
    print(f"adaptive: {len(rounds)} round(s), {last['n_sources']} sources, max sd of C·S "
          f"{last['max_sd']:.4f}; {last.get('stop', '')}")
    _report(out, regions=cfg.output.regions)
    print(f"results in {out} (rounds in {out / C.ADAPTIVE_ROUNDS_NAME})")
    return 0


def _report(run_dir: Path, regions: bool = False) -> list[Path]:
    from .report import write_summary_files

    with _warnings_as_lines():
        return write_summary_files(run_dir, regions=regions)


def _cmd_report(args) -> int:
    paths = _report(Path(args.run_dir), regions=args.regions)
    if args.html:
        from .report import write_html_report
        paths.append(write_html_report(Path(args.run_dir)))
    for p in paths:
        print(p)
    return 0


#: Warnings for developers, which Python itself hides by default: an unclosed file
#: found by the garbage collector (possibly another library's) is not news for the user.
_DEVELOPER_WARNINGS = (ResourceWarning, DeprecationWarning, PendingDeprecationWarning,
                       ImportWarning)


@contextlib.contextmanager
def _warnings_as_lines():
    """Every user-facing warning raised inside, each once, as one line on stderr."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for category in _DEVELOPER_WARNINGS:
            warnings.simplefilter("ignore", category)
        try:
            yield
        finally:
            _print_warnings(caught)


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

    with _warnings_as_lines():
        path = run_fit(run_dir, **kwargs)
    summary = json.loads((Path(run_dir) / "fit" / "summary.json").read_text())
    print(format_summary(summary), end="")
    return path


def _cmd_fit(args) -> int:
    cosmology = None
    if args.cosmology:
        from .galaxy.population import get_cosmology
        cosmology = get_cosmology(args.cosmology)
    from .inference.sampling import SamplerSettings

    sampler = SamplerSettings(max_steps=args.max_steps, seed=args.seed, progress=not args.quiet)
    if args.covariates:                          # checked before the long pooled fit
        from .inference.covariates import parse_covariates
        parse_covariates(args.covariates)
    path = _fit(args.run_dir, model=args.model, per_field=args.per_field, sampler=sampler,
                cosmology=cosmology, area_arcmin2=args.area_arcmin2, depth=args.depth)
    if args.covariates:
        from .pipeline.covariate_fit import add_covariates
        with _warnings_as_lines():
            got = add_covariates(args.run_dir, args.covariates, n_bins=args.covariate_bins,
                                 sampler=sampler)
        for field, covs in got.items():
            for name, c in covs.items():
                print(f"covariate {name} ({field}): {len(c['nodes'])} bins over {c['x']} "
                      f"{c['covered'][0]:.3g}..{c['covered'][1]:.3g}; PPC adequate per bin: "
                      f"{c['adequate']}")
    print(f"wrote {path}")
    return 0


def _cmd_next(args) -> int:
    from .config import load_config
    from .inference import SelectionFunction
    from .pipeline.adaptive import cells_yaml, proposal_cells
    from .pipeline.fitdir import hold_run
    from .rundir import atomic_write_text, read_manifest

    run_dir = Path(args.run_dir)
    if args.write is not None and (Path(args.write).is_dir()
                                   or not Path(args.write).resolve().parent.is_dir()):
        raise FileNotFoundError(f"--write {args.write}: expected a file path in an existing "
                                "directory")
    # Under the run's lock: the fit and the configuration read together, never mid-write.
    with hold_run(run_dir, "next"):
        sf = SelectionFunction.read(run_dir / C.SELECTION_FUNCTION_NAME, field=args.field)
        cfg_path = run_dir / C.RUN_CONFIG_NAME
        if not cfg_path.is_file():
            raise FileNotFoundError(f"{cfg_path}: the run's stored configuration is missing "
                                    "(needed for its simulated cells)")
        cfg = load_config(cfg_path)
        manifest = read_manifest(run_dir) or {}
    cells, stats = proposal_cells(sf, cfg, args.n, add_iterations=args.iterations,
                                  z_limit=manifest.get("detection_z_limit"))
    print(f"# largest posterior sd of C*S: {stats['max_sd']:.4f} at z = {stats['at'][0]:g}, "
          f"m = {stats['at'][1]:g}")
    print("# z mag width_68 median_CS n_iterations")
    for row, cell in zip(stats["ranked"], cells):
        print(f"{row['z']:.3f} {row['mag']:.3f} {row['width']:.4f} {row['median']:.4f} "
              f"{cell['n_iterations']}")
    if args.write is not None:
        atomic_write_text(Path(args.write), cells_yaml(
            cells, f"glaciar next {run_dir} -n {args.n}: simulate them with\n"
                   f"  glaciar simulate {cfg_path} --out {run_dir} --cells {args.write}\n"
                   "n_iterations is each cell's new total (iterations per field)."))
        print(f"wrote {args.write}")
    return 0


def _cmd_demo(args) -> int:
    from .demo import build_demo_survey
    from .execute import simulate
    from .workers import default_workers, process_cpu_seconds

    out = _check_out_dir(Path(args.out))
    t0 = time.perf_counter()
    cfg_path = build_demo_survey(out / "survey", seed=args.seed)
    if args.lensed:
        from .demo.lensed import write_lensed_demo_config

        cfg_path = write_lensed_demo_config(cfg_path)
    print(f"demo survey written: {cfg_path} ({time.perf_counter() - t0:.1f} s)")
    cfg = _load(cfg_path)
    run_dir = out / "run"
    workers = args.workers if args.workers is not None else default_workers()
    stats = simulate(cfg, run_dir, workers=workers, progress=not args.quiet)
    print(f"simulated {stats['n_sources']} sources in {stats['wall_seconds']:.1f} s")
    for p in _report(run_dir, regions=False):
        print(p)
    if not args.no_fit:
        from .inference.sampling import SamplerSettings

        path = _fit(run_dir, sampler=SamplerSettings(progress=not args.quiet))
        print(f"selection function: {path}")
    print(f"demo finished in {time.perf_counter() - t0:.1f} s; results in {run_dir}")
    return 0


def _cmd_catalog(args) -> int:
    from .pipeline.catalog import default_out, run_catalog

    out = args.out if args.out is not None else default_out(args.source)
    table = run_catalog(args.source, out, regions=args.regions, progress=not args.quiet)
    n_sel = int(table[C.COL_SELECTED].sum()) if len(table) else 0
    print(f"{len(table)} detections, {n_sel} selected; wrote {out}")
    if args.regions:
        print(f"wrote {Path(out).with_suffix('.reg')}")
    return 0


def _cmd_export(args) -> int:
    from .pipeline.export import export

    for p in export(args.source, args.out, fmt=args.format, field=args.field):
        print(f"wrote {p}")
    return 0


def _cmd_lf(args) -> int:
    import json

    from .lf import parse_fix
    from .pipeline.lf import run_lf

    fix = parse_fix(args.fix or [], args.model)
    out = run_lf(args.run_dir, args.catalog, model=args.model, fix=fix, muv_range=args.muv_range,
                 z_range=args.z_range, seed=args.seed, progress=not args.quiet)
    summary = json.loads((Path(out) / "summary.json").read_text())
    print(f"{summary['model']}: {summary['n_candidates']} candidates")
    for name, p in summary["parameters"].items():
        print(f"  {name:>14s} = {p['median']:.3f}  [{p['lo68']:.3f}, {p['hi68']:.3f}] (68 %)")
    if summary.get("interlopers", {}).get("added"):
        print(f"  interlopers added: {summary['interlopers']['expected_total']:.2f} expected "
              "among the candidates (counts.ecsv: n_interlopers)")
    print(f"wrote {out}")
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


def _positive_int_number(text):
    """argparse type: a whole number >= 1, also written as 1e5."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v >= 1 and v == int(v)):
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return int(v)
_non_negative_int = _int_at_least(0)


class _HelpFormatter(argparse.HelpFormatter):
    """Help text with each option's default appended, ``(default: X)``.

    Only a default worth showing is appended: not for flags (``store_true``), not for a
    default of None (whose help text says in words what happens without the option), and not
    when the help already names its default.
    """

    def _get_help_string(self, action):
        text = action.help or ""
        if ("%(default)" in text or "default" in text.lower() or action.default is None
                or action.default is argparse.SUPPRESS or action.nargs == 0):
            return text
        return f"{text} (default: %(default)s)"


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line: ``glaciar: error: --workers: ...`` (exit 2).

    Its sub-parsers are of the same class, so every one shows defaults (``_HelpFormatter``).
    """

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message):
        if message.startswith("argument "):
            message = message[len("argument "):]
        message = " ".join(message.split())
        self.exit(2, f"glaciar: error: {message}\n")


# Help strings shared by several sub-commands (one wording each).
_HELP_QUIET = "no progress bar or per-step progress lines"
_HELP_WORKERS = "worker processes, >= 1 (default: all CPUs)"


def build_parser() -> argparse.ArgumentParser:
    """The ``glaciar`` argument parser: one sub-parser per command, help on every option."""
    p = _Parser(prog="glaciar", description=__doc__.splitlines()[0],
                epilog="Run `glaciar COMMAND --help` for a command's options; README.md and docs/ "
                       "for the whole guide.")
    p.add_argument("--version", action="version", version=f"glaciar {__version__}",
                   help="print glaciar's version and exit")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND",
                           help="one of the commands below")

    s = sub.add_parser("demo", help="build the embedded demo survey and run simulate → report → fit")
    s.add_argument("--out", default="glaciar-demo",
                   help="output directory: the survey goes to OUT/survey, the run to OUT/run")
    s.add_argument("--workers", type=_positive_int, default=None, help=_HELP_WORKERS)
    s.add_argument("--seed", type=_non_negative_int, default=2018,
                   help="seed of the synthetic survey's images, also written as the demo "
                        "configuration's simulation.seed (an integer >= 0)")
    s.add_argument("--no-fit", action="store_true",
                   help="stop after simulate and report (no selection function)")
    s.add_argument("--lensed", action="store_true",
                   help="the survey behind an analytic cluster lens (SIS + external shear; "
                        "configs/demo_lensed.yaml, docs/lensing.md)")
    s.add_argument("--quiet", action="store_true", help=_HELP_QUIET)
    s.set_defaults(func=_cmd_demo)

    s = sub.add_parser("init", help="write a commented configuration template")
    s.add_argument("path", nargs="?", default="glaciar.yaml",
                   help="where to write the template (YAML)")
    s.add_argument("--force", action="store_true", help="overwrite PATH if it exists")
    s.set_defaults(func=_cmd_init)

    s = sub.add_parser("simulate", help="run (or resume) the injection-recovery simulation")
    s.add_argument("config", help="configuration file (YAML, or GLACiAR's parameters.yaml), or a "
                                  "run's stored RUN/config.yaml")
    s.add_argument("--out", default=None, help="run directory (default: glaciar-run beside the config)")
    s.add_argument("--workers", type=_positive_int, default=None, help=_HELP_WORKERS)
    s.add_argument("--seed", type=_non_negative_int, default=None,
                   help="override simulation.seed (an integer >= 0; default: the configuration's)")
    s.add_argument("--scheduler", default=None,
                   help="Dask scheduler address, e.g. tcp://host:8786 (default: local worker "
                        "processes; needs pip install glaciar[dask])")
    s.add_argument("--mode", choices=["windowed", "full"], default="windowed",
                   help="windowed: detect each injected source in a window grown until it equals "
                        "the full-frame answer; full: extract the whole frame per task (for "
                        "validation, slower)")
    s.add_argument("--shard", type=_shard_option, default=None, metavar="K/N",
                   help="run only shard K of N of the tasks (1 <= K <= N; balanced by expected "
                        "cost), beside the other shards' processes into the same --out, e.g. "
                        "--shard ${SLURM_ARRAY_TASK_ID}/N in a SLURM array (docs/scale-out.md; "
                        "default: every task)")
    s.add_argument("--cells", default=None, metavar="CELLS_YAML",
                   help="add the cells of this file (as written by `glaciar next --write`; "
                        "default: none)")
    s.add_argument("--adaptive", action="store_true",
                   help="after the design, rounds of fit -> propose -> simulate until "
                        "--target-sd or --budget (glaciar.pipeline.adaptive). A design "
                        "costing more than --budget starts coarse: every k-th z and mag "
                        "value (first and last kept), k the smallest stride costing <= half "
                        "the budget (fewer iterations if even the corners cost more), "
                        "without grid.cells/box; the rounds fill in the rest")
    s.add_argument("--target-sd", type=_finite_positive, default=0.02,
                   help="with --adaptive: stop when the largest posterior sd of C*S over the "
                        "candidate cells is below this")
    s.add_argument("--budget", type=_positive_int_number, default=None,
                   help="with --adaptive: stop at this many injected sources, exceeded by less "
                        "than one task per field (default: 3x the design)")
    s.add_argument("--round-size", type=_positive_int_number, default=None,
                   help="with --adaptive: sources added per round (default: a tenth of the "
                        "design, at least one task per field)")
    s.add_argument("--max-steps", type=_positive_int, default=None,
                   help="with --adaptive: cap on each round's sampler steps (default: 20000, as "
                        "glaciar fit)")
    s.add_argument("--quiet", action="store_true", help=_HELP_QUIET)
    s.set_defaults(func=_cmd_simulate)

    s = sub.add_parser("status", help="tasks done, running and missing of a run, per shard")
    s.add_argument("run_dir", metavar="RUN", help="a run directory written by `glaciar simulate`")
    s.set_defaults(func=_cmd_status)

    s = sub.add_parser("report", help="summary tables (ECSV) and plots of a run")
    s.add_argument("run_dir", help="a run directory written by `glaciar simulate`")
    s.add_argument("--regions", action="store_true", help="also write DS9 region files")
    s.add_argument("--html", action="store_true",
                   help="also write RUN_DIR/report.html, one self-contained page (glaciar.report)")
    s.set_defaults(func=_cmd_report)

    s = sub.add_parser("fit", help="fit C(m, z) and S(z, m) with emcee; write selection_function.fits")
    s.add_argument("run_dir", help="a run directory written by `glaciar simulate`")
    s.add_argument("--model", default="auto", choices=["auto", "logistic", "erf", "fleming", "sas"],
                   help="completeness step (auto: chosen by PSIS-LOO; sas: flexible monotone)")
    s.add_argument("--max-steps", type=_positive_int, default=None,
                   help="cap on each chain's steps in this call; chains stop earlier once converged, "
                        "and a re-run extends unconverged ones (default: 20000)")
    s.add_argument("--depth", default="auto", choices=["auto", "on", "off"],
                   help="depth-aware completeness C(m - local depth, z) (auto: when depth varies)")
    s.add_argument("--per-field", action="store_true",
                   help="fit every field separately instead of pooled (one fit per field in "
                        "selection_function.fits; read one with field=)")
    s.add_argument("--seed", type=_non_negative_int, default=0,
                   help="seed of the sampler's start and draws (an integer >= 0)")
    s.add_argument("--area-arcmin2", type=_finite_positive, default=None,
                   help="survey area for V_eff (default: the footprint area in the run manifest)")
    s.add_argument("--cosmology", default=None,
                   help="astropy realisation for V_eff, e.g. WMAP9 (default: Planck18)")
    s.add_argument("--covariates", default=None, metavar="NAMES",
                   help="also fit C per size bin and S per UV-slope bin: r_eff, beta or r_eff,beta "
                        "(sf.completeness(m, z, r_eff_arcsec=), docs/selection-function-file.md; default: none)")
    s.add_argument("--covariate-bins", type=_positive_int, default=None,
                   help="quantile bins per covariate (default: 4)")
    s.add_argument("--quiet", action="store_true", help=_HELP_QUIET)
    s.set_defaults(func=_cmd_fit)

    s = sub.add_parser("export", help="write the selection function in another code's layout "
                                      "(jollof: DET_COMP and SEL_COMP FITS images)")
    s.add_argument("source", help="a fitted run directory or a selection_function.fits")
    s.add_argument("--format", default="jollof", choices=["jollof"],
                   help="jollof: detection_completeness.fits and selection_completeness.fits")
    s.add_argument("--out", required=True, help="directory to write into (required; no default)")
    s.add_argument("--field", default=None,
                   help="which fit of a per-field file (default: the file's only fit)")
    s.set_defaults(func=_cmd_export)

    s = sub.add_parser("next", help="(z, m) cells where the fitted selection is least certain")
    s.add_argument("run_dir", help="a run directory fitted by `glaciar fit`")
    s.add_argument("-n", type=_positive_int, default=5, help="number of cells (>= 1)")
    s.add_argument("--field", default=None,
                   help="which field's fit, for per-field files (default: the survey's)")
    s.add_argument("--iterations", type=_positive_int, default=1,
                   help="iterations (n_galaxies sources per field each) to add per cell")
    s.add_argument("--write", default=None, metavar="CELLS_YAML",
                   help="write the proposal as a cells file for `glaciar simulate --cells` "
                        "(default: print only)")
    s.set_defaults(func=_cmd_next)

    s = sub.add_parser("catalog", help="detect, measure and select on the survey's own images "
                                       "with the run's settings (the candidates an LF counts)")
    s.add_argument("source", metavar="CONFIG_OR_RUN",
                   help="a configuration file, or a run directory (its settings and field caches)")
    s.add_argument("--out", default=None,
                   help="output file: .parquet (default), .ecsv or .fits (default: RUN/catalog.parquet, "
                        "or <config stem>_catalog.parquet beside the configuration)")
    s.add_argument("--regions", action="store_true",
                   help="also write a DS9 region file of the selected candidates (<out stem>.reg)")
    s.add_argument("--quiet", action="store_true", help=_HELP_QUIET)
    s.set_defaults(func=_cmd_catalog)

    s = sub.add_parser("lf", help="the UV luminosity function of a run's candidates: Poisson "
                                  "forward model through P = C*S and the transfer function")
    s.add_argument("run_dir", metavar="RUN", help="a run directory fitted by `glaciar fit`")
    s.add_argument("--catalog", default=None, metavar="CAT",
                   help="candidates from `glaciar catalog RUN` (default RUN/catalog.parquet)")
    s.add_argument("--model", default="schechter", choices=["schechter", "dpl", "double_power_law",
                                                          "stepwise"],
                   help="LF shape: Schechter, double power law (dpl), or binned stepwise phi")
    s.add_argument("--fix", action="append", metavar="NAME=VALUE",
                   help="hold a parameter fixed (repeatable), e.g. --fix M_star=-20.5 "
                        "(default: all free)")
    s.add_argument("--muv-range", type=float, nargs=2, metavar=("LO", "HI"), default=None,
                   help="M_UV range of the LF [AB mag] (default: the M_UV range the candidates' "
                        "observed-magnitude window reaches over the z range)")
    s.add_argument("--z-range", type=float, nargs=2, metavar=("LO", "HI"), default=None,
                   help="redshift range, inside the simulated one (default: the simulated range)")
    s.add_argument("--seed", type=_non_negative_int, default=0,
                   help="seed of the LF sampler (an integer >= 0)")
    s.add_argument("--quiet", action="store_true", help=_HELP_QUIET)
    s.set_defaults(func=_cmd_lf)
    return p


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings as one line each (``warning: ...``), without the source line."""
    if issubclass(category, _DEVELOPER_WARNINGS):
        return
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
