"""glaciar.execute.simulate with one worker: the set-up's code pages go before the tasks."""
from __future__ import annotations

import glaciar.execute as execute
from glaciar.config import load_config
from glaciar.contexts import clear_contexts
from glaciar.store import read_results


def test_one_worker_drops_file_pages_before_the_first_task_and_after_it(two_task_run, tmp_path,
                                                                        monkeypatch):
    cfg_path, reference = two_task_run
    events = []
    drop, run_task = execute.drop_file_pages, execute.task_columns

    def counted_drop():
        events.append("drop")
        return drop()

    def counted_task(*args, **kwargs):
        events.append("task")
        return run_task(*args, **kwargs)

    monkeypatch.setattr(execute, "drop_file_pages", counted_drop)
    monkeypatch.setattr(execute, "task_columns", counted_task)
    clear_contexts()                # the field is measured in this call
    execute.simulate(load_config(cfg_path), tmp_path / "run", workers=1, progress=False)
    assert events == ["drop", "task", "drop", "task"]
    # Again with the field's context kept from that call: no set-up ran, nothing dropped.
    events.clear()
    execute.simulate(load_config(cfg_path), tmp_path / "again", workers=1, progress=False)
    assert events == ["task", "task"]
    # The first task run apart from its chunk: the same rows, bit for bit.
    new, old = read_results(tmp_path / "run"), read_results(reference)
    key = sorted(new.columns)
    new = new[key].sort_values(key[:3]).reset_index(drop=True)
    old = old[key].sort_values(key[:3]).reset_index(drop=True)
    assert new.equals(old)
