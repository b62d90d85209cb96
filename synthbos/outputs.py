"""Output files and folders: checked before any work starts, written atomically, locked while in use.

Every output of the project goes through these helpers, so that an error a user can cause (a full
disk, a read-only file system, a folder without write permission, an output that would overwrite
the input) gives one ``SynthbosError`` naming the path, and never a partial file:

``check_output_file(path, inputs=...)``
    Before the work: the folder exists and is writable, the path is not a folder and is not one of
    the inputs.
``check_output_folder(path)`` / ``make_folder(path)``
    The same for a campaign, sweep or regression folder (it may not exist yet).
``atomic_output(path)``
    Yields a temporary name beside ``path`` (a hidden ``.name.XXXX.tmp``); the file is renamed to
    ``path`` only once complete, and removed on any error. An ``OSError`` of the disk (no space,
    quota, read-only, permission, I/O error) becomes a ``SynthbosError``. The file gets the user's
    umask.
``atomic_hdf5(path)``
    Yields an ``h5py.File`` built in memory; its bytes are written with ordinary ``write`` calls
    through ``atomic_output``. (The HDF5 library itself does not fail cleanly on a full disk.)
``folder_lock(folder)``
    An exclusive ``flock`` on ``folder/.lock`` for a campaign's life: a second campaign into the
    same folder is refused at once, or waits with ``wait=True``.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import io
import os
import re
import tempfile
import time
from glob import escape as glob_escape
from pathlib import Path

from .errors import SynthbosError

__all__ = [
    "atomic_hdf5",
    "atomic_output",
    "check_output_file",
    "check_output_folder",
    "disk_error",
    "folder_lock",
    "make_folder",
    "write_bytes",
]

# Errors of the file system that a user causes (or can fix): reported as one line.
_DISK_ERRNOS = {
    errno.ENOSPC,
    errno.EDQUOT,
    errno.EROFS,
    errno.EACCES,
    errno.EPERM,
    errno.EFBIG,
    errno.EIO,
    errno.ENAMETOOLONG,
    errno.ENOTDIR,
    errno.EISDIR,
    errno.ENOENT,
    errno.EEXIST,
}


def disk_error(err: OSError, path) -> SynthbosError | None:
    """The one-line ``SynthbosError`` for a file-system error while writing ``path`` (None: not one)."""
    if err.errno not in _DISK_ERRNOS:
        return None
    reason = os.strerror(err.errno)
    other = err.filename
    if other is not None and Path(str(other)).name.startswith(".") and str(other).endswith(".tmp"):
        other = None  # our own temporary file: name the output
    if other is not None and Path(str(other)) != Path(path):
        return SynthbosError(f"{other}: {reason} (while writing {path})")
    return SynthbosError(f"cannot write {path}: {reason}")


_MAX_PATH = 4096  # Linux's PATH_MAX


def _writable(folder: Path) -> bool:
    return os.access(folder, os.W_OK | os.X_OK)


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return a.resolve() == b.resolve()


def check_output_file(path, *, inputs=(), what="output") -> Path:
    """Check, before any work, that ``path`` can be written as a new file.

    Parameters
    ----------
    path : str or Path
        The file to write.
    inputs : iterable of str or Path
        Files the same command reads; writing over one of them is refused.
    what : str
        How to name the path in messages (an option such as ``-o``).

    Returns
    -------
    Path

    Raises
    ------
    SynthbosError
        The path is empty or a folder, its folder does not exist or is not writable (permissions or a
        read-only file system), or it is one of ``inputs``.
    """
    if path is None or str(path) == "":
        raise SynthbosError(f"{what}: no file name given")
    if len(str(path)) > _MAX_PATH or "\0" in str(path):
        raise SynthbosError(f"{what}: a path of at most {_MAX_PATH} characters without NUL, got "
                            f"{len(str(path)):,} characters")
    if str(path).endswith(("/", os.sep)):  # Path() drops the slash and would write a file of that name
        raise SynthbosError(f"{what} {path} names a folder; name a file to write")
    path = Path(path)
    if path.is_dir():
        raise SynthbosError(f"{what} {path} is a folder; name a file to write")
    folder = path.parent
    if not folder.exists():
        raise SynthbosError(f"{what} {path}: folder {folder} does not exist")
    if not folder.is_dir():
        raise SynthbosError(f"{what} {path}: {folder} is a file, not a folder")
    if not _writable(folder):
        raise SynthbosError(f"{what} {path}: cannot write in folder {folder} (read-only or no permission)")
    if path.exists() and not os.access(path, os.W_OK):
        raise SynthbosError(f"{what} {path} exists and is read-only")
    for other in inputs:
        if other is not None and str(other) != "" and _same_file(path, Path(other)):
            raise SynthbosError(f"{what} {path} is also an input ({other}); choose another output name")
    return path


def check_output_folder(path, *, what="--out") -> Path:
    """Check, before any work, that ``path`` is a writable folder or can be created as one.

    Raises
    ------
    SynthbosError
        The path names a file, lies under a file, or its nearest existing folder is not writable.
    """
    if path is None or str(path) == "":
        raise SynthbosError(f"{what}: no folder given")
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise SynthbosError(f"{what} {path} is a file, not a folder")
        if not _writable(path):
            raise SynthbosError(f"{what} {path}: cannot write in this folder (read-only or no permission)")
        return path
    parent = path.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise SynthbosError(f"{what} {path}: {parent} is a file, so no folder can be made under it")
    if not _writable(parent):
        raise SynthbosError(f"{what} {path}: cannot create it in {parent} (read-only or no permission)")
    return path


def make_folder(path, *, what="--out") -> Path:
    """``check_output_folder`` and create it (with its parents); file-system errors as one line."""
    path = check_output_folder(path, what=what)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        e = disk_error(err, path)
        if e is None:
            raise
        raise SynthbosError(f"{what} {path}: cannot create the folder ({os.strerror(err.errno)})") from None
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_TMP_TAIL = re.compile(r"(\d+)\.[A-Za-z0-9_]{8}\.tmp")


def _remove_orphans(path: Path) -> None:
    """Remove temporaries of ``path`` left by writers that were killed (their process no longer exists)."""
    for tmp in path.parent.glob(f".{glob_escape(path.name)}.*.tmp"):
        m = _TMP_TAIL.fullmatch(tmp.name[len(path.name) + 2:])  # "{pid}.{mkstemp's 8 characters}.tmp"
        if m is None:
            continue
        pid = m.group(1)
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except OSError:  # the process exists (another user's): leave its file
            pass


@contextlib.contextmanager
def atomic_output(path):
    """Yield a temporary path beside ``path``; on success rename it to ``path``, on any error remove it.

    Every output file of the project is written this way, so an interrupted or failed run never leaves
    a partial file under the final name. A full disk, a read-only file system or a missing permission
    raises ``SynthbosError`` (and leaves no temporary file). The temporary name carries the writer's
    process id, so the next write of ``path`` removes what a killed writer (SIGKILL) left.
    """
    path = Path(path)
    folder = path.parent
    if not folder.is_dir():
        raise SynthbosError(f"output folder {folder} does not exist")
    if path.is_dir():
        raise SynthbosError(f"output {path} is a folder; name a file to write")
    _remove_orphans(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp", dir=folder)
    except OSError as err:
        e = disk_error(err, path)
        if e is None:
            raise
        raise e from None
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        e = disk_error(err, path)
        if e is None:
            raise
        raise e from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically with plain ``write`` calls (errors as ``atomic_output``)."""
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        view = memoryview(data)
        while view:
            n = f.write(view)
            view = view[n:]
        f.flush()
        os.fsync(f.fileno())
    return Path(path)


@contextlib.contextmanager
def atomic_hdf5(path):
    """Yield a writable ``h5py.File`` held in memory; on success its bytes are written to ``path``.

    HDF5 writing straight onto a full disk can crash the process inside the HDF5 library; building
    the file in memory and writing the bytes with ``write`` turns a full disk into a clean
    ``SynthbosError`` and no file.
    """
    import h5py

    path = Path(path)
    if not path.parent.is_dir():
        raise SynthbosError(f"output folder {path.parent} does not exist")
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as f:
        yield f
    write_bytes(path, buffer.getvalue())


@contextlib.contextmanager
def folder_lock(folder, *, wait=False, poll_s=0.5, what="campaign folder"):
    """Hold an exclusive lock on ``folder/.lock`` for the life of the ``with`` block.

    Parameters
    ----------
    folder : str or Path
        An existing folder.
    wait : bool
        Wait for the lock (polling every ``poll_s`` seconds) instead of refusing at once.

    Raises
    ------
    SynthbosError
        Another process holds the lock and ``wait`` is False, or the lock file cannot be made.

    Notes
    -----
    ``flock`` locks belong to the open file: the operating system releases them when the holder
    exits, even by SIGKILL, so a stale lock file never blocks a later run. A run that ends removes the
    lock file (one killed leaves it, unlocked).
    """
    folder = Path(folder)
    lock = folder / ".lock"
    fd = _locked_file(lock, folder, wait=wait, poll_s=poll_s, what=what)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"process {os.getpid()}\n".encode(), 0)
        yield lock
    finally:
        with contextlib.suppress(OSError):  # the lock file goes with the run (still locked: no one else has it)
            lock.unlink()
        os.close(fd)


def _locked_file(lock: Path, folder: Path, *, wait, poll_s, what) -> int:
    """Open ``lock`` and take its ``flock``; the descriptor. The file is removed when a run ends, so a lock
    taken on a file that has since been removed (or replaced) is let go and taken again on the new one."""
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as err:
            e = disk_error(err, lock)
            if e is None:
                raise
            raise e from None
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if not wait:
                        holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "another process"
                        raise SynthbosError(
                            f"{what} {folder} is in use by {holder}; wait for it to finish or add --wait"
                        ) from None
                    time.sleep(poll_s)
            try:
                same = os.fstat(fd).st_ino == os.stat(lock).st_ino
            except FileNotFoundError:
                same = False
        except BaseException:
            os.close(fd)
            raise
        if same:
            return fd
        os.close(fd)
