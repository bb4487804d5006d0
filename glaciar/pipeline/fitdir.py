"""One consistent reader and writer of a run's fit outputs.

``glaciar fit``, ``report`` and ``next`` read a run while ``glaciar simulate``
may be writing it.  They take the run's lock (:class:`glaciar.rundir.RunLock`,
the one ``simulate`` holds while it writes) for as long as they read and
write, so they never read a half-grown store and ``simulate`` cannot start
under them; a run that is being written is refused in one line
(:func:`hold_run`).

``glaciar fit`` writes ``RUN_DIR/fit/`` and ``RUN_DIR/selection_function.fits``
as one unit (:class:`FitStage`):

1. everything is built in ``RUN_DIR/.fit.new/`` (``fit/`` and the file);
2. ``.fit.new`` is renamed ``.fit.commit``: from here on the new result is complete
   and the commit is rolled forward whatever happens;
3. ``fit/`` is renamed ``.fit.old``, ``.fit.commit/fit`` becomes ``fit/``, the
   file replaces ``selection_function.fits``, and ``.fit.old`` and ``.fit.commit``
   are removed.

A fit killed in step 1 leaves the previous result untouched (and ``.fit.new``,
removed at the next start); one killed in step 3 is completed at the next start
of ``fit``, ``report`` or ``next`` (:func:`recover_fit_outputs`), so the two never
come from different fits.  Temporary files of a killed fit (``fit/.*.tmp``,
``.selection_function.fits.*.tmp`` of glaciar versions that wrote in place) are
removed at that start too.
"""
from __future__ import annotations

import contextlib
import errno
import os
import shutil
from pathlib import Path

from .. import constants as C

__all__ = ["hold_run", "recover_fit_outputs", "FitStage", "STAGE_NAME", "COMMIT_NAME", "OLD_NAME"]

#: Staging directory of a fit being built (removed if found at a start: the fit was killed).
STAGE_NAME = ".fit.new"
#: The staged result once complete: a commit in progress (rolled forward if found).
COMMIT_NAME = ".fit.commit"
#: The previous ``fit/`` during a commit.
OLD_NAME = ".fit.old"
FIT_DIRNAME = "fit"


def _rmtree(path: Path) -> None:
    # A symlink is removed, never followed (only our own directories are deleted).
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.is_dir():
        shutil.rmtree(path)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def recover_fit_outputs(run_dir) -> None:
    """Finish or undo a killed fit's writes; remove its temporary files.

    Only the holder of the run's lock may call this.

    - ``.fit.new`` (a fit killed while building): removed; the previous result stays.
    - ``.fit.commit`` (killed while swapping in a complete result): the swap is
      completed, so ``fit/`` and ``selection_function.fits`` are both the new fit's.
    - ``.fit.old`` without a commit (killed while cleaning up): removed.
    - ``fit/.*.tmp`` and ``.selection_function.fits.*.tmp``: removed.
    """
    run_dir = Path(run_dir)
    stage, commit, old = run_dir / STAGE_NAME, run_dir / COMMIT_NAME, run_dir / OLD_NAME
    fit_dir = run_dir / FIT_DIRNAME
    _rmtree(stage)
    if commit.is_dir() and not commit.is_symlink():
        # Roll forward: the old result is not needed any more.
        _rmtree(old)
        if (commit / FIT_DIRNAME).is_dir():
            if fit_dir.exists() or fit_dir.is_symlink():
                os.replace(fit_dir, old)
            os.replace(commit / FIT_DIRNAME, fit_dir)
        if (commit / C.SELECTION_FUNCTION_NAME).is_file():
            os.replace(commit / C.SELECTION_FUNCTION_NAME, run_dir / C.SELECTION_FUNCTION_NAME)
        _fsync_dir(run_dir)
    _rmtree(commit)
    _rmtree(old)
    if fit_dir.is_dir() and not fit_dir.is_symlink():
        for p in fit_dir.glob(".*.tmp"):
            p.unlink(missing_ok=True)
    for p in run_dir.glob(f".{C.SELECTION_FUNCTION_NAME}.*.tmp"):
        p.unlink(missing_ok=True)


@contextlib.contextmanager
def hold_run(run_dir, command: str):
    """Hold ``run_dir``'s lock while ``command`` reads (and writes) it.

    Refuses (:class:`glaciar.rundir.RunLockedError`, one line naming the run) when
    ``glaciar simulate`` or another fit/report holds the lock.  Inside, a killed
    fit's leftovers have been cleaned (:func:`recover_fit_outputs`).

    Raises
    ------
    FileNotFoundError
        ``run_dir`` is not a directory.
    glaciar.rundir.RunLockedError
        Another process is writing the run.
    """
    from ..paths import check_run_tree
    from ..rundir import RunLock, RunLockedError, running_shards

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: no such run directory (expected the --out of "
                                "`glaciar simulate`)")
    lock = RunLock(run_dir)
    read_only = False
    try:
        lock.acquire()
    except OSError as exc:
        if exc.errno not in (errno.EACCES, errno.EPERM, errno.EROFS):
            raise
        read_only = True
    except RunLockedError as exc:
        if running_shards(run_dir):
            # The lock's own refusal names the shards and their pids (from their own
            # locks: the pid in RUN/.lock may be an earlier process's).
            raise RunLockedError(f"{exc}; `glaciar {command}` reads the run then") from None
        try:
            pid = (run_dir / C.LOCK_NAME).read_text().strip() or "unknown"
        except OSError:
            pid = "unknown"
        raise RunLockedError(f"{run_dir}: this run is being written by another glaciar process "
                             f"(pid {pid}: `glaciar simulate`, or a fit); `glaciar {command}` "
                             "reads it once that has finished — run it again then") from None
    if read_only:
        # A read-only run (an archive): nobody can write it, so reading is consistent; a
        # lock someone else holds is still refused (and nothing can be cleaned).
        lock.check_free()
        yield lock
        return
    try:
        # Linked sub-directories are refused before anything is read or cleaned, so a
        # fit, report or next never writes (or deletes) outside the run.
        check_run_tree(run_dir)
        recover_fit_outputs(run_dir)
        yield lock
    finally:
        lock.release()


class FitStage:
    """Build a fit's outputs beside the current ones, then swap them in as one unit.

    ``stage.fit_dir`` is where ``fit/`` is built and ``stage.selection_file``
    where ``selection_function.fits`` is written; :meth:`commit` swaps both in.
    Leaving the ``with`` block without a commit (an error) removes the stage and
    leaves the previous result untouched.
    """

    def __init__(self, run_dir):
        self.run_dir = Path(run_dir)
        self.root = self.run_dir / STAGE_NAME
        self.fit_dir = self.root / FIT_DIRNAME
        self.selection_file = self.root / C.SELECTION_FUNCTION_NAME
        self.committed = False

    def __enter__(self) -> "FitStage":
        _rmtree(self.root)
        self.fit_dir.mkdir(parents=True)
        return self

    def __exit__(self, exc_type, exc, tb):
        if not self.committed:
            _rmtree(self.root)
        return False

    def commit(self) -> Path:
        """Swap the staged ``fit/`` and file in; returns the path of the new file."""
        _fsync_dir(self.fit_dir)
        _fsync_dir(self.root)
        commit = self.run_dir / COMMIT_NAME
        _rmtree(commit)
        os.replace(self.root, commit)          # the point of no return
        self.committed = True
        _fsync_dir(self.run_dir)
        recover_fit_outputs(self.run_dir)      # the roll-forward: one code path for both
        return self.run_dir / C.SELECTION_FUNCTION_NAME
