"""CPU cost of the injected sources' shot noise (issue 23, point 4).

Builds the embedded 4-band demo field in a temporary directory (gains = exposure
times, so ``source.shot_noise`` is on by default), runs ``--warmup`` untimed tasks,
then times ``--tasks`` tasks of ``--n`` sources at each magnitude through
:func:`glaciar.engine.task.run_task`, alternating shot noise on and off (the same
tasks, so the same sources, each task run once untimed first so that both find every
template cached; alternating spreads a shared machine's load over both),
and prints CPU milliseconds per injected source (``time.process_time``): the whole
task with and without noise, their ratio, the time spent drawing the noise
(:func:`glaciar.engine.shotnoise.add_shot_noise`) and the stamp pixels noised per source.

Usage::

    python benchmarks/shot_noise.py [--size 1000] [--tasks 10] [--n 50] [--z 8] [--mag 26] [--warmup 2]
"""
from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time

import glaciar.engine.task as task_module
from glaciar.config import load_config
from glaciar.demo import build_demo_survey
from glaciar.fieldprep import build_field_context
from glaciar.plan import plan_tasks
from glaciar.survey import Survey


def measure(opt, mag, tmp):
    path = build_demo_survey(tmp, shape=(opt.size, opt.size), seed=opt.seed, n_galaxies=opt.n,
                             n_iterations=opt.tasks + opt.warmup, z_values=(opt.z,), mag_values=(mag,))
    cfg = load_config(path)
    on = build_field_context(cfg, Survey.from_config(cfg), cfg.survey.fields[0])
    off = dataclasses.replace(on, source_model=dataclasses.replace(on.source_model, shot_noise=False))
    specs = plan_tasks(cfg)
    seed = cfg.simulation.seed
    real = task_module.add_shot_noise
    r = dict(on=0.0, off=0.0, noise=0.0, pixels=0, n=0)

    def timed(stamps, *args, **kwargs):
        t = time.process_time()
        out = real(stamps, *args, **kwargs)
        r["noise"] += time.process_time() - t
        r["pixels"] += sum(s[2].size for s in stamps)
        return out

    for spec in specs[:opt.warmup + opt.tasks]:
        # Untimed: fills the template cache (shared by both contexts) with every stamp of
        # the timed tasks, and the shot-noise core/wings cache: the timed runs compare the
        # steady state of a long run, where each template has been used before.
        task_module.run_task(on, spec, seed)
    for k, spec in enumerate(specs[opt.warmup:opt.warmup + opt.tasks]):
        order = (("on", on), ("off", off)) if k % 2 else (("off", off), ("on", on))
        for key, ctx in order:
            task_module.add_shot_noise = timed if key == "on" else real
            try:
                t = time.process_time()
                table = task_module.run_task(ctx, spec, seed)
                r[key] += time.process_time() - t
            finally:
                task_module.add_shot_noise = real
        r["n"] += len(table)
    r["gains"] = {b: g for b, g in on.gains.items()}
    return r


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1000, help="image side [pixels] (default 1000, the demo's)")
    ap.add_argument("--tasks", type=int, default=10, help="timed tasks per magnitude (default 10)")
    ap.add_argument("--n", type=int, default=50, help="sources per task (default 50, the demo's)")
    ap.add_argument("--z", type=float, default=8.0, help="redshift (default 8)")
    ap.add_argument("--mag", type=float, nargs="+", default=[26.0], help="F160W magnitudes (default 26)")
    ap.add_argument("--seed", type=int, default=3, help="seed of the demo images (default 3)")
    ap.add_argument("--warmup", type=int, default=2, help="untimed tasks first (default 2)")
    opt = ap.parse_args(argv)
    rows = []
    for mag in opt.mag:
        with tempfile.TemporaryDirectory(prefix="glaciar-shot-noise-") as tmp:
            rows.append((mag, measure(opt, mag, tmp)))
    gains = ", ".join(f"{b} {g:g}" for b, g in rows[0][1]["gains"].items())
    print(f"shot noise cost: {opt.size}x{opt.size} px demo field (gains {gains}), z = {opt.z:g}, "
          f"{opt.tasks} tasks x {opt.n} sources per magnitude; CPU ms per injected source")
    print()
    print("| m | without | with | ratio | noise draws | stamp pixels noised per source |")
    print("|---|---|---|---|---|---|")
    for mag, r in rows:
        ms = lambda t: 1e3 * t / r["n"]  # noqa: E731
        print(f"| {mag:g} | {ms(r['off']):.3f} | {ms(r['on']):.3f} | {r['on'] / r['off']:.3f} | "
              f"{ms(r['noise']):.3f} | {r['pixels'] / r['n']:.0f} |")


if __name__ == "__main__":
    main()
