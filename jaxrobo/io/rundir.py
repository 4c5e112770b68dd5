"""Run directories that are never lost nor mixed: checked before anything compiles, written whole or not at all.

The rules (``jaxrobo train``; ``jaxrobo sweep`` uses the same helpers):

* :func:`check_out` validates an output path at the boundary, before any compile: an existing file, a non-empty
  directory (without ``--overwrite`` or ``--resume``), a non-writable parent are refused with a
  :class:`~jaxrobo.core.config.ConfigError` naming the flag, what is wrong and which flag would allow it.
* Finished results are written into a fresh hidden sibling (:func:`staging`) and moved into place by
  :func:`publish`, so a crash while writing never leaves a half-written directory that looks complete; an old run
  is replaced only when the caller says so (``--overwrite``, or resuming it).
* Single files that are rewritten while a run goes on (the checkpoint, ``status.json``) go through
  :func:`atomic_write`: a temporary file in the same directory, ``fsync``, ``os.replace``, ``fsync`` of the
  directory. A reader sees the old file or the new one, never a torn one.
* ``status.json`` says what a directory holds: ``{"status": "running" | "interrupted" | "complete", ...}``
  (:func:`write_status` / :func:`read_status`); :func:`is_complete` and :func:`is_resumable` read it.
* The life of a run directory, shared by ``jaxrobo train`` and ``jaxrobo sweep``: :func:`live_dir` is where a new
  run keeps its state (checkpoint, status) while it runs; :func:`interrupted` marks it interrupted and says on
  stderr how to go on; :func:`publish_results` writes the finished results into a staging directory and moves
  them into place, then drops the state.
"""
from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import fnmatch
import json
import os
import re
import shutil
import stat
import sys
import tempfile
from typing import IO, Any, Callable, Iterator

from jaxrobo.core.config import ConfigError, parse_json

#: The training carry of an unfinished run (see :func:`jaxrobo.training.checkpoint.save_checkpoint`), or a sweep's
#: finished groups.
CHECKPOINT = "checkpoint.npz"
#: The learner's tables of a run's checkpoint, in a file of their own beside it (``checkpoint.tables.<8 hex>.npz``,
#: laid out as ``qtables.npz``: :func:`jaxrobo.training.checkpoint.save_checkpoint`), as an ``fnmatch`` pattern.
CHECKPOINT_TABLES = "checkpoint.tables.*.npz"
#: Its episode records, likewise (``checkpoint.records.<8 hex>.npz``, laid out as ``records.npz``).
CHECKPOINT_RECORDS = "checkpoint.records.*.npz"
#: What the directory holds: ``running``, ``interrupted`` or ``complete``, and how to resume.
STATUS = "status.json"
RUNNING, INTERRUPTED, COMPLETE = "running", "interrupted", "complete"
#: Every entry that ``jaxrobo train`` (tabular and ppo/sac) and ``jaxrobo sweep`` write in a run directory, as
#: ``fnmatch`` patterns: only these are ever replaced or removed (with the hidden temporaries ``.NAME.*`` of
#: :func:`atomic_path` beside them); every other file or folder belongs to the user and is kept through a resume,
#: an ``--overwrite`` and a sweep. tests/test_rundir_owned.py checks that real runs write nothing else.
OWNED = (
    # tabular runs (jaxrobo.io.results)
    "config.yaml", STATUS, CHECKPOINT, CHECKPOINT_TABLES, CHECKPOINT_RECORDS, "summary.json", "episodes.csv",
    "episode_stats.csv", "records.npz", "qtables.npz", "eval.csv", "tensorboard",
    # ppo/sac runs (jaxrobo.deep.output, jaxrobo.deep.policy)
    "policy.npz", "policy.json", "best", "evaluations.csv", "training_metrics.csv", "rewards.png",
    # sweeps (jaxrobo.training.sweep.state, .output)
    "sweep.csv", "sweep_state.json", "group_*.npz", "sweep_*.png", "heatmap_*.png",
)
#: What jaxrobo writes inside the directories of :data:`OWNED` (the rest of such a directory is the user's: a
#: ``best/`` a user made in a tabular run's directory keeps what they put there).
OWNED_INSIDE = {"best": ("policy.npz", "policy.json"), "tensorboard": ("events.out.tfevents.*",)}
#: Files by which a directory is recognised as a jaxrobo run (or sweep), besides a ``status.json`` of a known
#: status: only such a directory is ever replaced. One of them alone (a project's own ``config.yaml``) is not.
LEGACY_MARKERS = (("summary.json", "config.yaml"), ("summary.json", "sweep.csv"))


# ---- status --------------------------------------------------------------------------------------------------
#: Bytes of ``status.json`` read at most: jaxrobo writes a few hundred; a larger file is not one of its statuses.
STATUS_MAX_BYTES = 1 << 20


def read_status(path: str) -> dict[str, Any] | None:
    """The directory's ``status.json`` as a dict, or None when it has none (or an unreadable one, one larger than
    :data:`STATUS_MAX_BYTES`, or one that is not a regular file)."""
    try:
        if not stat.S_ISREG(os.stat(os.path.join(path, STATUS)).st_mode):
            return None
        with open(os.path.join(path, STATUS), "rb") as f:
            raw = f.read(STATUS_MAX_BYTES + 1)  # never more than the cap, whatever the file's size
        status = parse_json(raw) if len(raw) <= STATUS_MAX_BYTES else None
    except (OSError, ValueError):
        return None
    return status if isinstance(status, dict) else None


def write_status(path: str, status: str, **fields: Any) -> None:
    """Atomically write ``status.json``: ``{"status": status, **fields}``."""
    atomic_write_json(os.path.join(path, STATUS), {"status": status, **fields})


def is_complete(path: str) -> bool:
    """A finished run: its status says ``complete`` (a directory from before statuses existed: it has the files of
    one of :data:`LEGACY_MARKERS` and no checkpoint)."""
    if not os.path.isdir(path):
        return False
    status = read_status(path)
    if status is not None:
        return status.get("status") == COMPLETE
    return _looks_like_run(path) and not os.path.exists(os.path.join(path, CHECKPOINT))


def is_resumable(path: str) -> bool:
    """An unfinished run that can go on: it has a checkpoint and its status is not ``complete``."""
    return (os.path.isdir(path) and os.path.isfile(os.path.join(path, CHECKPOINT))
            and (read_status(path) or {}).get("status") != COMPLETE)


def _looks_like_run(path: str) -> bool:
    """A jaxrobo run or sweep: a ``status.json`` of a known status, or (from before statuses existed) both files of
    one of :data:`LEGACY_MARKERS`."""
    if (read_status(path) or {}).get("status") in (RUNNING, INTERRUPTED, COMPLETE):
        return True
    return any(all(os.path.isfile(os.path.join(path, n)) for n in names) for names in LEGACY_MARKERS)


def looks_like_run(path: str) -> bool:
    """Whether the directory ``path`` holds a jaxrobo run or sweep (:func:`_looks_like_run`); False if missing."""
    return os.path.isdir(path) and _looks_like_run(path)


def owned(name: str, patterns: tuple[str, ...] = OWNED) -> bool:
    """Whether the entry ``name`` of a run directory is jaxrobo's (one of ``patterns``, :data:`OWNED` by default,
    or a hidden temporary of one)."""
    if any(fnmatch.fnmatchcase(name, pattern) for pattern in patterns):
        return True
    return name.startswith(".") and any(fnmatch.fnmatchcase(name, f".{pattern}.*") for pattern in patterns)


def user_entries(path: str) -> list[str]:
    """The entries of the directory ``path`` that are not jaxrobo's (:func:`owned`): the user's, kept."""
    try:
        return sorted(n for n in os.listdir(path) if not owned(n))
    except OSError:
        return []


def check_owned_entries(path: str, flag: str = "--resume") -> None:
    """Refuse (:class:`ConfigError` naming the path) a run directory that jaxrobo is to read and write in place
    (``--resume``) when one of its own entries is not a plain file or folder: a symlink (a write would go through
    it, possibly outside the directory) or a special file (a FIFO or a device, which a read would hang on or
    never finish)."""
    try:
        names = os.listdir(path)
    except OSError:
        return
    for name in sorted(names):
        if not owned(name) or name.startswith("."):
            continue
        full = os.path.join(path, name)
        st = os.lstat(full)
        if stat.S_ISLNK(st.st_mode):
            raise ConfigError(f"{flag} {path}: {full} is a symlink (to {os.readlink(full)}); jaxrobo writes its own "
                              "files only as plain files in the run directory: replace the link with the file")
        if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
            raise ConfigError(f"{flag} {path}: {full} is not a regular file (a FIFO, socket or device); remove it")


def _describe(path: str) -> str:
    if is_complete(path):
        return "a complete run"
    if is_resumable(path):
        return "an interrupted run"
    if _looks_like_run(path):
        return "an unfinished run without a checkpoint"
    return "files that are not a jaxrobo run"


# ---- checks at the boundary ----------------------------------------------------------------------------------
def check_out(path: str, *, overwrite: bool = False, resume: bool = False, flag: str = "--out") -> str:
    """Refuse an output path that would lose or mix runs, before anything compiles.

    ``path`` may be missing (it is created, parents too) or an empty directory. A non-empty directory needs
    ``overwrite`` (and must look like a jaxrobo run: nothing else is ever replaced) or ``resume`` (and must hold
    a checkpoint of an unfinished run). An existing file, or a parent that is a file or not writable, is refused
    whatever the flags. Raises :class:`ConfigError` naming ``flag`` (``--out`` or ``--resume``). Returns the
    absolute path the run goes to (:func:`resolve_out`: a symlink to a directory is followed)."""
    if not path:
        raise ConfigError(f"{flag}: empty path")
    where = f"{flag} {path}"
    path = resolve_out(path, flag)
    if os.path.exists(path) and not os.path.isdir(path):
        if resume:  # the advice for --out (a new or empty directory) would be nonsense here
            raise ConfigError(f"{where}: is an existing file, not a run directory; give the directory of the run "
                              "to go on with")
        raise ConfigError(f"{where}: is an existing file, not a directory; give a new or empty directory "
                          "(--overwrite replaces run directories only)")
    if resume:
        try:
            if not os.path.isdir(path):
                raise ConfigError(f"{where}: no such run directory")
            if not is_resumable(path):
                path = pending(path) or path
            check_owned_entries(path, flag)
            if is_complete(path):
                raise ConfigError(f"{where}: the run is complete, nothing to resume")
            if not is_resumable(path):
                raise ConfigError(f"{where}: no {CHECKPOINT} in it ({_describe(path)}); nothing to resume")
        except ConfigError:
            # A run another process is writing has no checkpoint yet (or its --overwrite state no checkpoint beside
            # the complete old run): that process is the reason, named as a second writer's refusal names it.
            holder = lock_holder(path)
            if holder is not None:
                raise RunLocked(_locked_message(where, holder)) from None
            raise
    elif os.path.isdir(path) and os.listdir(path):
        what = _describe(path)
        if not overwrite:
            hint = "give --overwrite to replace it" if _looks_like_run(path) else "choose another path"
            if is_resumable(path):
                hint += f", or --resume {path} to continue it"
            raise ConfigError(f"{where}: directory is not empty (it holds {what}); {hint}")
        if not _looks_like_run(path):
            raise ConfigError(f"{where}: directory is not empty and holds {what}; --overwrite replaces jaxrobo run "
                              "directories only: choose another path")
    # The parent must take a hidden sibling (staging) and a rename: the nearest existing ancestor must be a
    # writable directory.
    parent = os.path.dirname(os.path.abspath(path))
    ancestor = parent
    while not os.path.exists(ancestor):
        ancestor = os.path.dirname(ancestor)
    if not os.path.isdir(ancestor):
        raise ConfigError(f"{where}: {ancestor} is a file, not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ConfigError(f"{where}: cannot write in {ancestor} (permission denied)")
    # os.access says yes to root on a read-only or pseudo file system (/proc): try a directory there.
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".jaxrobo-probe.", dir=ancestor))
    except OSError as err:
        raise ConfigError(f"{where}: cannot write in {ancestor} ({err.strerror or err})") from None
    return path


#: Room a hidden sibling (``.NAME.<8 random>.partial``, ``.NAME.lock``) needs on top of NAME.
_SIBLING_EXTRA = len("..12345678.partial")


def resolve_out(path: str, flag: str = "--out") -> str:
    """The directory a run at ``path`` is written to, checked at the boundary: a symlink to a directory is
    followed (the run is published into its target, never replacing the link); a symlink loop, a dangling
    symlink, a name too long for the file system (with room for the hidden siblings) or a path that cannot be
    looked up is a :class:`ConfigError` naming ``flag``. Returns the absolute path."""
    where = f"{flag} {path}"
    if "\0" in path:
        raise ConfigError(f"{where!r}: a path cannot hold a NUL character")
    try:
        if os.path.islink(path):
            target = os.path.realpath(path, strict=True)
            if not os.path.isdir(target):
                raise ConfigError(f"{where}: is a symlink to {target}, which is not a directory")
            path = target
        os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            raise ConfigError(f"{where}: is a dangling symlink (to {os.readlink(path)}); remove it or give "
                              "another path") from None
    except OSError as err:
        what = {errno.ELOOP: "a symlink loop", errno.ENAMETOOLONG: "a name too long for the file system"}.get(
            err.errno)
        if what is None:  # e.g. a path under a file: check_out names the file
            return os.path.abspath(path)
        raise ConfigError(f"{where}: {what}") from None
    path = os.path.abspath(path).rstrip(os.sep) or os.sep
    parent, name = os.path.split(path)
    try:
        name_max = os.pathconf(_existing(parent), "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    if len(os.fsencode(name)) + _SIBLING_EXTRA > name_max:
        raise ConfigError(f"{flag}: the name {name[:40]}... is {len(os.fsencode(name))} bytes; at most "
                          f"{name_max - _SIBLING_EXTRA} (the file system's {name_max}, less room for the hidden "
                          "staging sibling)")
    return path


def _existing(path: str) -> str:
    while path and not os.path.exists(path):
        up = os.path.dirname(path)
        if up == path:
            break
        path = up
    return path or os.sep


def check_writable(path: str, flag: str, *, directory: bool) -> None:
    """Refuse, before any work, an output of a command that writes a plain directory (``directory``: ``eval
    --out``, ``export --out``) or one file (``show --video``) where it cannot be written: ConfigError naming
    ``flag`` and ``path`` when ``path`` is a file where a directory is wanted (or a directory where a file is), or
    the nearest existing entry on its way (the directory itself where it exists) is not a directory (a file, a
    dangling link) or not writable. Left alone, the command flew or exported first and failed at its first write."""
    where = f"{flag} {path}"
    if directory and os.path.exists(path) and not os.path.isdir(path):
        raise ConfigError(f"{where}: is an existing file, not a directory; give a new or existing directory")
    if not directory and os.path.isdir(path):
        raise ConfigError(f"{where}: is a directory; give a file name")
    ancestor = os.path.abspath(path) if directory else os.path.dirname(os.path.abspath(path))
    while not os.path.lexists(ancestor):
        ancestor = os.path.dirname(ancestor)
    if os.path.isfile(ancestor):
        raise ConfigError(f"{where}: {ancestor} is a file, not a directory")
    if not os.path.isdir(ancestor):  # a dangling symlink, a FIFO, a device
        raise ConfigError(f"{where}: {ancestor} is not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ConfigError(f"{where}: cannot write in {ancestor} (permission denied)")


# ---- one writer per run directory ------------------------------------------------------------------------------
_PARTIAL = re.compile(r"^\.(?P<name>.+)\.[^.]+\.partial$")


def run_name(path: str) -> str:
    """The run a directory belongs to: ``path`` itself, or, for a hidden staging sibling ``.NAME.<r>.partial``
    (where an ``--overwrite`` run keeps its state), the sibling ``NAME`` it will replace."""
    path = os.path.abspath(path).rstrip(os.sep)
    parent, name = os.path.split(path)
    m = _PARTIAL.match(name)
    return os.path.join(parent, m.group("name")) if m else path


def lock_path(path: str) -> str:
    """The lock file of the run at ``path`` (and of its staging siblings): ``.NAME.lock`` beside it, so that it
    outlives the renames that publish the run."""
    parent, name = os.path.split(run_name(path))
    return os.path.join(parent, f".{name}.lock")


class RunLocked(ConfigError):
    """Another live process writes this run directory."""


@contextlib.contextmanager
def locked(path: str, flag: str = "--out") -> Iterator[None]:
    """Hold the run at ``path`` for this process: an OS lock (``flock``) on :func:`lock_path`, so that a second
    ``jaxrobo train``/``sweep`` on the same directory (or its staging sibling) is refused with
    :class:`RunLocked` naming the first one's pid, and a process killed with ``kill -9`` releases it (the kernel
    drops its locks). Once held, leftover staging directories of the run (``.NAME.*.partial`` of a killed
    publish) that hold no resumable state are removed."""
    lock = lock_path(path)
    os.makedirs(os.path.dirname(lock), exist_ok=True)
    while True:
        # Never through a symlink (the pid would be written into its target), never a FIFO or device.
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o666 & ~_umask())
        except OSError as err:
            if err.errno == errno.ELOOP:
                raise ConfigError(f"{flag} {path}: the lock file {lock} is a symlink (to {os.readlink(lock)}); "
                                  "jaxrobo does not write through it: remove it") from None
            raise
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_nlink > 1:  # a hard link would carry the pid to another file
            os.close(fd)
            raise ConfigError(f"{flag} {path}: the lock file {lock} is not a regular file of its own (a FIFO, "
                              "device or hard link); remove it")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            finally:
                os.close(fd)
            raise RunLocked(_locked_message(f"{flag} {path}", holder)) from None
        # The file may have been unlinked by its last holder between our open and flock: then lock it afresh.
        try:
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        remove_stale_partials(path)
        yield
    finally:
        try:
            os.unlink(lock)
        except OSError:
            pass
        os.close(fd)


def _locked_message(where: str, holder: str) -> str:
    return (f"{where}: another jaxrobo process (pid {holder}) is writing this run directory; wait for it to end or "
            "choose another path")


def lock_holder(path: str) -> str | None:
    """The pid written in the lock file of the run at ``path`` while another process holds it (:func:`locked`),
    else None. Probed with a shared lock dropped at once (called on a refusal's path only: a writer starting in
    that instant would find the run held); this process's own lock (another descriptor of the same file) is not
    taken for another's."""
    try:
        fd = os.open(lock_path(path), os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:
        return None  # no lock file, or one locked() refuses anyway (a symlink)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            return None if holder == str(os.getpid()) else holder
        return None
    finally:
        os.close(fd)  # drops the probe's shared lock


@contextlib.contextmanager
def claimed(path: str, *, overwrite: bool = False, resume: bool = False, flag: str = "--out") -> Iterator[None]:
    """:func:`locked`, then :func:`check_out` again: the directory checked before the lock was taken may have
    been filled by a writer that has since finished."""
    with locked(path, flag):
        check_out(path, overwrite=overwrite, resume=resume, flag=flag)
        yield


def remove_stale_partials(path: str) -> list[str]:
    """Remove the hidden staging siblings ``.NAME.*.partial`` of the run at ``path`` that a killed process left
    (call it holding :func:`locked`); one that holds a resumable state (an ``--overwrite`` run or sweep
    interrupted before it replaced the old one) is kept. Returns the removed paths."""
    name_path = run_name(path)
    parent, name = os.path.split(name_path)
    removed = []
    try:
        entries = os.listdir(parent)
    except OSError:
        return removed
    for entry in entries:
        m = _PARTIAL.match(entry)
        full = os.path.join(parent, entry)
        if (m and m.group("name") == name and full != os.path.abspath(path) and os.path.isdir(full)
                and not os.path.islink(full) and not is_resumable(full)):
            # An old run killed between its swap and the move of the user's entries still holds them: back they go.
            if os.path.isdir(name_path):
                _carry_user_entries(full, name_path)
            if remove_run(full):
                removed.append(full)
    return removed


def _partials(path: str) -> list[str]:
    """The hidden staging siblings ``.NAME.*.partial`` of the run at ``path`` (real directories)."""
    parent, name = os.path.split(run_name(path))
    try:
        entries = os.listdir(parent)
    except OSError:
        return []
    found = []
    for entry in entries:
        m = _PARTIAL.match(entry)
        full = os.path.join(parent, entry)
        if m and m.group("name") == name and os.path.isdir(full) and not os.path.islink(full):
            found.append(full)
    return found


def pending(path: str) -> str | None:
    """The newest interrupted run that is to replace the run at ``path`` (an ``--overwrite`` run stopped before it
    finished keeps its state in a hidden sibling, the old run whole), or None: ``--resume PATH`` goes on with it."""
    waiting = [p for p in _partials(path) if is_resumable(p)]
    return max(waiting, key=lambda p: os.stat(os.path.join(p, CHECKPOINT)).st_mtime_ns) if waiting else None


# ---- staging and publishing ----------------------------------------------------------------------------------
def staging(path: str) -> str:
    """A fresh, empty hidden sibling of ``path`` (``.<name>.<random>.partial``, on the same file system, so that
    :func:`publish` is a rename); the parent is created if missing."""
    path = os.path.abspath(path)
    parent, name = os.path.split(path.rstrip(os.sep))
    os.makedirs(parent, exist_ok=True)
    path = tempfile.mkdtemp(prefix=f".{name}.", suffix=".partial", dir=parent)
    os.chmod(path, 0o777 & ~_umask())  # mkdtemp makes it private; a published run has the usual permissions
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _fsync_dir(path: str) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover - some file systems refuse fsync on directories
        pass
    finally:
        os.close(fd)


def _fsync_tree(path: str) -> None:
    for root, _, files in os.walk(path):
        for name in files:
            try:
                fd = os.open(os.path.join(root, name), os.O_RDONLY)
            except OSError:
                continue
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        _fsync_dir(root)


def _exchange(a: str, b: str) -> bool:
    """Swap two paths in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where unavailable."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = (ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint)
    at_fdcwd, rename_exchange = -100, 2
    return fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


def publish(staging_dir: str, path: str, *, overwrite: bool = False) -> None:
    """Move a finished ``staging_dir`` (from :func:`staging`) to ``path``, its files flushed to disk first.

    A missing or empty ``path`` is replaced by one ``rename``. An existing run is replaced only with
    ``overwrite``: swapped in one step where the OS can (Linux ``renameat2``), else moved aside, the new one
    renamed in and the old one removed (a crash in between leaves the old run as ``.<name>.<random>.old``, never
    a mix of both). Without ``overwrite`` a non-empty ``path`` raises :class:`FileExistsError`."""
    path = os.path.abspath(path).rstrip(os.sep)
    parent = os.path.dirname(path)
    _fsync_tree(staging_dir)
    if not os.path.exists(path) or (os.path.isdir(path) and not os.listdir(path)):
        try:
            os.rename(staging_dir, path)
            _fsync_dir(parent)
            return
        except OSError:
            # Only a run that appeared at ``path`` meanwhile goes on to the overwrite rules below.
            if not (os.path.isdir(path) and os.listdir(path)):
                raise
    if not overwrite:
        raise FileExistsError(f"{path} exists and is not empty; not replacing it")
    if not os.path.isdir(path):
        raise FileExistsError(f"{path} is a file; not replacing it")
    if _exchange(staging_dir, path):
        _fsync_dir(parent)
        _retire(staging_dir, path)  # now the old run
        return
    old = tempfile.mkdtemp(prefix=f".{os.path.basename(path)}.", suffix=".old", dir=parent)
    os.rename(path, os.path.join(old, "run"))
    os.rename(staging_dir, path)
    _fsync_dir(parent)
    _retire(os.path.join(old, "run"), path)
    with contextlib.suppress(OSError):
        os.rmdir(old)


def _retire(old: str, new: str) -> None:
    """The old run ``old`` that ``new`` replaced: the user's entries move into ``new``, jaxrobo's are removed."""
    left = _carry_user_entries(old, new)
    for name, patterns in OWNED_INSIDE.items():  # a user's files inside one of jaxrobo's folders move with it
        inside = os.path.join(old, name)
        if os.path.isdir(inside) and not os.path.islink(inside):
            _remove_owned_inside(inside, patterns)
            if os.path.isdir(inside) and not os.path.lexists(os.path.join(new, name)):
                with contextlib.suppress(OSError):
                    os.rename(inside, os.path.join(new, name))
            if os.path.isdir(inside):
                left.append(name)
    if not remove_run(old):
        print(f"jaxrobo: kept {old}: {', '.join(left)} of the replaced run could not move into {new} (the new run "
              "holds those names)", file=sys.stderr)


def _carry_user_entries(old: str, new: str) -> list[str]:
    """Move the user's entries (not :func:`owned`) of the directory ``old`` into ``new``, where the name is free;
    returns the names left in ``old``."""
    left, moved = [], False
    for name in user_entries(old):
        target = os.path.join(new, name)
        if os.path.lexists(target):
            left.append(name)
            continue
        try:
            os.rename(os.path.join(old, name), target)
            moved = True
        except OSError:
            left.append(name)
    if moved:
        _fsync_dir(new)
    return left


def remove_run(path: str) -> bool:
    """Remove jaxrobo's own entries (:func:`owned`) of the directory ``path``, then the directory if that empties
    it; the user's entries are never removed (nor the directory that holds them). Returns whether it is gone."""
    try:
        names = os.listdir(path)
    except FileNotFoundError:
        return True
    except OSError:
        return False
    for name in names:
        if not owned(name):
            continue
        full = os.path.join(path, name)
        if os.path.isdir(full) and not os.path.islink(full):
            if name in OWNED_INSIDE:  # jaxrobo's entries inside; the directory too if nothing else is left
                _remove_owned_inside(full, OWNED_INSIDE[name])
            else:  # a hidden temporary of jaxrobo's (a staging copy)
                shutil.rmtree(full, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                os.unlink(full)
    try:
        os.rmdir(path)
    except OSError:
        return False
    return True


def _remove_owned_inside(path: str, patterns: tuple[str, ...]) -> None:
    """The files of the directory ``path`` that are jaxrobo's (:func:`owned` by ``patterns``), then the directory
    if that empties it."""
    try:
        names = os.listdir(path)
    except OSError:
        return
    for name in names:
        full = os.path.join(path, name)
        if owned(name, patterns) and (os.path.islink(full) or not os.path.isdir(full)):
            with contextlib.suppress(OSError):
                os.unlink(full)
    with contextlib.suppress(OSError):
        os.rmdir(path)


def discard(staging_dir: str) -> None:
    """Remove a staging (or state) directory that will not be published: jaxrobo's entries, and the directory
    once empty (:func:`remove_run`)."""
    remove_run(staging_dir)


# ---- a run's life: where its state lives, interrupted, published ----------------------------------------------
def live_dir(out: str) -> str:
    """Where a new run (or sweep) keeps its state while it runs: ``out`` itself when it is new or empty (created
    here), so that a hard crash leaves it resumable; else (an old run that ``--overwrite`` replaces, allowed by
    :func:`check_out`) a hidden sibling (:func:`staging`), so that the old run stays whole until the new one
    replaces it."""
    if os.path.isdir(out) and os.listdir(out):
        return staging(out)
    os.makedirs(out, exist_ok=True)
    return out


def interrupted(live: str | None, *, out: str, resume: str, prog: str, what: str, publish_live: bool = False,
                **fields: Any) -> None:
    """Mark the run whose state is in ``live`` interrupted and say how to go on: ``status.json`` becomes
    ``{"status": "interrupted", "out": ..., "resume": resume, **fields}`` (None ``live``: not written, another
    process owns it), and one line goes to stderr: ``"<prog>: <what>; to go on: <resume>"``. A ``live`` staging
    directory (an ``--overwrite`` run) stays where it is, beside the old run, which stays whole: an old run is
    replaced only by a complete one; ``--resume OUT`` finds it there (:func:`pending`). ``publish_live`` moves it
    into place only where ``out`` holds no run (an empty or missing directory)."""
    if live is not None:
        write_status(live, INTERRUPTED, out=os.path.abspath(run_name(out)), resume=resume, **fields)
        if (publish_live and os.path.abspath(live) != os.path.abspath(out)
                and not (os.path.isdir(out) and os.listdir(out))):
            publish(live, out, overwrite=True)
    print(f"{prog}: {what}; to go on: {resume}", file=sys.stderr)


def publish_results(out: str, live: str, write: Callable[[str], None]) -> None:
    """The finished run: ``write(staged)`` fills a fresh staging directory (its ``status.json`` saying
    ``complete`` included), which then replaces ``out`` in one step (``out`` holds this run's own state, or an
    old run that ``--overwrite`` allowed to replace; a resumed hidden sibling ``.NAME.*.partial`` publishes to
    ``NAME``), the user's files in it kept (:func:`publish`); a failure discards it and leaves ``out`` as it was.
    A ``live`` state directory other than ``out``, and the state of earlier interrupted ``--overwrite`` runs of
    ``out`` (superseded by this complete one), are removed afterwards."""
    out = run_name(out)
    staged = staging(out)
    try:
        write(staged)
        _pause_before_publish()
        publish(staged, out, overwrite=True)
    except BaseException:
        discard(staged)
        raise
    if os.path.abspath(live) != os.path.abspath(out):
        discard(live)
    for superseded in _partials(out):
        if is_resumable(superseded):
            discard(superseded)


#: Seconds :func:`publish_results` waits between filling its staging directory and moving it into place, when
#: this environment variable is set: the fault tests kill a process there (``kill -9`` during publishing).
PAUSE_ENV = "JAXROBO_PAUSE_BEFORE_PUBLISH"


def _pause_before_publish() -> None:
    from jaxrobo.core.environ import PAUSE_MAX, env_seconds

    value = env_seconds(PAUSE_ENV, PAUSE_MAX)  # checked by the CLI before the run (jaxrobo.core.environ)
    if value:
        import time

        time.sleep(value)


# ---- atomic single files -------------------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_path(path: str, suffix: str = ".tmp") -> Iterator[str]:
    """A temporary file name beside ``path`` (ending in ``suffix``, for writers that pick a format by it) to write
    into; when the block ends normally it is ``os.replace``-d over ``path`` and the directory ``fsync``-ed, and on
    any error it is removed: a full disk or a crash leaves the old file or none, never a torn one."""
    directory, name = os.path.split(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=suffix, dir=directory)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it private
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    _fsync_dir(directory)


def atomic_write(path: str, writer: Callable[[IO], None], mode: str = "wb") -> None:
    """Write ``path`` through ``writer(file)`` all at once (:func:`atomic_path`), flushed and ``fsync``-ed."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, **({} if "b" in mode else {"newline": ""})) as f:
            writer(f)
            f.flush()
            os.fsync(f.fileno())


def atomic_savefig(fig: Any, path: str, **kwargs: Any) -> None:
    """``fig.savefig(path, **kwargs)`` through :func:`atomic_write`: a full disk or a crash leaves the old image
    or none, never a 0-byte or torn one."""
    fmt = os.path.splitext(path)[1].lstrip(".").lower() or None
    atomic_write(path, lambda f: fig.savefig(f, format=fmt, **kwargs))


def atomic_write_json(path: str, obj: Any) -> None:
    atomic_write(path, lambda f: f.write(json.dumps(obj, indent=2) + "\n"), mode="w")


def atomic_savez(path: str, **arrays: Any) -> None:
    """An uncompressed ``.npz`` (``np.savez``'s layout, no pickled objects) written atomically."""
    from jaxrobo.io.npz import write_npz_deflated

    atomic_write(path, lambda f: write_npz_deflated(f, compress=False, **arrays))
