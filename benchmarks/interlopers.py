"""Interlopers (issue 23): their cost per source, and the BoRG J-dropout contamination figures.

Two tables, on the embedded 4-band demo field (the BoRG bands F160W, F098M, F125W,
F606W; built in a temporary directory and measured once):

``cost``
    The same number of sources per task, run with :func:`glaciar.engine.task.run_task`
    on one field context: high-z tasks (z = 9, 10; the demo's power-law sources) and
    interloper tasks (z = 1.5, 3, 4.5; ``configs/borg_jdropout.yaml``'s families), at
    the same detection-band magnitudes (25, 26, 27), interleaved task by task so that a
    shared machine's load falls on both alike; CPU per injected source
    (``time.process_time``).  Acceptance (issue 23): within 20 %.
``borg``
    ``configs/borg_jdropout.yaml``'s ``interlopers:`` section, selection, detection and
    classification settings on the demo images (its own BoRG images are not shipped),
    simulated with :func:`glaciar.execute.simulate` (its one high-z cell as a token),
    then the passing fraction per measured F160W magnitude
    (:func:`glaciar.pipeline.contamination.run_contamination`), with each family's own
    passing fraction and the expected interlopers per arcmin^2.

Usage::

    python benchmarks/interlopers.py [--table cost|borg|both] [--size 600] [--n 60]
        [--tasks 4] [--borg-n 100] [--workers 2]
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


def cost_table(size: int, n: int, tasks: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_config(_demo(Path(tmp), size, n))
        survey = Survey.from_config(cfg)
        field = cfg.survey.fields[0]
        ctx = build_field_context(cfg, survey, field)
        borg = yaml.safe_load(BORG.read_text())["interlopers"]
        model = InterloperModel.from_config({**borg, "n_per_task": n},
                                            SourceModel(**cfg.source.model_dump()))
        kinds = {"high-z (z 9, 10)": [("", z) for z in (9.0, 10.0)],
                 "interlopers (z 1.5, 3, 4.5)": [("interloper-bench", z) for z in (1.5, 3.0, 4.5)]}
        cpu = {k: 0.0 for k in kinds}
        n_src = {k: 0 for k in kinds}
        for i in range(tasks + 1):
            for mag in (25.0, 26.0, 27.0):
                order = list(kinds) if i % 2 else list(kinds)[::-1]
                for kind in order:
                    for pop, z in kinds[kind]:
                        spec = TaskSpec(field, 0, 0, 0, i, z, mag, population=pop)
                        t0 = time.process_time()
                        table = run_task(ctx, spec, seed=1, interlopers=model)
                        dt = time.process_time() - t0
                        if i == 0:           # warm-up: templates and band tables enter caches
                            continue
                        cpu[kind] += dt
                        n_src[kind] += len(table)
    base = cpu["high-z (z 9, 10)"] / n_src["high-z (z 9, 10)"] * 1e3
    print(f"cost: demo field {size}^2 px, {tasks} rounds x 3 magnitudes (25, 26, 27), "
          f"{n} sources per task, CPU per injected source")
    print(f"{'population':<30}{'sources':>9}{'CPU [ms/source]':>17}{'vs high-z':>11}")
    for kind in kinds:
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
        print(f"expected interlopers among J-dropouts, {E[0]:g}-{E[-1]:g} mag: "
              f"{dens.sum():.3f} per arcmin^2 (counts log10 dN/dm = {model.counts[0]:g} + "
              f"{model.counts[1]:g} (m - {model.counts[2]:g}))")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--table", choices=("cost", "borg", "both"), default="both")
    ap.add_argument("--size", type=int, default=600, help="field side [pixels]")
    ap.add_argument("--n", type=int, default=60, help="sources per task (cost table)")
    ap.add_argument("--tasks", type=int, default=4, help="timed rounds (cost table)")
    ap.add_argument("--borg-n", type=int, default=100, help="interlopers per task (borg table)")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    if args.table in ("cost", "both"):
        cost_table(args.size, args.n, args.tasks)
    if args.table in ("borg", "both"):
        borg_table(args.size, args.borg_n, args.workers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
