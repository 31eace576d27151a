"""Atomic output files: written under a temporary name in the same directory, then renamed."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator


class OutputError(ValueError):
    """An output path cannot be written; the message names the path and the fix."""


def check_writable(path: str) -> None:
    """Raises OutputError unless a file can be created at `path`."""
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise OutputError(f"cannot write {path}: directory {directory} does not exist (create it first)")
    if os.path.isdir(path):
        raise OutputError(f"cannot write {path}: it is a directory (give a file name)")
    try:  # a real probe: os.access says yes to root even on read-only directories
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError:
        raise OutputError(f"cannot write {path}: directory {directory} is read-only (choose another output path)") from None


@contextlib.contextmanager
def atomic_path(path: str) -> Iterator[str]:
    """Yields a temporary path beside `path`; renames it onto `path` only if the block succeeds.

    A failure or interruption inside the block leaves no partial file behind, and an existing
    file at `path` untouched.
    """
    check_writable(path)
    directory = os.path.dirname(os.path.abspath(path))
    handle, temporary = tempfile.mkstemp(prefix=".matfit-", suffix=os.path.splitext(path)[1], dir=directory)
    os.close(handle)
    try:
        yield temporary
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


def write_text(path: str, text: str) -> None:
    """Writes a text file atomically."""
    with atomic_path(path) as temporary, open(temporary, "w") as file:
        file.write(text)


def write_bytes(path: str, data: bytes) -> None:
    """Writes a binary file atomically."""
    with atomic_path(path) as temporary, open(temporary, "wb") as file:
        file.write(data)
