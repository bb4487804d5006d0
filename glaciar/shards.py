"""Sharded runs: a deterministic 1/N of a run's tasks per process, and a run's status.

``glaciar simulate CONFIG --out RUN --shard K/N`` runs shard K of N
(:func:`shard_tasks`): N processes (a SLURM array, machines sharing a file
system) fill one run directory together.  How they share it safely (locks,
set-up, field cache, compaction) is :class:`glaciar.rundir.RunLock`'s,
:func:`glaciar.manifest.open_run`'s and :func:`glaciar.store.compact`'s; the shard
count a run was started with is recorded once per shard in ``RUN/.shards/``
(:func:`glaciar.rundir.check_shard_count`).  :func:`run_status` is what
``glaciar status RUN`` prints.

:func:`parse_shard`, :func:`check_shard` and :func:`shard_bounds` are pure.
"""
from __future__ import annotations

import re
from pathlib import Path

from . import constants as C

__all__ = ["SHARD_SNAP_FRACTION", "parse_shard", "check_shard", "shard_bounds", "shard_tasks",
           "shard_task_names", "shard_scope", "run_status", "format_status"]

#: A cut between two shards moves to the nearest (field, z) boundary when that boundary lies
#: within this fraction of one shard's expected cost of the equal-cost cut: the shard's worker
#: then renders that (field, z)'s templates alone (glaciar.execute chunks one (field, z) at a
#: time).  It bounds the imbalance (:func:`shard_bounds`).
SHARD_SNAP_FRACTION = 0.1

_SHARD_TEXT = re.compile(r"\s*(\d+)\s*/\s*(\d+)\s*")


def check_shard(shard) -> tuple[int, int]:
    """``(k, n)`` as two ints with ``1 <= k <= n``, else a one-line :class:`ValueError`."""
    try:
        k, n = shard
        ok = all(isinstance(v, int) and not isinstance(v, bool) for v in (k, n))
    except (TypeError, ValueError):
        ok = False
    if not ok or not 1 <= k <= n:
        raise ValueError(f"shard: expected (K, N) with integers 1 <= K <= N, got {shard!r}")
    return int(k), int(n)


def parse_shard(text: str) -> tuple[int, int]:
    """``"K/N"`` (e.g. ``"3/8"``, SLURM's ``${SLURM_ARRAY_TASK_ID}/8``) as ``(k, n)``.

    Raises
    ------
    ValueError
        One line naming the text when it is not two integers with ``1 <= K <= N``.
    """
    m = _SHARD_TEXT.fullmatch(str(text))
    if m is None or not 1 <= int(m.group(1)) <= int(m.group(2)):
        raise ValueError(f"expected K/N with integers 1 <= K <= N (e.g. 1/4), got {text!r}")
    return int(m.group(1)), int(m.group(2))


def shard_bounds(costs, group_starts, n: int) -> list[int]:
    """Where the ordered tasks are cut into ``n`` contiguous shards of about equal cost.

    Parameters
    ----------
    costs : sequence of float
        Each task's expected cost (> 0), in plan order.
    group_starts : set of int
        Task indices at which a new (field, z) group starts (0 and ``len(costs)``
        count as boundaries anyway).
    n : int
        Number of shards (>= 1).

    Returns
    -------
    list of int
        ``n + 1`` non-decreasing indices, ``0`` first and ``len(costs)`` last: shard
        ``k`` (1-based) is ``tasks[b[k - 1]:b[k]]``.

    Notes
    -----
    With ``C`` the summed cost, cut ``i`` ideally lies at cumulative cost ``i C / n``.
    It is put at the group boundary nearest that point if one lies within
    ``SHARD_SNAP_FRACTION * C / n``, else at the nearest task boundary (at most half
    the largest task cost ``c_max`` away).  Every cut is thus within
    ``d = max(SHARD_SNAP_FRACTION * C / n, c_max / 2)`` of its ideal point, and every
    shard's cost within ``2 d`` of ``C / n``.
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"n: expected an integer >= 1, got {n!r}")
    cum = [0.0]
    for c in costs:
        cum.append(cum[-1] + float(c))
    total, n_tasks = cum[-1], len(cum) - 1
    snap = SHARD_SNAP_FRACTION * total / n
    groups = sorted({0, n_tasks} | {int(g) for g in group_starts if 0 <= g <= n_tasks})
    bounds = [0]
    for i in range(1, n):
        ideal = i * total / n
        near = min(groups, key=lambda j: (abs(cum[j] - ideal), j))
        if abs(cum[near] - ideal) > snap:
            near = min(range(n_tasks + 1), key=lambda j: (abs(cum[j] - ideal), j))
        bounds.append(max(near, bounds[-1]))
    bounds.append(n_tasks)
    return bounds


def shard_tasks(specs, k: int, n: int, costs=None) -> list:
    """Shard ``k`` of ``n`` of a plan's tasks: a contiguous piece of about 1/n of the cost.

    Parameters
    ----------
    specs : list of glaciar.engine.task.TaskSpec
        The plan, in :func:`glaciar.plan.plan_tasks`' order (field -> z -> mag -> iteration).
    k, n : int
        Shard number (1-based) and count, ``1 <= k <= n``.
    costs : sequence of float, optional
        Each task's expected cost.  Default: 1 per task.  The cost model: a task's CPU
        scales with its source count, and every task of a run draws
        ``simulation.n_galaxies`` sources, so tasks cost the same; no per-magnitude
        factor is applied (none measured).

    Returns
    -------
    list of TaskSpec
        The shard's tasks in plan order.  Every task is in exactly one shard of a
        given ``n``; the assignment depends only on the plan and ``n``.  Contiguous
        pieces keep most (field, z) groups inside one shard (at most ``n - 1`` are
        split), cut at group boundaries where that costs little (:func:`shard_bounds`).
    """
    k, n = check_shard((k, n))
    specs = list(specs)
    costs = [1.0] * len(specs) if costs is None else [float(c) for c in costs]
    if len(costs) != len(specs):
        raise ValueError(f"costs: expected {len(specs)} values, got {len(costs)}")
    starts = {i for i in range(1, len(specs))
              if (specs[i].field, specs[i].z) != (specs[i - 1].field, specs[i - 1].z)}
    b = shard_bounds(costs, starts, n)
    return specs[b[k - 1]:b[k]]


def shard_task_names(cfg, shard) -> set[str]:
    """File names (:func:`glaciar.plan.spec_filename`) of shard ``(k, n)``'s tasks of ``cfg``."""
    from .plan import plan_tasks, spec_filename

    k, n = check_shard(shard)
    return {spec_filename(s) for s in shard_tasks(plan_tasks(cfg), k, n)}


def shard_scope(plan, shard) -> tuple[list, dict]:
    """The tasks a process runs and the :func:`glaciar.store.compact` arguments that keep it
    to its own files: ``(plan, {})`` unsharded, ``(shard_tasks(plan, k, n), {"tasks": their
    file names, "tag": "s<k>"})`` for shard ``(k, n)``."""
    from .plan import spec_filename

    if shard is None:
        return list(plan), {}
    k, n = check_shard(shard)
    specs = shard_tasks(plan, k, n)
    return specs, {"tasks": {spec_filename(s) for s in specs}, "tag": f"s{k}"}


# --------------------------------------------------------------------------
# Status of a run directory (``glaciar status``)
# --------------------------------------------------------------------------
def run_status(run_dir) -> list[dict]:
    """Per shard (or once, for an unsharded run) the tasks done, running and missing.

    The plan is that of the run's stored configuration (``RUN/config.yaml``); a task is
    done when the store holds it (:func:`glaciar.store.finished_task_names`).  A shard's
    not-done tasks count as running while its shard lock is held (an unsharded run's while
    the run's lock is held exclusively), else as missing.

    Returns
    -------
    list of dict
        ``{"shard": k or None, "of": n or None, "tasks", "done", "running", "missing",
        "pid": holder's pid text or None}``, shards in order.
    """
    from .config import load_config
    from .plan import finished_specs, plan_tasks
    from .rundir import read_shard_counts, run_holder, shard_holder

    run_dir = Path(run_dir)
    cpath = run_dir / C.RUN_CONFIG_NAME
    if not cpath.is_file():
        raise FileNotFoundError(f"{cpath}: no stored configuration (expected the --out of "
                                "`glaciar simulate`)")
    specs = plan_tasks(load_config(cpath))
    finished = finished_specs(run_dir, specs, verify=False)   # each population in its store
    counts = set(read_shard_counts(run_dir).values())
    if len(counts) > 1:
        raise ValueError(f"{run_dir / C.SHARDS_DIRNAME}: shard records disagree on the shard "
                         f"count ({', '.join(map(str, sorted(counts)))})")

    def row(k, n, tasks, pid):
        done = sum(s in finished for s in tasks)
        rest = len(tasks) - done
        return {"shard": k, "of": n, "tasks": len(tasks), "done": done,
                "running": rest if pid else 0, "missing": 0 if pid else rest, "pid": pid}

    if not counts:
        return [row(None, None, specs, run_holder(run_dir))]
    n = counts.pop()
    return [row(k, n, shard_tasks(specs, k, n), shard_holder(run_dir, k)) for k in range(1, n + 1)]


def format_status(run_dir, rows: list[dict]) -> str:
    """:func:`run_status`'s rows as ``glaciar status`` prints them (one line each, a total)."""
    def counts(r):
        who = f" (pid {r['pid']})" if r["pid"] else ""
        return (f"{r['tasks']} tasks: {r['done']} done, {r['running']} running{who}, "
                f"{r['missing']} missing")

    if rows and rows[0]["shard"] is None:
        return f"{run_dir}: {counts(rows[0])}\n"
    lines = [f"shard {r['shard']}/{r['of']}: {counts(r)}" for r in rows]
    total = {key: sum(r[key] for r in rows) for key in ("tasks", "done", "running", "missing")}
    lines.append(f"{run_dir}: {total['tasks']} tasks in {len(rows)} shards: {total['done']} done, "
                 f"{total['running']} running, {total['missing']} missing")
    return "\n".join(lines) + "\n"

