"""Writing files a user keeps: one atomic writer and one rule for what a command may replace; and the
one reader of the ``.npz`` / ``.npy`` arrays a user gives (:func:`load_npz`, :func:`load_npy`: nothing
unpickled, one-line errors).

Atomic: every file jaxtalk writes goes to a temporary file in the target's folder (a unique name, so
concurrent writers never share one), then ``os.replace`` puts it in place. An interrupted or failing
write leaves the old file or the new one, never a half-written one, and readers never see a mix.

What may be replaced (checked by :func:`claim_outputs` before a command does any work):

* a command never writes over one of its own inputs, whatever the options (paths compared resolved);
* a path the user named (``--out``) may replace an existing file, the usual convention;
* a name the command picks itself (a default output name, a side file such as the audio beside a
  ``.glb``, a report) never replaces an existing file unless the user passes ``--overwrite``;
* an output path that is a folder, or whose parent is a file, is refused before any work;
* an output inside a folder the command reads (a run folder, an encoder folder) is one of its inputs.

A command that writes a whole folder (:func:`claim_folder`) replaces an existing one only with
``--overwrite``, only when everything in it is a previous output of the same command, and never when
it holds one of the command's inputs or the current working folder.

Missing parent folders are created when the file is written.

One writer per folder: a command that keeps writing into a folder for a long time (a training run)
holds :func:`folder_lock` on it; a second writer is refused with one line naming the process. The
lock is the operating system's (``flock``), so it ends with its process however that ends: a lock
left by a killed process is taken over, with no guess about whether its process id still runs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import uuid
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "load_npz",
    "load_npy",
    "Output",
    "OutputError",
    "atomic_output",
    "atomic_write_text",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_savez",
    "atomic_save_npy",
    "atomic_copy",
    "check_output_path",
    "claim_folder",
    "claim_outputs",
    "FolderInUseError",
    "LOCK_FILE",
    "folder_lock",
]


class OutputError(ValueError):
    """An output path a command must not write: an input, an existing file it may not replace, a
    folder, or a path under a file. Raised before any work is done."""


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix); on success rename it onto ``path``.

    The parent folder is created if missing. On an exception the temporary file is removed and
    ``path`` is left as it was. The temporary name is unique per call, so concurrent writers of the
    same target never write into one file (the last rename wins, whole).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any, *, indent: int | None = 1) -> Path:
    """Write ``obj`` as JSON to ``path`` atomically (values JSON cannot hold are written with ``str``)."""
    return atomic_write_text(path, json.dumps(obj, indent=indent, default=str))


def atomic_savez(path: str | os.PathLike, **arrays: Any) -> Path:
    """``np.savez`` to ``path`` atomically (the name is kept exactly: no ``.npz`` is appended)."""
    with atomic_output(path) as tmp, open(tmp, "wb") as handle:
        np.savez(handle, **arrays)
    return Path(path)


def atomic_save_npy(path: str | os.PathLike, array: Any) -> Path:
    """``np.save`` to ``path`` atomically (the name is kept exactly: no ``.npy`` is appended)."""
    with atomic_output(path) as tmp, open(tmp, "wb") as handle:
        np.save(handle, np.asarray(array))
    return Path(path)


def atomic_copy(src: str | os.PathLike, dst: str | os.PathLike) -> Path:
    """Copy the file ``src`` to ``dst`` atomically."""
    import shutil

    with atomic_output(dst) as tmp:
        shutil.copyfile(src, tmp)
    return Path(dst)


def check_output_path(path: str | os.PathLike, suffixes: Sequence[str] | None = None) -> Path:
    """Check that a file can be written at ``path``, before any work is done.

    Args:
        path: the file to write.
        suffixes: accepted lower-case suffixes, e.g. ``(".mp4",)``; None accepts any.

    Returns:
        The path as a ``Path``.

    Raises:
        OutputError: a wrong suffix, a path that is a folder, or a parent that is a file.
        PermissionError: the nearest existing parent folder is not writable.
    """
    path = Path(path)
    if suffixes is not None and path.suffix.lower() not in tuple(suffixes):
        raise OutputError(f"output path {str(path)!r} must end in {' or '.join(suffixes)}")
    if path.is_dir():
        raise OutputError(f"output path {str(path)!r} is a folder; give a file name")
    # Missing folders are created on writing; the nearest existing ancestor must be a writable folder.
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"cannot write {str(path)!r}: {str(parent)!r} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PermissionError(f"cannot write {str(path)!r}: folder {str(parent)!r} is not writable")
    return path


@dataclasses.dataclass(frozen=True)
class Output:
    """A file a command is about to write.

    Attributes:
        path: where.
        named: True when the user named this path (``--out``): an existing file there may be
            replaced. False for names the command picks itself and for side files.
        suffixes: accepted suffixes (None: any).
    """

    path: Path
    named: bool = False
    suffixes: tuple[str, ...] | None = None


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and os.path.samefile(a, b))
    except OSError:
        return False


def _inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` is ``folder`` or lies under it (links resolved)."""
    try:
        return path.resolve().is_relative_to(folder.resolve())
    except OSError:
        return False


def _input_clash(path: Path, src: Path) -> str | None:
    """Why ``path`` may not be written, as an output, given the input ``src`` (None: it may)."""
    if _same_file(path, src):
        return f"{str(path)!r} is an input of this command; it would be overwritten: choose another output name"
    if src.is_dir() and _inside(path, src):
        return (f"{str(path)!r} is an input of this command (it is inside {str(src)!r}, which the command reads); "
                "it would be overwritten: choose another output name")
    return None


def claim_outputs(
    outputs: Iterable[Output],
    inputs: Iterable[str | os.PathLike | None] = (),
    *,
    overwrite: bool = False,
) -> list[Path]:
    """Check, before any work, that a command may write every one of ``outputs``.

    Args:
        outputs: the files the command will write.
        inputs: the files and folders it reads (None entries are skipped); no output may be one of
            them or lie inside one of the folders (every file of a run folder is an input of every
            command that reads the run).
        overwrite: the user passed ``--overwrite``: names the command picks may replace files.

    Returns:
        The output paths, in order.

    Raises:
        OutputError: an output that is an input (whatever ``overwrite`` says), an existing file under
            a name the command picked (without ``overwrite``), two outputs at one path, a folder, or a
            path under a file. The message names the file and the option that would allow it.
        PermissionError: a folder that cannot be written.
    """
    inputs = [Path(p) for p in inputs if p is not None]
    claimed: list[Path] = []
    for out in outputs:
        path = check_output_path(out.path, out.suffixes)
        for src in inputs:
            if (why := _input_clash(path, src)) is not None:
                raise OutputError(why)
        for other in claimed:
            if _same_file(path, other):
                raise OutputError(f"two outputs of this command are both {str(path)!r}; choose another output name")
        if path.exists() and not out.named and not overwrite:
            raise OutputError(f"{str(path)!r} exists; pass --overwrite to replace it (or --out to choose another name)")
        claimed.append(path)
    return claimed


def claim_folder(
    folder: str | os.PathLike,
    inputs: Iterable[str | os.PathLike | None] = (),
    *,
    ours: Iterable[str],
    previous_output: bool,
    overwrite: bool = False,
    option: str = "--out",
) -> Path:
    """Check, before any work, that a command may write the whole folder ``folder`` (replacing it).

    A folder is never replaced when it holds the current working folder or one of the command's
    inputs, whatever ``overwrite`` says. An existing non-empty folder is replaced only with
    ``overwrite`` and only when it is a previous output of the same command (``previous_output``)
    holding nothing but the names the command writes (``ours``): a user's file beside them is kept
    by refusing.

    Args:
        folder: the folder the command writes.
        inputs: the files and folders the command reads (None entries are skipped).
        ours: the names (files or folders) the command writes directly inside ``folder``.
        previous_output: whether ``folder`` holds this command's record (e.g. its ``run.json``).
        overwrite: the user passed ``--overwrite``.
        option: the option that named the folder, for the messages.

    Returns:
        ``folder`` as a ``Path``.

    Raises:
        OutputError: any of the cases above, naming the folder and what is in the way.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{option} {str(folder)!r} is a file, not a folder")
    if _inside(Path.cwd(), folder):
        raise OutputError(f"{option} {str(folder)!r} is the current folder or holds it; it would be replaced: "
                          "name a new folder")
    for src in (Path(p) for p in inputs if p is not None):
        if _inside(src, folder):
            raise OutputError(f"{option} {str(folder)!r} holds {str(src)!r}, an input of this command; it would be "
                              f"lost when the folder is replaced: choose another {option}")
    entries = sorted(p.name for p in folder.iterdir()) if folder.is_dir() else []
    if not entries:
        return folder
    if not overwrite:
        raise OutputError(f"{option} {str(folder)!r} exists and is not empty; pass --overwrite to replace it")
    foreign = [name for name in entries if name not in set(ours)]
    if not previous_output or foreign:
        shown = ", ".join(foreign[:5] or entries[:5]) + (" ..." if len(foreign or entries) > 5 else "")
        raise OutputError(f"{option} {str(folder)!r} holds files this command did not write ({shown}); "
                          f"--overwrite replaces only its own previous output: choose another {option}")
    return folder


LOCK_FILE = ".jaxtalk.lock"

# Folders this process holds, with their nesting count: the command and the training loop below it
# both take the lock on a run folder, and the inner one must not refuse its own process.
_HELD: dict[Path, list[Any]] = {}


class FolderInUseError(OutputError):
    """A folder another process is writing (it holds the folder's lock)."""


def _lock_owner(lock: Path) -> str:
    """Who holds ``lock``, as its holder recorded it (best effort: it may be mid-write)."""
    try:
        info = json.loads(lock.read_text())
        return f"process {info['pid']} on {info['host']} ({info['command']}, since {info['since']})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Hold the write lock of ``folder`` (created if missing) for the ``with`` block.

    Re-entrant within one process. The lock file (:data:`LOCK_FILE`) holds the holder's process
    id, host, command and start time, for the message a second writer gets; it is removed on
    release, and a folder this call created is removed again if it is still empty.

    Raises:
        FolderInUseError: another process holds the lock (the message names it).
    """
    import fcntl
    import platform
    import sys
    import time

    folder = Path(folder)
    key = folder.resolve()
    if key in _HELD:
        _HELD[key][1] += 1
        try:
            yield folder
        finally:
            _HELD[key][1] -= 1
        return
    created = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / LOCK_FILE
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise FolderInUseError(f"{str(folder)!r} is in use by {_lock_owner(lock)}: wait for it to finish, or "
                                   "choose another folder") from None
        # The holder before us may have removed the file between our open and our lock: then the lock
        # we hold is on a file no one else will open, so try again on the current one.
        try:
            if os.stat(lock).st_ino == os.fstat(fd).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    info = {"pid": os.getpid(), "host": platform.node(), "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])[:200],
            "since": time.strftime("%Y-%m-%d %H:%M:%S")}
    os.ftruncate(fd, 0)
    os.write(fd, json.dumps(info).encode())
    _HELD[key] = [fd, 1]
    try:
        yield folder
    finally:
        del _HELD[key]
        with contextlib.suppress(FileNotFoundError):
            lock.unlink()  # while still locked, so no one locks the file being removed
        os.close(fd)
        if created:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only if still empty


# ---- reading the arrays a user gives ----------------------------------------------------------------
def _stored_dtype(handle) -> np.dtype | None:
    """The dtype a NumPy array file's header declares, or None when the bytes are not one.

    Only the header is read: what follows is never parsed, so nothing is unpickled.
    """
    from numpy.lib import format as npy_format

    try:
        version = npy_format.read_magic(handle)
        # Versions 2.0 and 3.0 differ from 1.0 in the header length's width only (3.0 also allows
        # UTF-8 field names, which the 2.0 reader decodes as latin-1: the dtype's kind is the same).
        header = npy_format.read_array_header_1_0 if version == (1, 0) else npy_format.read_array_header_2_0
        return header(handle)[2]
    except (ValueError, EOFError, OSError, SyntaxError, TypeError):
        return None


def _object_arrays(path: Path, keys: list[str] | None = None) -> ValueError:
    """The error for object arrays (of an ``.npz``'s ``keys``; None: an ``.npy``'s one array)."""
    # Object arrays are pickles, which can run code when read: jaxtalk reads numbers only, whoever
    # wrote the file.
    if keys is None:
        return ValueError(f"{str(path)!r} holds an object array, which jaxtalk never reads: save a plain numeric "
                          "array")
    names = ", ".join(repr(k) for k in keys)
    return ValueError(f"{str(path)!r} holds object arrays ({names}), which jaxtalk never reads: save plain "
                      "numeric arrays")


def load_npz(path: str | os.PathLike, *, what: str = "file") -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file, read without unpickling anything.

    The one reader of the ``.npz`` files a user gives jaxtalk: whatever is wrong with one, the error is
    one line that names the file and the problem.

    Args:
        path: the ``.npz``.
        what: what the file is, for the message of a missing one (``"motion file"``).

    Returns:
        ``{name: array}`` in the file's order.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a zip archive, a member that is not a NumPy array, object (pickled) arrays, or
            a damaged file.
    """
    import zipfile
    import zlib

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {str(path)!r}")
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{str(path)!r} is not an .npz file (not a zip archive)")
    damaged = (zipfile.BadZipFile, zlib.error, EOFError, OSError)
    objects = []
    try:
        with zipfile.ZipFile(path) as archive:
            for member in archive.namelist():
                if member.endswith("/"):
                    continue
                with archive.open(member) as handle:
                    dtype = _stored_dtype(handle)
                if dtype is None:
                    raise ValueError(f"{str(path)!r} is not an .npz file: its member {member!r} is not a NumPy array")
                if dtype.hasobject:
                    objects.append(member.removesuffix(".npy"))
    except damaged as err:
        raise ValueError(f"{str(path)!r} is a damaged .npz file ({err})") from None
    if objects:
        raise _object_arrays(path, objects)
    try:  # every header is a plain array's: what fails now is the data (a truncated or corrupted file)
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (ValueError, *damaged) as err:
        raise ValueError(f"{str(path)!r} is a damaged .npz file ({err})") from None


def load_npy(path: str | os.PathLike, *, what: str = "file", mmap: bool = False) -> np.ndarray:
    """The array of an ``.npy`` file, read without unpickling anything, by :func:`load_npz`'s rules.

    Args:
        path: the ``.npy``.
        what: what the file is, for the message of a missing one (``"vertex sequence"``).
        mmap: map the file read-only instead of reading it (a long sequence is then read a window at a
            time as it is used).

    Returns:
        The array.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a NumPy array file, an object (pickled) array, or a damaged file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {str(path)!r}")
    try:
        with open(path, "rb") as handle:
            dtype = _stored_dtype(handle)
    except OSError as err:
        raise ValueError(f"cannot read {str(path)!r} ({err})") from None
    if dtype is None:
        raise ValueError(f"{str(path)!r} is not a NumPy .npy file")
    if dtype.hasobject:
        raise _object_arrays(path)
    try:
        return np.load(path, allow_pickle=False, mmap_mode="r" if mmap else None)
    except (ValueError, EOFError, OSError) as err:
        raise ValueError(f"{str(path)!r} is a damaged .npy file ({err})") from None
