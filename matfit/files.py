"""Output files: written under a temporary name beside them, verified, then renamed into place (atomic, together).

A write either completes or fails with an OutputError (a full disk, a quota, a size limit): the
bytes are written, flushed to the disk (`fsync`, where a delayed allocation failure would show) and
their size checked before the rename, and no temporary file survives a failure. Temporary files
are registered with `interrupt`, which removes them when an interruption ends the process at once.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
from collections.abc import Iterator

from matfit import interrupt
from matfit.errors import OutputError

PREFIX = ".matfit-"
_finals: dict[str, str] = {}  # a Batch's temporary path -> the output it stands for, for messages


def final_name(path: str) -> str:
    """Returns the output a temporary path of a Batch stands for (messages name that), else the path itself."""
    return _finals.get(path, path)


def sha256(path: str) -> str:
    """Returns the SHA-256 of a file's bytes (what a result records of the picture it was computed from)."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


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
        raise OutputError(
            f"cannot write {path}: directory {directory} is read-only (choose another output path)"
        ) from None


@contextlib.contextmanager
def atomic_path(path: str) -> Iterator[str]:
    """Yields a temporary path beside `path`; renames it onto `path` only if the block succeeds.

    A failure or interruption inside the block leaves no partial file behind, and an existing
    file at `path` untouched.
    """
    check_writable(path)
    temporary = temporary_beside(path)
    try:
        yield temporary
        os.chmod(temporary, 0o666 & ~current_umask())
        os.replace(temporary, path)
    finally:
        remove(temporary)


def temporary_beside(path: str) -> str:
    """Returns a new empty temporary file in the directory of `path`, registered for removal on interruption."""
    directory = os.path.dirname(os.path.abspath(path))
    try:
        handle, temporary = tempfile.mkstemp(prefix=PREFIX, suffix=os.path.splitext(path)[1], dir=directory)
    except OSError as error:
        raise OutputError(f"cannot write {final_name(path)}: {error.strerror}") from None
    interrupt.register(temporary)
    os.close(handle)
    return temporary


def remove(temporary: str) -> None:
    """Removes a temporary file if it is still there."""
    if os.path.lexists(temporary):
        os.unlink(temporary)
    interrupt.unregister(temporary)


def current_umask() -> int:
    """Returns the process's umask (which can only be read by setting it)."""
    umask = os.umask(0)
    os.umask(umask)
    return umask


def fill(temporary: str, data: bytes, path: str) -> None:
    """Writes `data` into the file `temporary` (standing for `path`), flushed to the disk and its size checked.

    Raises OutputError, naming `path` (or the output it stands for), when the disk is full or the write fails otherwise.
    """
    path = final_name(path)
    try:
        with open(temporary, "wb") as file:
            file.write(data)
            file.flush()
            os.fsync(file.fileno())
            written = os.fstat(file.fileno()).st_size
    except OSError as error:
        raise OutputError(f"cannot write {path}: {error.strerror or error}") from None
    if written != len(data):
        raise OutputError(f"cannot write {path}: only {written} of {len(data)} bytes reached the disk")


def write_text(path: str, text: str) -> None:
    """Writes a text file (UTF-8) atomically."""
    write_bytes(path, text.encode("utf-8", "surrogateescape"))  # file names that are not UTF-8 keep their bytes


def write_bytes(path: str, data: bytes) -> None:
    """Writes a binary file atomically: complete and verified, or not at all."""
    with atomic_path(path) as temporary:
        fill(temporary, data, path)


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
        temporary = temporary_beside(final)
        self.pending.append((temporary, final))
        _finals[temporary] = final
        return temporary

    def commit(self) -> None:
        """Renames every temporary file onto its final path."""
        umask = current_umask()
        for temporary, final in self.pending:
            os.chmod(temporary, 0o666 & ~umask)
            os.replace(temporary, final)
            interrupt.unregister(temporary)
            _finals.pop(temporary, None)
        self.pending = []

    def discard(self) -> None:
        """Removes the temporary files not committed."""
        for temporary, _ in self.pending:
            remove(temporary)
            _finals.pop(temporary, None)
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
