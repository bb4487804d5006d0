"""Size-aware completeness on real injections, and V_eff re-weighted to another size law.

Two runs of the demo survey, identical but for the injected size scatter: ``wide``
(source.r_eff_scatter_dex = 0.3) and ``narrow`` (0.1).  Both are fitted as
``glaciar fit`` does (logistic step); ``wide`` also with ``--covariates r_eff``
(:mod:`glaciar.inference.covariates`).  Printed:

* per size bin of ``wide``: its sources, mean log10 r_e, the bin's m50 and w, and its
  posterior-predictive check (extreme cells / cells) -- the acceptance check of
  issue 23 (C(m, r_e) against the binned fractions per size bin);
* V_eff(m) of ``wide`` as injected, ``wide`` re-weighted to the narrow law, and the
  ``narrow`` run itself with its 68 % interval, and whether the re-weighted median lies
  inside that interval.

Usage::

    python benchmarks/size_reweighting.py [--iterations 6] [--galaxies 40] [--workers 2]
"""
from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import yaml


def _run(root, name, scatter, args):
    from glaciar.config import load_config
    from glaciar.demo import build_demo_survey
    from glaciar.execute import simulate

    out = Path(root) / name
    cfg = build_demo_survey(out, shape=(320, 320), seed=11, n_galaxies=args.galaxies,
                            n_iterations=args.iterations, z_values=(9.8, 10.4),
                            mag_values=tuple(np.round(np.arange(24.5, 28.01, 0.5), 2)))
    d = yaml.safe_load(Path(cfg).read_text())
    d.setdefault("source", {})["r_eff_scatter_dex"] = scatter
    d["simulation"]["seed"] = args.seed + (0 if name == "wide" else 1)
    d["noise"] = {"correlated": "off"}
    (out / "cfg.yaml").write_text(yaml.safe_dump(d))
    simulate(load_config(out / "cfg.yaml"), out / "run", workers=args.workers, progress=False)
    return out / "run", d["source"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--iterations", type=int, default=6)
    p.add_argument("--galaxies", type=int, default=40)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--bins", type=int, default=4)
    p.add_argument("--max-steps", type=int, default=3000)
    p.add_argument("--seed", type=int, default=3)
    args = p.parse_args(argv)
    from glaciar.inference import SelectionFunction, SizeRelation
    from glaciar.inference.sampling import SamplerSettings
    from glaciar.pipeline import run_fit
    from glaciar.pipeline.covariate_fit import add_covariates

    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as root:
        wide, src = _run(root, "wide", 0.3, args)
        narrow, _ = _run(root, "narrow", 0.1, args)
        t_sim = time.perf_counter() - t0
        sampler = SamplerSettings(max_steps=args.max_steps)
        for r in (wide, narrow):
            run_fit(r, model="logistic", plots=False, sampler=sampler)
        t1 = time.perf_counter()
        add_covariates(wide, "r_eff", n_bins=args.bins, sampler=sampler)
        t_cov = time.perf_counter() - t1
        sw = SelectionFunction.read(wide / "selection_function.fits")
        sn = SelectionFunction.read(narrow / "selection_function.fits")
        nodes = sw.covariates["r_eff"]
        names = sw.model.param_names
        print(f"simulation {t_sim:.0f} s; covariate fit ({len(nodes.centres)} bins) {t_cov:.0f} s; "
              f"pooled m50_0 = {np.median(sw.draws[:, names.index('m50_0')]):.3f}")
        print(f"injected log10 r_e/arcsec: {nodes.covered[0]:.3f} .. {nodes.covered[1]:.3f}")
        print("bin  n_src  <log r_e>   m50_0 [16, 84]            w     PPC extreme/cells  adequate")
        for k, x in enumerate(nodes.centres):
            q = np.percentile(nodes.draws[k][:, names.index("m50_0")], [16, 50, 84])
            w = np.exp(np.median(nodes.draws[k][:, names.index("log_w_0")]))
            print(f"{k:3d}  {nodes.n_sources[k]:5d}  {x:+8.3f}  {q[1]:7.3f} [{q[0]:.3f}, {q[2]:.3f}]"
                  f"  {w:5.3f}  {nodes.n_extreme[k]:8d} / {nodes.n_cells[k]:<8d} {bool(nodes.adequate[k])}")
        law = SizeRelation(r_eff_kpc_z6=src.get("r_eff_kpc_z6", 1.075),
                           size_evolution=src.get("size_evolution", -1.0),
                           size_luminosity_slope=src.get("size_luminosity_slope", 0.0),
                           r_eff_scatter_dex=0.1)
        m = np.array([25.5, 26.0, 26.25, 26.5, 26.75, 27.0])
        a, b, c = (sw.effective_volume(m), sw.effective_volume(m, size_relation=law),
                   sn.effective_volume(m))
        print("   m   V_eff wide [Mpc3]   wide -> narrow law [68 %]   narrow run [68 %]      inside")
        for i, mi in enumerate(m):
            inside = c.lower[i] <= b.median[i] <= c.upper[i]
            print(f"{mi:5.2f}  {a.median[i].value:9.1f}         {b.median[i].value:7.1f} "
                  f"[{b.lower[i].value:.1f}, {b.upper[i].value:.1f}]     "
                  f"{c.median[i].value:7.1f} [{c.lower[i].value:.1f}, {c.upper[i].value:.1f}]"
                  f"   {inside}")
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
