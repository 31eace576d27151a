"""Output files: written under a temporary name in the same directory, then renamed into place (atomic, together)."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator

from matfit.errors import OutputError

PREFIX = ".matfit-"


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
    handle, temporary = tempfile.mkstemp(prefix=PREFIX, suffix=os.path.splitext(path)[1], dir=directory)
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


class Batch:
    """Several outputs of one command, written under temporary names and renamed into place together at the end.

    `path(final)` gives the temporary path to write `final` to; `commit()` renames every one of
    them, only once all were written; whatever was not committed is removed by `discard()`. So an
    error or Ctrl-C while writing any of them leaves none of them behind (`together()` does both).
    """

    def __init__(self):
        self.pending: list[tuple[str, str]] = []

    def path(self, final: str) -> str:
        """Returns a new temporary path beside `final`, to be renamed onto it by `commit`."""
        check_writable(final)
        handle, temporary = tempfile.mkstemp(prefix=PREFIX, suffix=os.path.splitext(final)[1], dir=os.path.dirname(os.path.abspath(final)))
        os.close(handle)
        self.pending.append((temporary, final))
        return temporary

    def commit(self) -> None:
        """Renames every temporary file onto its final path."""
        umask = os.umask(0)
        os.umask(umask)
        for temporary, final in self.pending:
            os.chmod(temporary, 0o666 & ~umask)
            os.replace(temporary, final)
        self.pending = []

    def discard(self) -> None:
        """Removes the temporary files not committed."""
        for temporary, _ in self.pending:
            if os.path.exists(temporary):
                os.unlink(temporary)
        self.pending = []


@contextlib.contextmanager
def together() -> Iterator[Batch]:
    """Yields a Batch; commits it if the block succeeds, discards it in any case."""
    batch = Batch()
    try:
        yield batch
        batch.commit()
    finally:
        batch.discard()
