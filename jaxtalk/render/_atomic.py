"""Atomic file output: write to a temporary file in the target directory, then rename over the target.

A crash or an error half-way (a NaN frame, ffmpeg failing) never leaves a truncated file at the
target path, and readers never see a partly written one (``os.replace`` is atomic on one filesystem).
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_output", "check_output_path"]


def check_output_path(path: str | os.PathLike, suffixes: tuple[str, ...]) -> Path:
    """Validate an output path before any work is done.

    Args:
        path: the file to write.
        suffixes: accepted lower-case suffixes, e.g. ``(".mp4",)``.

    Returns:
        The path as a ``Path``.

    Raises:
        ValueError: for a wrong suffix or a path that is an existing directory.
        FileNotFoundError: if the parent directory does not exist.
        NotADirectoryError: if the parent is not a directory.
        PermissionError: if the parent directory is not writable.
    """
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise ValueError(f"output path {str(path)!r} must end in one of {suffixes}")
    if path.is_dir():
        raise ValueError(f"output path {str(path)!r} is a directory")
    parent = path.parent
    if not parent.exists():
        raise FileNotFoundError(f"cannot write {str(path)!r}: directory {str(parent)!r} does not exist")
    if not parent.is_dir():
        raise NotADirectoryError(f"cannot write {str(path)!r}: {str(parent)!r} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PermissionError(f"cannot write {str(path)!r}: directory {str(parent)!r} is not writable")
    return path


@contextlib.contextmanager
def atomic_output(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix); on success rename it to ``path``.

    On an exception the temporary file is removed and ``path`` is left untouched.
    """
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
