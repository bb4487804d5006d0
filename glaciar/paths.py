"""File names from user strings, directories inside a run, and full disks.

Three facts every writer of a run directory shares, defined once here:

* :func:`file_stem` is the one mapping from a user string (a field, band or
  catalogue name) to a file-name part.  Ordinary names are used as they are
  (so the demo's and the tests' file names do not change); any other name is
  escaped and gets a short hash of the exact string, so distinct names never
  share a file and no name can leave its directory (``../x``, ``a/b``, ``.``).
* :func:`run_subdir` returns a sub-directory of a run directory, creating it,
  and refuses one that is a symbolic link (or not a directory) with one line
  naming it: glaciar writes only inside the run directory.
* :class:`DiskFullError` is how a write that ran out of space is reported: one
  line naming the file and saying that the same command resumes once space is
  freed.  :func:`allocate` reserves a file's blocks before it is written or
  memory-mapped, so that a full disk raises ``ENOSPC`` there instead of killing
  the process with ``SIGBUS`` when a mapped page is first written.

Task files of the store keep their own, older naming (:func:`readable` part plus
a hash of the exact task key, :func:`glaciar.store.task_filename`), which is
already injective and safe: changing it would orphan every existing run.
"""
from __future__ import annotations

import errno
import hashlib
import os
import re
import stat
from pathlib import Path

__all__ = ["file_stem", "readable", "run_subdir", "check_run_tree", "UnsafePathError", "DiskFullError",
           "disk_full", "allocate", "RUN_SUBDIRS"]

#: An ordinary name: used as a file-name part unchanged.  Letters, digits and ``_+-.``, not
#: starting with ``.`` (no hidden files, no ``.``/``..``), at most 64 characters.
_ORDINARY = re.compile(r"[A-Za-z0-9_+-][A-Za-z0-9_.+-]{0,63}")
#: Characters of an escaped name kept as they are (others become ``_``).
_KEEP = re.compile(r"[^A-Za-z0-9_.+-]")
#: Separator of an escaped name and its hash: never in an ordinary name, so an escaped
#: name never equals an ordinary one.
_HASH_SEP = "~"
#: Hex digits of the SHA-256 of the exact name appended to an escaped name.
_HASH_CHARS = 10
#: Characters of the readable part of an escaped name.
_READABLE_CHARS = 40

#: Sub-directories of a run that glaciar writes into (each refused when a symbolic link).
RUN_SUBDIRS = ("results", "results/compact", "results/corrupt", "summary", "summary/regions",
               "fit", "lf", ".context")


class UnsafePathError(ValueError):
    """A path inside a run directory that glaciar refuses to write through (one line)."""


class DiskFullError(OSError):
    """A write ran out of space (``ENOSPC``/``EDQUOT``); the message names the file.

    ``str()`` is the one-line message alone (no ``[Errno 28]`` prefix); the
    instance is an :class:`OSError` with ``errno`` set, so callers that already
    handle write failures (e.g. a field cache that cannot be written) still do.
    """

    def __init__(self, code: int, message: str):
        super().__init__(code, message)

    def __str__(self) -> str:
        return str(self.strerror)


def readable(name, n: int) -> str:
    """The first ``n`` characters of ``name`` with every character other than letters,
    digits and ``_.+-`` replaced by ``_`` (the readable part of an escaped name; task files
    and compacted partitions use it beside a hash of the exact name, glaciar.store)."""
    return _KEEP.sub("_", str(name))[:n]


def file_stem(name, reserved=()) -> str:
    """The file-name part of a user string (field, band or catalogue name).

    Parameters
    ----------
    name : str
        Any string.
    reserved : iterable of str
        Stems the caller uses for something else in the same directory (e.g.
        ``"all"`` for the pooled summary): a name equal to one is escaped.

    Returns
    -------
    str
        ``name`` itself when it is ordinary (letters, digits, ``_+-.``, not
        starting with ``.``, at most 64 characters) and not reserved; else its
        first 40 characters with every other character replaced by ``_``, then
        ``~`` and the first 10 hex digits of the SHA-256 of ``name``.  The
        result never contains a path separator, never is ``.`` or ``..``, and
        distinct names give distinct stems (ordinary ones are unchanged, escaped
        ones carry ``~`` which ordinary ones cannot, and differ by their 40-bit
        hash).  On a case-insensitive file system ``A`` and ``a`` still meet.
    """
    s = str(name)
    if _ORDINARY.fullmatch(s) and s not in set(reserved):
        return s
    digest = hashlib.sha256(s.encode("utf-8", "surrogatepass")).hexdigest()[:_HASH_CHARS]
    return f"{readable(s, _READABLE_CHARS).lstrip('.')}{_HASH_SEP}{digest}"


def _refuse_link(p: Path) -> UnsafePathError:
    try:
        target = os.readlink(p)
    except OSError:
        target = "?"
    return UnsafePathError(f"{p}: is a symbolic link (to {target}); glaciar writes only inside "
                           "the run directory: replace it with a real directory (or remove it)")


def run_subdir(run_dir, *parts: str, create: bool = True) -> Path:
    """``run_dir / parts...``, each level a real directory inside the run (created if missing).

    Raises
    ------
    UnsafePathError
        A level is a symbolic link, or exists and is not a directory (named).
    """
    p = Path(run_dir)
    if create:
        p.mkdir(parents=True, exist_ok=True)      # the run directory itself may be a link
    for part in parts:
        for piece in Path(part).parts:
            if piece in ("", ".", "..") or os.sep in piece:
                raise UnsafePathError(f"{p}: {piece!r} is not a sub-directory name")
            p = p / piece
            try:
                st = os.lstat(p)
            except FileNotFoundError:
                if not create:
                    continue
                try:
                    p.mkdir()
                except FileExistsError:        # made meanwhile: checked below
                    pass
                st = os.lstat(p)
            if stat.S_ISLNK(st.st_mode):
                raise _refuse_link(p)
            if not stat.S_ISDIR(st.st_mode):
                raise UnsafePathError(f"{p}: exists and is not a directory; glaciar needs a "
                                      "directory there (move the file away)")
    return p


def check_run_tree(run_dir, names=RUN_SUBDIRS) -> None:
    """Refuse a run directory in which a sub-directory glaciar writes to is a symbolic link.

    Checks ``names`` (default :data:`RUN_SUBDIRS`), the partitions of compacted parts
    and the run's lock file; creates nothing.  Raises :class:`UnsafePathError` naming the first offending path.
    """
    root = Path(run_dir)
    for name in names:
        run_subdir(root, name, create=False)
    # The partitions of compacted parts (results/compact/field=*/z=*/): parts are written,
    # and corrupt ones moved, below them.
    compact = root / "results" / "compact"
    if compact.is_dir():
        for field_dir in compact.iterdir():
            if field_dir.is_symlink():
                raise _refuse_link(field_dir)
            if field_dir.is_dir():
                for z_dir in field_dir.iterdir():
                    if z_dir.is_symlink():
                        raise _refuse_link(z_dir)
    lock = root / ".lock"
    if lock.is_symlink():
        raise _refuse_link(lock)


# --------------------------------------------------------------------------
# Full disks
# --------------------------------------------------------------------------
_NO_SPACE = frozenset({errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)})


def disk_full(path, exc: BaseException) -> DiskFullError | None:
    """A :class:`DiskFullError` naming ``path`` if ``exc`` is a full disk or quota, else None."""
    if isinstance(exc, DiskFullError):
        return exc
    if not isinstance(exc, OSError) or exc.errno not in _NO_SPACE:
        return None
    what = "disk quota exceeded" if exc.errno != errno.ENOSPC else "no space left on device"
    return DiskFullError(exc.errno, f"{path}: {what}; free some space and run the same command "
                                    "again: what is written is kept and the run resumes")


def allocate(fd: int, size: int, path) -> None:
    """Reserve ``size`` bytes of the open file ``fd`` (``os.posix_fallocate``) before writing.

    A file that is memory-mapped and then written gets its blocks when a page is
    first written: on a full disk the kernel then sends ``SIGBUS`` and the process
    dies ("Bus error", no message).  Allocated first, the same full disk is an
    ``ENOSPC`` here, raised as :class:`DiskFullError` naming ``path``.  Where the
    call is unavailable or unsupported by the file system, nothing is reserved.
    """
    fallocate = getattr(os, "posix_fallocate", None)
    if fallocate is None or size <= 0:
        return
    try:
        fallocate(fd, 0, int(size))
    except OSError as exc:
        full = disk_full(path, exc)
        if full is not None:
            raise full from None
        if exc.errno in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS,
                         getattr(errno, "ENOTSUP", errno.EOPNOTSUPP)):
            return
        raise
