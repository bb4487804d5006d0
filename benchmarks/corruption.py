"""How often random garbage inside a task file's data pages goes unnoticed, before and after
page checksums (issue 21, bullet 7).

Builds a tiny demo run (one field, 200x200 px, 2 tasks of 40 sources; ~10 s), takes one
of its task files and, after compaction, its compacted part, and writes each twice: as
glaciar writes it now (Parquet page checksums, footer digests) and as it did before
(``pq.write_table`` without checksums, the same rows and footer metadata).  Then, N times
(default 300, seeded), it overwrites 1-8 random bytes at a random position inside one
random column chunk's pages (dictionary and data pages, page headers included; the footer
is left alone) and asks

* the reader: ``pd.read_parquet`` before, :func:`glaciar.store._read_task_file` (footer
  check, page checksums verified) after -- did it raise, return the original values
  ("harmless": the garbage hit bytes nothing decodes, e.g. statistics in a page header),
  or return other values ("silent": wrong numbers);
* the resume check: does ``glaciar simulate`` count the task as done -- before, the
  footer-level check (:func:`glaciar.taskfile.task_file_problem`, magic bytes and task key);
  after, :func:`glaciar.taskfile.unit_problem` (every page read with its checksum).

Usage::

    python benchmarks/corruption.py [--trials 300] [--seed 0] [--keep DIR]

Measured (2-core shared machine, pyarrow 26.0.1, 300 trials each, seed 0).  "detected": the
reader raised (naming the file); "harmless": it returned the original values (the garbage
hit bytes nothing decodes, e.g. statistics in a page header); "silent": it returned other
values without an error; "resume misses": simulate would count the corrupt file as done:

================  ======  ========  ========  ======  =============
file              writer  detected  harmless  silent  resume misses
================  ======  ========  ========  ======  =============
task file         before       154        41     105            300
task file         after        269        31       0              0
compacted part    before       120        32     148            300
compacted part    after        268        32       0              0
================  ======  ========  ========  ======  =============

(The issue measured 107/300 silent on its own task file, before.)  After, no corruption
is read back as wrong values (page checksums: CRC-32 over each page's data), and
simulate's check catches all 300 (a digest of every byte before the footer, page
headers included), so every corrupt file is set aside and its task redone.  Readers do
not hash whole files: the 31 whose values are intact are read without a word.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq


def _tiny_run(root: Path) -> Path:
    from glaciar.config import load_config
    from glaciar.demo import build_demo_survey
    from glaciar.execute import simulate

    cfg_path = build_demo_survey(root / "survey", shape=(200, 200), seed=5, n_galaxies=40,
                                 n_iterations=2, z_values=(8.0,), mag_values=(25.0,))
    run = root / "run"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        simulate(load_config(cfg_path), run, workers=1, progress=False)
    return run


def _without_checksums(src: Path, dst: Path) -> None:
    """``src`` rewritten as glaciar wrote it before page checksums (same rows and footer)."""
    pq.write_table(pq.read_table(src), dst)


def _page_ranges(path: Path) -> list[tuple[int, int]]:
    """(start, length) of every column chunk's pages (dictionary page first, headers included)."""
    md = pq.read_metadata(path)
    out = []
    for g in range(md.num_row_groups):
        rg = md.row_group(g)
        for c in range(rg.num_columns):
            col = rg.column(c)
            start = col.dictionary_page_offset if col.has_dictionary_page else col.data_page_offset
            out.append((int(start), int(col.total_compressed_size)))
    return out


def _same(a: pd.DataFrame, b: pd.DataFrame) -> bool:
    try:
        pd.testing.assert_frame_equal(a, b, check_exact=True)
        return True
    except AssertionError:
        return False


def _trial_files(path: Path, trials: int, seed: int):
    """Yield (trial, corrupted bytes) for ``trials`` seeded in-page corruptions of ``path``."""
    data = path.read_bytes()
    ranges = _page_ranges(path)
    rng = np.random.default_rng(seed)
    for t in range(trials):
        start, length = ranges[int(rng.integers(len(ranges)))]
        n = int(rng.integers(1, 9))
        at = start + int(rng.integers(max(1, length - n + 1)))
        junk = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        if junk == data[at:at + n]:                      # make sure something changes
            junk = bytes(b ^ 0xFF for b in junk)
        yield t, data[:at] + junk + data[at + n:]


def measure(path: Path, key: str | None, after: bool, trials: int, seed: int, scratch: Path) -> dict:
    """Counts of detected / harmless / silent corruptions and resume misses for one file."""
    from glaciar import store, taskfile

    ref = pd.read_parquet(path)
    counts = {"detected": 0, "harmless": 0, "silent": 0, "resume_misses": 0}
    f = scratch / path.name
    for _, blob in _trial_files(path, trials, seed):
        f.write_bytes(blob)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                got = store._read_task_file(f, None) if after else pd.read_parquet(f)
        except Exception:  # noqa: BLE001 - any error is a detection
            counts["detected"] += 1
        else:
            counts["harmless" if _same(got, ref) else "silent"] += 1
        if after:
            missed = taskfile.unit_problem(f) is None
        elif key is not None:
            missed = taskfile.task_file_problem(f, key) is None
        else:                                          # a part: its footer parses
            missed = taskfile.footer_metadata(f)[0] is not None
        counts["resume_misses"] += bool(missed)
    return counts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", default=None, help="build the run here and keep it")
    args = ap.parse_args(argv)

    from glaciar import store

    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="glaciar-corruption-"))
    try:
        t0 = time.perf_counter()
        run = _tiny_run(root)
        task = sorted((run / "results").glob("task_*.parquet"))[0]
        key = pq.read_metadata(task).metadata[b"glaciar.task"].decode("utf-8")
        work = root / "files"
        work.mkdir(exist_ok=True)
        files = {("task file", "after"): work / "task_after.parquet",
                 ("task file", "before"): work / "task_before.parquet"}
        shutil.copyfile(task, files[("task file", "after")])
        _without_checksums(task, files[("task file", "before")])
        store.compact(run)
        part = sorted((run / "results" / "compact").rglob("part-*.parquet"))[0]
        files[("compacted part", "after")] = work / "part_after.parquet"
        files[("compacted part", "before")] = work / "part_before.parquet"
        shutil.copyfile(part, files[("compacted part", "after")])
        _without_checksums(part, files[("compacted part", "before")])
        scratch = root / "scratch"
        scratch.mkdir(exist_ok=True)
        print(f"tiny run built in {time.perf_counter() - t0:.1f} s; {args.trials} in-page "
              f"corruptions per file (seed {args.seed})")
        print(f"{'file':<16}{'writer':<8}{'detected':>10}{'harmless':>10}{'silent':>8}"
              f"{'resume misses':>15}")
        for (what, writer) in (("task file", "before"), ("task file", "after"),
                               ("compacted part", "before"), ("compacted part", "after")):
            c = measure(files[(what, writer)], key if what == "task file" else None,
                        writer == "after", args.trials, args.seed, scratch)
            print(f"{what:<16}{writer:<8}{c['detected']:>10}{c['harmless']:>10}{c['silent']:>8}"
                  f"{c['resume_misses']:>15}")
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
