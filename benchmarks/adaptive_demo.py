"""Adaptive vs uniform simulation on the demo survey (the image-based half of issue 8's benchmark).

A long uniform reference run fixes P_ref = C·S (posterior median of the
logistic surface) on the design's refined lattice.  For each seed, a uniform
design is simulated at 1, 2 and 4 iterations per cell, and an adaptive run
(coarse design = 1 iteration per cell, then `glaciar simulate --adaptive`
rounds) is stopped at the same budgets; after each, the fit's posterior
median of P is compared with P_ref (largest and RMS absolute difference)
and the largest posterior sd of P is reported.  CPU is whole-process
(parent + workers).

Usage::

    python benchmarks/adaptive_demo.py [--seeds 3] [--ref-iterations 8] [--workers 2]

Prints one table per design and the injection ratio: the sources the adaptive
design needs to reach the uniform design's final error, relative to the uniform
design's.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def _p_median(run_dir, zc, mc):
    from glaciar import constants as C
    from glaciar.inference import SelectionFunction

    sf = SelectionFunction.read(Path(run_dir) / C.SELECTION_FUNCTION_NAME)
    draws = sf.grid_draws(zc, mc)["P"]
    return np.nanmedian(draws, axis=0), float(np.nanmax(np.nanstd(draws, axis=0)))


def _config(base_cfg, n_iterations, seed):
    from glaciar.config import config_from_dict, config_to_dict

    d = config_to_dict(base_cfg)
    d["simulation"]["n_iterations"] = int(n_iterations)
    d["simulation"]["seed"] = int(seed)
    return config_from_dict(d, base_dir=base_cfg.base_dir)


def _fit(run_dir):
    from glaciar.inference.sampling import SamplerSettings
    from glaciar.pipeline import run_fit

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_fit(run_dir, model="logistic", sampler=SamplerSettings(seed=0), resume=False,
                plots=False)


def _n_sources(run_dir):
    from glaciar import constants as C
    from glaciar.pipeline.inputs import read_columns

    return len(read_columns(run_dir, [C.COL_Z]))


def main(argv=None):
    from glaciar.config import load_config
    from glaciar.demo import build_demo_survey
    from glaciar.inference import candidate_grid
    from glaciar.pipeline.adaptive import AdaptiveSettings, run_adaptive
    from glaciar.execute import simulate
    from glaciar.plan import detection_z_limit
    from glaciar.workers import process_cpu_seconds

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--ref-iterations", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--n-galaxies", type=int, default=50)
    ap.add_argument("--work", default=None, help="working directory (default: a temporary one)")
    args = ap.parse_args(argv)

    work = Path(args.work or tempfile.mkdtemp(prefix="glaciar-adaptive-"))
    cfg_path = build_demo_survey(work / "survey", n_galaxies=args.n_galaxies, n_iterations=1)
    base = load_config(cfg_path)
    zlim = detection_z_limit(base)
    zc, mc = candidate_grid(base.grid.z_values, base.grid.mag_values)
    zc = zc[zc < zlim] if zlim is not None else zc
    n_cells = len(base.grid.z_values) * len(base.grid.mag_values) * len(base.survey.fields)
    unit = n_cells * args.n_galaxies

    t0 = time.perf_counter()
    rows = []
    ref_dir = work / "reference"
    st = simulate(_config(base, args.ref_iterations, 10_000), ref_dir, workers=args.workers,
                  progress=False)
    _fit(ref_dir)
    p_ref, sd_ref = _p_median(ref_dir, zc, mc)
    print(f"# reference: {st['n_sources']} sources ({args.ref_iterations} iterations per cell), "
          f"largest posterior sd of P {sd_ref:.4f}; {time.perf_counter() - t0:.0f} s wall")

    def err(run_dir):
        p, sd = _p_median(run_dir, zc, mc)
        d = np.abs(p - p_ref)
        return float(np.nanmax(d)), float(np.sqrt(np.nanmean(d ** 2))), sd

    budgets = [unit, 2 * unit, 4 * unit]
    for seed in range(1, args.seeds + 1):
        # Uniform: 1, 2, 4 iterations per cell (each a resume of the previous store).
        c0 = process_cpu_seconds()
        u_dir = work / f"uniform_{seed}"
        for k in (1, 2, 4):
            simulate(_config(base, k, seed), u_dir, workers=args.workers, progress=False)
            _fit(u_dir)
            rows.append(("uniform", seed, _n_sources(u_dir), process_cpu_seconds() - c0,
                         *err(u_dir)))
        # Adaptive: the 1-iteration design, then rounds until each budget (each call
        # resumes the previous one's store and rounds log).
        c0 = process_cpu_seconds()
        a_dir = work / f"adaptive_{seed}"
        for budget in budgets[1:]:
            settings = AdaptiveSettings(target_sd=1e-9, budget=budget,
                                        round_size=max(unit // 4, args.n_galaxies))
            rounds = run_adaptive(_config(base, 1, seed), a_dir, settings, workers=args.workers,
                                  progress=False, echo=lambda *_: None)
            rows.append(("adaptive", seed, _n_sources(a_dir), process_cpu_seconds() - c0,
                         *err(a_dir)))
        (work / f"rounds_{seed}.json").write_text(json.dumps(rounds, indent=1))

    print(f"\n{'design':9s} {'seed':>4s} {'sources':>8s} {'CPU s':>8s} {'max|dP|':>8s} "
          f"{'rms|dP|':>8s} {'max sd':>7s}")
    for r in rows:
        print(f"{r[0]:9s} {r[1]:4d} {r[2]:8d} {r[3]:8.1f} {r[4]:8.4f} {r[5]:8.4f} {r[6]:7.4f}")
    # Injection ratio: sources the adaptive design needed to reach the uniform final error.
    # (Budgets are 1, 2 and 4 design units, so a ratio is resolved only to these steps.)
    print()
    for col, name in ((4, "max|dP|"), (6, "max sd")):
        for seed in range(1, args.seeds + 1):
            u = [r for r in rows if r[0] == "uniform" and r[1] == seed]
            a = [r for r in rows if r[0] == "adaptive" and r[1] == seed]
            target = u[-1][col]
            reached = [r for r in a if r[col] <= target]
            if reached:
                print(f"seed {seed}: uniform reaches {name} {target:.4f} with {u[-1][2]} sources; "
                      f"adaptive with {reached[0][2]} (ratio >= {u[-1][2] / reached[0][2]:.2f}x)")
            else:
                print(f"seed {seed}: uniform reaches {name} {target:.4f} with {u[-1][2]} sources; "
                      f"adaptive does not within {a[-1][2]} (its best "
                      f"{min(r[col] for r in a):.4f})")


if __name__ == "__main__":
    main()
