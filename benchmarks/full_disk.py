"""``glaciar simulate`` on a full disk: tiny tmpfs file systems (issue 21, bullet 7).

Needs root (it mounts tmpfs file systems of a few hundred kB under a temporary
directory, and unmounts them); nothing else on the machine is touched.  Builds the
small demo survey (320x320 px, 8 tasks of 12 sources) on the normal disk and a
reference run there, then for each size and worker count: simulates into a fresh
tmpfs of that size, records the exit status and the stderr lines, grows the file
system to 20 MB (``mount -o remount``: space freed) and runs the same command
again, and checks that the resumed run's rows equal the reference run's.

Usage::

    sudo python benchmarks/full_disk.py [--sizes 3m 400k 250k 120k] [--workers 1 2]

Measured (2-core shared machine): before this change (glaciar at 02c6920) the runs on
3m, 400k and 150k file systems each died of SIGBUS ("Bus error", exit 135, no message; the field
cache is a sparse file written through a memory map) and left a half-written
``.context/*.tmp``.  Now::

    size   workers  exit  stderr                                                  resumed
    3m     1, 2     0     warning: RUN/.context/<key>: field cache not written    rows identical
                          (No space left on device); the field's arrays stay
                          in memory  -- the run completes
    400k   1, 2     2     that warning, then one error line: "glaciar simulate:  rows identical
    250k   1, 2     2     error: RUN/results/task_...parquet: no space left on   rows identical
    120k   1, 2     2     device; free some space and run the same command      rows identical
                          again: what is written is kept and the run resumes"

("resumed": after the file system is grown the same command finishes the run, and its
rows equal the reference run's.)  A completely full disk fails at the first file the run
writes, e.g. ``RUN/manifest.json: no space left on device; ...`` (exit 2).
(the field cache's blocks are reserved with ``posix_fallocate`` before it is mapped:
on a full disk it is not written and the field stays in memory, with one warning).
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path


def _rows(run):
    from glaciar import constants as C
    from glaciar.store import read_results

    keys = [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]
    return read_results(run).sort_values(keys).reset_index(drop=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=["3m", "400k", "250k", "120k"])
    ap.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    args = ap.parse_args(argv)
    if os.geteuid() != 0:
        print("needs root (mounts tmpfs file systems); nothing done")
        return 0

    import pandas as pd

    from glaciar.config import load_config
    from glaciar.demo import build_demo_survey
    from glaciar.execute import simulate

    root = Path(tempfile.mkdtemp(prefix="glaciar-full-disk-"))
    mnt = root / "mnt"
    mnt.mkdir()
    try:
        cfg_path = build_demo_survey(root / "survey", shape=(320, 320), seed=11, n_galaxies=12,
                                     n_iterations=2, z_values=(8.0, 10.4), mag_values=(24.0, 27.5))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            simulate(load_config(cfg_path), root / "reference", workers=1, progress=False)
        ref = _rows(root / "reference")
        cmd = [sys.executable, "-m", "glaciar", "simulate", str(cfg_path), "--out",
               str(mnt / "run"), "--quiet"]
        print(f"{'size':<7}{'workers':>8}{'exit':>6}  stderr / resumed")
        for size in args.sizes:
            for w in args.workers:
                subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)],
                               check=True)
                try:
                    p = subprocess.run(cmd + ["--workers", str(w)], capture_output=True,
                                       text=True)
                    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
                    subprocess.run(["mount", "-o", "remount,size=20m", str(mnt)], check=True)
                    q = subprocess.run(cmd + ["--workers", str(w)], capture_output=True,
                                       text=True)
                    try:
                        pd.testing.assert_frame_equal(_rows(mnt / "run"), ref)
                        resumed = f"resume exit {q.returncode}, rows identical to the reference"
                    except (AssertionError, FileNotFoundError, ValueError) as exc:
                        resumed = f"resume exit {q.returncode}, rows DIFFER ({exc})"
                    print(f"{size:<7}{w:>8}{p.returncode:>6}  {len(lines)} line(s)")
                    for ln in lines:
                        print(f"{'':23}{ln[:160]}")
                    print(f"{'':23}{resumed}")
                finally:
                    subprocess.run(["umount", str(mnt)], check=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
