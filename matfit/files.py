"""Files: inputs opened without blocking and only when regular; outputs written under a temporary name beside them,
verified, then renamed into place (atomic, together).

Every file matfit reads itself is opened with O_NONBLOCK and checked, on the open descriptor, to be a
regular file before a byte is read (`open_input`, `read_input`): a FIFO or a device planted where a file
is expected (`mkfifo params.json`, `--init /dev/zero`) is a one-line error, never a read that blocks or
never ends; a path a library opens by name (OpenImageIO, NumPy's memory maps) is checked the same way first
(`check_input`).

A write either completes or fails with an OutputError (a full disk, a quota, a size limit): the
bytes are written, flushed to the disk (`fsync`, where a delayed allocation failure would show) and
their size checked before the rename, and no temporary file survives a failure. Temporary files
are registered with `interrupt`, which removes them when an interruption ends the process at once;
one left by a process killed outright (`kill -9`) is named after its owner
(`.matfit-<pid>@<host>-...`) and removed by the next write beside it once that process is gone.

Before any work, a command checks all its outputs together (`check_outputs`): each can be written,
its name (and its temporary's) fits the folder, no two are the same file and none is one of the
command's inputs, compared as files on the disk (symbolic and hard links included), not as text.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import socket
import stat
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from typing import BinaryIO

from matfit import interrupt, shipped
from matfit.errors import OutputError

PREFIX = ".matfit-"
RANDOM_LETTERS = 8  # what `tempfile.mkstemp` adds between the prefix and the suffix
DEFAULT_NAME_MAX = 255  # where the folder's file system does not say (the limit of ext4, XFS, APFS, NTFS)
_OWNED = re.compile(re.escape(PREFIX) + r"(\d+)@")
_finals: dict[str, str] = {}  # a Batch's temporary path -> the output it stands for, for messages
_swept: set[str] = set()  # folders whose stale temporaries this process removed already


def final_name(path: str) -> str:
    """Returns the output a temporary path of a Batch stands for (messages name that), else the path itself."""
    return _finals.get(path, path)


def sha256(path: str) -> str:
    """Returns the SHA-256 of a file's bytes (what a result records of the picture it was computed from)."""
    digest = hashlib.sha256()
    with open_input(path) as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def kind(mode: int) -> str:
    """Returns what a file of status mode `mode` is, in words ("a FIFO (named pipe)")."""
    kinds = (
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    )
    return next((words for test, words in kinds if test(mode)), "not a regular file")


class NotRegularError(OSError):
    """A path that names something other than a regular file (a FIFO, a device, a folder, a socket)."""


def open_input(path: str) -> BinaryIO:
    """Returns the regular file `path` opened for binary reading; OSError if it cannot be opened, NotRegularError if
    it is not a regular file (its `strerror` says what it is: "it is a FIFO (named pipe), not a regular file").

    The file is opened with O_NONBLOCK, so that opening a FIFO that no one writes returns at once, and its type is
    checked on the open descriptor (no race with a file swapped in after a check by name).
    """
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        mode = os.fstat(descriptor).st_mode
        if not stat.S_ISREG(mode):
            raise NotRegularError(errno.EINVAL, f"it is {kind(mode)}, not a regular file", path)
        os.set_blocking(descriptor, True)
        return os.fdopen(descriptor, "rb")
    except BaseException:
        os.close(descriptor)
        raise


def read_input(path: str, limit: int | None = None) -> bytes:
    """Returns the bytes of the regular file `path` (`open_input`), at most `limit` + 1 of them: a caller that gets
    more than `limit` knows the file is too large without reading it all."""
    with open_input(path) as file:
        return file.read() if limit is None else file.read(limit + 1)


def check_input(path: str) -> None:
    """Raises OSError (as `open_input`) unless `path` is a regular file that can be opened for reading: for paths a
    library then opens by name."""
    open_input(path).close()


def check_writable(path: str) -> None:
    """Raises OutputError unless a file can be created at `path` (its folder exists and is writable, its name fits)."""
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise OutputError(f"cannot write {path}: directory {directory} does not exist (create it first)")
    if os.path.isdir(path):
        raise OutputError(f"cannot write {path}: it is a directory (give a file name)")
    check_name_length(path)
    if not takes_files(directory):
        raise OutputError(f"cannot write {path}: directory {directory} is read-only (choose another output path)")


def takes_files(directory: str) -> bool:
    """Returns whether a file can be created in `directory` (a real probe: os.access says yes to root on read-only)."""
    try:
        with tempfile.TemporaryFile(dir=directory):
            return True
    except OSError:
        return False


def check_folder(
    folder: str,
    outputs: Named | None = None,
    inputs: Named | None = None,
    field: str = "out",
    *,
    model: str | None = None,
) -> None:
    """Raises OutputError, before any work, unless output folder `folder` takes new files or can be created.

    The folders missing on the way are created by the command; the nearest one that exists must be
    writable. `outputs` (files the command writes inside `folder`) and `inputs` are then checked as
    `check_outputs` does (with `model`), once the folder exists (a folder still to be made holds no input).
    """
    name = words(field)
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise OutputError(f"{name} {folder} is a file: give a folder", field=field)
    existing = os.path.abspath(folder)
    while not os.path.exists(existing):
        check_name_length(existing)
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        raise OutputError(
            f"{name} {folder} cannot be created: {existing} is a file (choose another folder)", field=field
        )
    if not takes_files(existing):
        raise OutputError(
            f"{name} {folder} cannot be written: {existing} is read-only (choose another folder)", field=field
        )
    if os.path.isdir(folder):
        check_outputs(outputs, inputs, folder_field=field, model=model)
    else:
        for _, path in named_paths(outputs):
            check_name_length(path)


def name_max(directory: str) -> int:
    """Returns the longest file name, in bytes, that the file system of `directory` takes."""
    try:
        return os.pathconf(directory, "PC_NAME_MAX")
    except (OSError, ValueError):
        return DEFAULT_NAME_MAX


def owner() -> str:
    """Returns `<pid>@<host>`: who writes a temporary file, as its name records it."""
    host = re.sub(r"[^A-Za-z0-9.-]", "_", socket.gethostname())[:64] or "host"
    return f"{os.getpid()}@{host}"


def temporary_prefix() -> str:
    """Returns the start of this process's temporary file names: `.matfit-<pid>@<host>-`."""
    return f"{PREFIX}{owner()}-"


def check_name_length(path: str) -> None:
    """Raises OutputError when the name of `path`, or of the temporary file written beside it, is too long.

    Checked before any work: the rename at the end of a fit was where a 300-character name failed.
    """
    directory = os.path.dirname(os.path.abspath(path))
    limit = name_max(directory)
    name = os.path.basename(path)
    length = len(os.fsencode(name))
    if length > limit:
        raise OutputError(
            f"cannot write {path}: its name is {length} bytes, longer than the {limit} its folder takes "
            "(choose a shorter name)"
        )
    temporary = len(os.fsencode(temporary_prefix() + "x" * RANDOM_LETTERS + os.path.splitext(name)[1]))
    if temporary > limit:
        raise OutputError(
            f"cannot write {path}: the temporary file written beside it would have a name of {temporary} bytes, "
            f"longer than the {limit} its folder takes (choose a shorter extension)"
        )


def _identity(path: str) -> tuple:
    """Returns what names one file: the file on the disk, or for a new one the folder and name it would have."""
    try:
        status = os.stat(path)  # follows symbolic links; hard links share the inode
        return ("file", status.st_dev, status.st_ino)
    except OSError:
        pass
    real = os.path.realpath(path)  # not there yet: the place it would be created at
    try:
        folder = os.stat(os.path.dirname(real))
        return ("new", folder.st_dev, folder.st_ino, os.path.basename(real))
    except OSError:
        return ("new", real)


Named = Mapping[str, str | None] | Iterable[tuple[str, str | None]]


def named_paths(paths: Named | None) -> list[tuple[str, str]]:
    """Returns (what the file is, its path) pairs of a mapping or of pairs, leaving out paths not given (None)."""
    pairs = (paths or {}).items() if isinstance(paths, Mapping | None) else paths
    return [(label, path) for label, path in pairs if path is not None]


def check_outputs(
    outputs: Named | None, inputs: Named | None = None, *, folder_field: str | None = None, model: str | None = None
) -> None:
    """Raises OutputError, before any work, unless every output can be written without losing a file.

    `outputs` and `inputs` map what each file is (the option's name: "report", "mask"; a name may
    repeat in pairs) to its path (None: not given). Each output must be writable with a name its
    folder takes (`check_writable`); no two outputs may be the same file (one would silently
    replace the other), no output may be one of the inputs (the user's picture would be
    overwritten), and none may lie in the folder of the model in use (`model`) or of the shipped
    one, nor be one of their files (`check_not_model`). Files are compared on the disk: a symbolic
    or hard link to an input is that input. `folder_field`: the outputs are files the command names
    inside that output folder, which is the thing to change.
    """
    named = named_paths(outputs)
    folder = f"another {words(folder_field)} folder" if folder_field else None
    for label, path in named:
        check_writable(path)
        fix = f"choose {folder or f'another path for the {words(label)}'}"
        check_not_model(label, path, model, fix=fix, field=folder_field or label)
    check_apart(named, inputs, folder_field=folder_field)


def check_apart(outputs: Named | None, inputs: Named | None = None, *, folder_field: str | None = None) -> None:
    """Raises OutputError when two of `outputs` are one file or an output is one of `inputs`, compared on the disk
    (`check_outputs`' comparison alone: a batch compares every picture's outputs with every other's and with every
    picture, each already checked on its own)."""
    named, sources = named_paths(outputs), named_paths(inputs)
    folder = f"another {words(folder_field)} folder" if folder_field else None
    read = {_identity(source): (source_label, source) for source_label, source in reversed(sources)}
    written: dict[tuple, tuple[str, str]] = {}
    for label, path in named:
        identity = _identity(path)
        if identity in written:
            other_label, other = written[identity]
            fix = f"choose {folder}" if folder else "give each output its own path"
            raise OutputError(
                f"{words(other_label)} {other} and {words(label)} {path} are the same file: one would replace "
                f"the other; {fix}",
                field=folder_field or other_label,
            )
        written[identity] = (label, path)
        if identity in read:
            source_label, source = read[identity]
            raise OutputError(
                f"{words(label)} {path} is the {words(source_label)} {source}: writing it would overwrite the "
                f"{words(source_label)}; choose {folder or f'another path for the {words(label)}'}",
                field=folder_field or label,
            )


def check_not_model(label: str, path: str, model: str | None, *, fix: str, field: str) -> None:
    """Raises OutputError when output `path` lies in the folder of `model` or of the shipped model (followed through
    links), or is one of their files by another name (a hard link): writing it would change the model every later
    fit reads (`-o <model>/decoder.json` replaced the decoder's description with a params.json)."""
    real = os.path.dirname(os.path.realpath(path))
    identity = _identity(path)
    for folder in dict.fromkeys(str(place) for place in (model, shipped.MODEL) if place is not None):
        try:
            with os.scandir(folder) as listing:
                held = identity[0] == "file" and any(_identity(entry.path) == identity for entry in listing)
            inside = os.path.samefile(real, folder)
        except OSError:  # no such model folder: `load_model` says so
            continue
        if inside or held:
            raise OutputError(
                f"{words(label)} {path} is a file of the model {folder}: writing it would change the model; {fix}",
                field=field,
            )


def words(label: str) -> str:
    """Returns a field name as the words of a message ("mitsuba_xml" -> "mitsuba xml")."""
    return label.replace("_", " ")


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
    remove_stale(directory)
    try:
        handle, temporary = tempfile.mkstemp(prefix=temporary_prefix(), suffix=os.path.splitext(path)[1], dir=directory)
    except OSError as error:
        raise OutputError(f"cannot write {final_name(path)}: {error.strerror}") from None
    interrupt.register(temporary)
    os.close(handle)
    return temporary


def remove_stale(directory: str) -> list[str]:
    """Removes the temporary files in `directory` whose owner, a process of this host, is gone; returns them.

    A process killed outright (`kill -9`, a power cut on a shared disk's other host aside) cannot
    remove its temporary file; the next write beside it does, once per folder and process. Files
    of another host, of a process still running, or not named by matfit are left alone.
    """
    folder = os.path.abspath(directory)
    if folder in _swept:
        return []
    _swept.add(folder)
    host = owner().partition("@")[2]
    removed = []
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    for name in names:
        match = _OWNED.match(name)
        if match is None or not name[match.end() :].startswith(host + "-"):
            continue
        if not running(int(match.group(1))):
            path = os.path.join(folder, name)
            with contextlib.suppress(OSError):
                if not os.path.isdir(path):
                    os.unlink(path)
                    removed.append(path)
    return removed


def running(pid: int) -> bool:
    """Returns whether process `pid` of this host exists (another user's counts; an impossible pid does not)."""
    if pid == os.getpid():
        return True
    if not 0 < pid < 1 << 22:  # Linux's largest pid_max; 0 and -1 would signal groups
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


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
