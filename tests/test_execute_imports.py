"""glaciar.execute.simulate with one worker: the tasks run and write without pandas.

pandas' import stays resident (~22 MB anonymous memory) for the rest of a process: a
one-worker ``simulate`` imports it only after its tasks (summaries), so that it is not part
of the tasks' peak RSS.  Its task files are the same bytes as those written from the
rows' DataFrame.
"""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from glaciar.constants import COL_MAG_INPUT, RESULTS_DIRNAME, band_column, OBS_MAG_QUANTITY
from glaciar.store import write_task_table
from glaciar.taskfile import META_COUNTS, META_HIST, META_TASK, ipc_table

from tiny_runs import tiny_config, write_yaml

#: Run in a fresh interpreter: glaciar imported, a one-worker simulate, and at each task
#: file written (after each task) whether pandas has been imported so far; then a copy of
#: the run compacted (as a long run does every COMPACT_EVERY tasks).
_CHILD = textwrap.dedent("""
    import json, shutil, sys
    import glaciar.execute as execute
    from glaciar.config import load_config
    from glaciar.store import compact

    seen, write = [], execute.write_task_table

    def hooked(*args, **kwargs):
        out = write(*args, **kwargs)
        seen.append("pandas" in sys.modules)
        return out

    execute.write_task_table = hooked
    stats = execute.simulate(load_config(sys.argv[1]), sys.argv[2], workers=1, progress=False)
    shutil.copytree(sys.argv[2], sys.argv[2] + "_compacted")
    n = compact(sys.argv[2] + "_compacted", min_tasks=0)
    print(json.dumps({"pandas_at_each_task": seen, "n_run": stats["n_run"], "n_compacted": n,
                      "pandas_after_compaction": "pandas" in sys.modules}))
""")


@pytest.fixture(scope="module")
def child_run(small_survey_dict, tmp_path_factory):
    root = tmp_path_factory.mktemp("no_pandas")
    d = tiny_config(small_survey_dict, mag=(24.0, 27.5))
    cfg = write_yaml(d, root / "c.yaml")
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(cfg), str(root / "run")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return d, root / "run", json.loads(proc.stdout.strip().splitlines()[-1])


def test_one_worker_tasks_import_no_pandas(child_run):
    _, _, report = child_run
    assert report["n_run"] == 2
    # Before: glaciar.execute imported pandas (engine.task, store, counting at module level).
    assert report["pandas_at_each_task"] == [False, False]
    # Before: a compaction converted the tasks' footer tables to DataFrames (and
    # pyarrow.parquet.read_table imports pandas through pyarrow.dataset).
    assert report["n_compacted"] == 2 and report["pandas_after_compaction"] is False


def test_compacted_part_holds_the_task_files_rows_and_footer_tables(child_run):
    _, run, _ = child_run
    files = sorted((run / RESULTS_DIRNAME).glob("task_*.parquet"))
    parts = sorted((run.parent / "run_compacted" / RESULTS_DIRNAME).rglob("part-*.parquet"))
    assert len(parts) == 1
    tasks = [pq.read_table(f) for f in files]
    part = pq.read_table(parts[0])
    assert part.replace_schema_metadata(None).equals(
        pa.concat_tables([t.replace_schema_metadata(None) for t in tasks]))
    meta = pq.read_metadata(parts[0]).metadata
    for key in (META_COUNTS, META_HIST):
        want = pa.concat_tables([ipc_table(pq.read_metadata(f).metadata[key]) for f in files])
        assert ipc_table(meta[key]).equals(want)


def test_task_files_are_the_bytes_written_from_the_dataframe(child_run, tmp_path):
    d, run, _ = child_run
    files = sorted((run / RESULTS_DIRNAME).glob("task_*.parquet"))
    assert len(files) == 2
    obs = band_column(OBS_MAG_QUANTITY, d["survey"]["detection_band"])
    for f in files:
        table = pq.read_table(f)
        rows = table.to_pandas()
        # the rows as the DataFrame path wrote them: same key, counts and histograms
        key = table.schema.metadata[META_TASK].decode("utf-8")
        write_task_table(tmp_path, f.name, rows, key=key, mag_column=COL_MAG_INPUT, obs_column=obs)
        assert (tmp_path / RESULTS_DIRNAME / f.name).read_bytes() == f.read_bytes()
