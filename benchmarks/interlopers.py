"""Interlopers (issue 23): their cost per source, and the BoRG J-dropout contamination figures.

Two tables, on the embedded 4-band demo field (the BoRG bands F160W, F098M, F125W,
F606W; built in a temporary directory and measured once):

``cost``
    The same number of sources per task, run with :func:`glaciar.engine.task.run_task`
    on one field context: high-z tasks (z = 9, 10; the demo's power-law sources) and
    interloper tasks (z = 1.5, 3, 4.5; ``configs/borg_jdropout.yaml``'s section), at the
    same detection-band magnitudes (25, 26, 27), in z blocks as a run orders them (the
    template cache cleared between blocks), the populations' blocks alternating; CPU per
    injected source (``time.process_time``).  Acceptance (issue 23): within 20 %.
``borg``
    ``configs/borg_jdropout.yaml``'s ``interlopers:`` section, selection, detection and
    classification settings on the demo images (its own BoRG images are not shipped),
    simulated with :func:`glaciar.execute.simulate` (its one high-z cell as a token),
    then the passing fraction per measured F160W magnitude
    (:func:`glaciar.pipeline.contamination.run_contamination`), with each family's own
    passing fraction and the expected interlopers per arcmin^2.

Usage::

    python benchmarks/interlopers.py [--table cost|borg|both] [--size 600] [--n 60]
        [--rounds 2] [--iterations 3] [--scatter DEX] [--size-bins K] [--borg-n 100]
        [--workers 2]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from glaciar.config import load_config
from glaciar.demo import build_demo_survey
from glaciar.engine.interlopers import InterloperModel, count_weights
from glaciar.engine.task import TaskSpec, run_task
from glaciar.fieldprep import build_field_context
from glaciar.galaxy.population import SourceModel
from glaciar.survey import Survey

ROOT = Path(__file__).resolve().parents[1]
BORG = ROOT / "configs" / "borg_jdropout.yaml"


def _demo(tmp: Path, size: int, n: int) -> Path:
    return build_demo_survey(tmp, shape=(size, size), seed=5, n_galaxies=n, n_iterations=1,
                             z_values=(9.0,), mag_values=(26.0,))


def cost_table(size: int, n: int, rounds: int, iterations: int, scatter=None, size_bins=None) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_config(_demo(Path(tmp), size, n))
        survey = Survey.from_config(cfg)
        field = cfg.survey.fields[0]
        ctx = build_field_context(cfg, survey, field)
        borg = yaml.safe_load(BORG.read_text())["interlopers"]
        sizes = {k: v for k, v in (("r_eff_scatter_dex", scatter), ("size_bins", size_bins))
                 if v is not None}
        model = InterloperModel.from_config({**borg, "n_per_task": n, **sizes},
                                            SourceModel(**cfg.source.model_dump()))
        hz, il = "high-z (z 9, 10)", "interlopers (z 1.5, 3, 4.5)"
        # As a run orders its tasks: one z after the other, its magnitudes and iterations
        # inside (templates stay cached within a z); the two populations' z blocks
        # alternate so that a shared machine's load falls on both alike.
        blocks = [(hz, "", 9.0), (il, "interloper-bench", 1.5), (hz, "", 10.0),
                  (il, "interloper-bench", 3.0), (il, "interloper-bench", 4.5)]
        cpu = {hz: 0.0, il: 0.0}
        n_src = {hz: 0, il: 0}
        it0 = 0
        for r in range(rounds + 1):
            for kind, pop, z in blocks:
                for it in range(it0, it0 + iterations):
                    for mag in (25.0, 26.0, 27.0):
                        spec = TaskSpec(field, 0, 0, 0, it, z, mag, population=pop)
                        t0 = time.process_time()
                        table = run_task(ctx, spec, seed=1, interlopers=model)
                        dt = time.process_time() - t0
                        if r == 0:       # warm-up round: band tables, imports (not templates)
                            continue
                        cpu[kind] += dt
                        n_src[kind] += len(table)
                ctx.cache.clear()        # the next z block starts cold, as in a run
            it0 += iterations
    base = cpu[hz] / n_src[hz] * 1e3
    print(f"cost: demo field {size}^2 px, {rounds} round(s) of z blocks of {iterations} "
          f"iteration(s) x 3 magnitudes (25, 26, 27), {n} sources per task, template cache "
          f"cleared per z block; interloper sizes: scatter {model.size_scatter_dex:g} dex on "
          f"{model.size_bins} node(s); CPU per injected source")
    print(f"{'population':<30}{'sources':>9}{'CPU [ms/source]':>17}{'vs high-z':>11}")
    for kind in (hz, il):
        ms = cpu[kind] / n_src[kind] * 1e3
        print(f"{kind:<30}{n_src[kind]:>9d}{ms:>17.3f}{ms / base - 1:>+11.1%}")


def borg_table(size: int, n: int, workers: int) -> None:
    from glaciar.execute import simulate
    from glaciar.pipeline.contamination import interloper_rows, run_contamination

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        demo = yaml.safe_load(_demo(tmp, size, 3).read_text())
        borg = yaml.safe_load(BORG.read_text())
        d = dict(demo)
        for key in ("detection", "classification", "selection"):
            d[key] = borg[key]
        d["interlopers"] = {**borg["interlopers"], "n_per_task": n}
        d["grid"] = {"z": {"values": [10.0]}, "mag": {"values": [26.0]},
                     "magnitude_type": "apparent"}
        d["simulation"] = {"n_galaxies": 3, "n_iterations": 1, "seed": 20180523}
        path = tmp / "borg_on_demo.yaml"
        path.write_text(yaml.safe_dump(d, sort_keys=False))
        cfg = load_config(path)
        t0 = time.perf_counter()
        st = simulate(cfg, tmp / "run", workers=workers, progress=False)
        wall = time.perf_counter() - t0
        c = run_contamination(tmp / "run", cfg, cfg.survey.detection_band)
        rows = interloper_rows(tmp / "run", cfg)
        model = InterloperModel.from_config(cfg.interlopers, SourceModel(**cfg.source.model_dump()))
        w = count_weights(rows["mag_input"], rows["mag"], model)
        fam = rows["interloper_family"].to_numpy().astype(str)
        m_in = rows["mag_input"].to_numpy()
        m_obs = rows[f"mag_auto_{cfg.survey.detection_band}"].to_numpy()
        sel = rows["selected"].to_numpy() & np.isfinite(m_obs)
        E = c.m_edges
        dens = c.surface_density(E)
        print(f"borg: configs/borg_jdropout.yaml's interlopers, selection, detection on the demo "
              f"images ({size}^2 px); {len(rows)} interlopers at z = "
              f"{model.z_nodes[0]:g}-{model.z_nodes[-1]:g}, {st['n_sources']} sources in "
              f"{wall:.0f} s wall ({workers} workers)")
        print(f"{'m_obs F160W':<13}{'injected':>9}{'selected':>9}{'f (median)':>12}"
              f"{'68 % interval':>18}{'dusty':>9}{'balmer':>9}{'N/arcmin2':>11}")
        for k in range(len(E) - 1):
            per = []
            for f in ("dusty", "balmer"):
                inb = (fam == f) & (m_in >= E[k]) & (m_in < E[k + 1])
                ok = (fam == f) & sel & (m_obs >= E[k]) & (m_obs < E[k + 1])
                per.append(w[ok].sum() / w[inb].sum() if w[inb].sum() > 0 else np.nan)
            print(f"{E[k]:5.2f}-{E[k + 1]:5.2f}  {c.n_injected[k]:>9d}{c.n_selected[k]:>9d}"
                  f"{c.fraction[k]:>12.4f}   [{c.lower[k]:.4f}, {c.upper[k]:.4f}]"
                  f"{per[0]:>9.4f}{per[1]:>9.4f}{dens[k]:>11.4f}")
        zs = rows["z"].to_numpy()
        print("passing fraction by family and z (all magnitudes, weighted to the counts); "
              "median A_V or D4000 of the passing ones")
        print(f"{'family':<8}" + "".join(f"{z:>7g}" for z in model.z_nodes))
        for f, col in (("dusty", "a_v"), ("balmer", "d4000")):
            vals, par = [], []
            for z in model.z_nodes:
                mine = (fam == f) & np.isclose(zs, z)
                vals.append(w[mine & sel].sum() / w[mine].sum() if w[mine].sum() > 0 else np.nan)
                p = rows[col].to_numpy()[mine & sel]
                par.append(np.median(p) if p.size else np.nan)
            print(f"{f:<8}" + "".join(f"{v:>7.3f}" for v in vals))
            print(f"{'  ' + col:<8}" + "".join(f"{v:>7.2f}" for v in par))
        print(f"expected interlopers among J-dropouts, {E[0]:g}-{E[-1]:g} mag: "
              f"{dens.sum():.3f} per arcmin^2 (counts log10 dN/dm = {model.counts[0]:g} + "
              f"{model.counts[1]:g} (m - {model.counts[2]:g}))")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--table", choices=("cost", "borg", "both"), default="both")
    ap.add_argument("--size", type=int, default=600, help="field side [pixels]")
    ap.add_argument("--n", type=int, default=60, help="sources per task (cost table)")
    ap.add_argument("--rounds", type=int, default=2, help="timed rounds (cost table)")
    ap.add_argument("--iterations", type=int, default=3,
                    help="iterations per (z, magnitude) in a z block (cost table)")
    ap.add_argument("--scatter", type=float, help="interlopers' r_eff_scatter_dex (cost table)")
    ap.add_argument("--size-bins", type=int, help="interlopers' size_bins (cost table)")
    ap.add_argument("--borg-n", type=int, default=100, help="interlopers per task (borg table)")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    if args.table in ("cost", "both"):
        cost_table(args.size, args.n, args.rounds, args.iterations, args.scatter, args.size_bins)
    if args.table in ("borg", "both"):
        borg_table(args.size, args.borg_n, args.workers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
