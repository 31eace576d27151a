"""Compiled programs kept across processes: matfit's compiled stages stored once as executables and read back.

JAX's persistent compilation cache keeps machine code, but a new process must still trace and
lower every jitted function to find it, and tracing matfit's three stages (best-of-n, the gradient
step, the finish) through Flax was the largest part of a cold `matfit fit` after JAX's import.
`jit` is `jax.jit` with static arguments whose compiled executable, once the store is enabled, is
serialized the first time (`jax.experimental.serialize_executable`) and loaded by later processes,
which then skip tracing, lowering and compiling. (Storing `jax.export` programs instead still costs
their lowering and JAX's cache look-up in every process, on CPU with JAX importing SciPy to
initialise LAPACK: docs/decisions.md.)

The key of a stored program holds everything it was compiled from: matfit's own source (every .py
of the package, hashed once per process), the versions of jax, jaxlib and flax, the JAX settings
that change a trace (64-bit, promotion rules, matmul precision), the backend, its devices and
XLA_FLAGS, the processor's features (machine code compiled for one CPU may not run on another
sharing the home directory), the function's name, the static arguments' repr, and the tree
structure, shapes and dtypes of the others. So a changed matfit, JAX, machine or model
architecture finds no stale program. A static argument without a
faithful repr (one naming a memory address) cannot be keyed: such calls are traced as usual.
Under a JAX transformation (a tracer among the arguments), or before `enable`, a `jit` function
is plain `jax.jit`. An unreadable stored program is compiled again and rewritten. A program is
compiled under a lock on its file (`compiling`), so processes sharing the store compile it once. A stored file
holds the argument and result trees (their protocol-buffer form) and the executable as JAX
serializes it for its own compilation cache.

Loading an executable unpickles it and runs the machine code it holds, so a file that anyone else
could have written must never be loaded. Every stored file therefore begins with an HMAC-SHA256 of
its name and contents, keyed by a per-user secret (`KEY_NAME` beside the store, 32 random bytes,
mode 0600); the HMAC is checked over the whole file before anything in it is parsed, and an entry
that fails is ignored (compiled again and rewritten), never loaded. A store directory, or a key,
that is a symbolic link, belongs to another user or that others may write is not used at all
(`enable` raises OutputError): nothing is stored or read, and every process traces and compiles.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import hmac
import inspect
import json
import os
import platform
import re
import secrets
import stat
import struct
import sys
import tempfile
import threading
from collections.abc import Callable
from typing import Any

import jax

from matfit import files, shipped
from matfit.errors import OutputError

SUFFIX = ".jaxexecutable"
LOCK = ".lock"  # beside a program while it is compiled (`compiling`); removed by `prune` once the program is gone
MAGIC = b"matfit executable 1\n"  # then three little-endian sizes: argument tree, result tree, executable
KEY_NAME = "programs.key"  # the per-user secret that authenticates stored files, beside the store directory
KEY_BYTES = 32
SEAL_BYTES = hashlib.sha256().digest_size  # every stored file begins with its HMAC-SHA256
# What `prune` may remove, by whole name: the store's own files (`_stored_path`: a function's name, 32 hex digits, a
# suffix, perhaps a lock), and in the folder earlier versions gave JAX's persistent cache (`matfit/jax`), JAX's
# (`<module>-<64 hex digits>`, then `-cache` or `-atime` since JAX 0.4.26, and its `.lockfile`).
STORED_NAME = re.compile(r"[^/]+-[0-9a-f]{32}(?:" + re.escape(SUFFIX) + r"|\.json)(?:" + re.escape(LOCK) + ")?")
JAX_CACHE_NAME = re.compile(r"[^/]+-[0-9a-f]{64}(?:-cache|-atime)?|\.lockfile")
_directory: str | None = None
_key: bytes | None = None
_ignored: set[str] = set()  # stored paths that are not regular files, said once per process


def enable(directory: str) -> None:
    """Stores and reads compiled programs under `directory` from now on (it is created, private, if needed).

    Raises OutputError, and leaves the store off, for a directory or key that another user could have written.
    """
    global _directory, _key
    _directory = _key = None
    os.makedirs(directory, mode=0o700, exist_ok=True)
    check_private(directory, "directory", f"chmod 700 {directory}")
    _key = read_key(os.path.join(os.path.dirname(os.path.abspath(directory)), KEY_NAME))
    _directory = directory


def check_private(path: str, kind: str, fix: str) -> os.stat_result:
    """Returns the status of `path` (not following a link) after checking that only this user can change it."""
    status = os.lstat(path)
    if stat.S_ISLNK(status.st_mode):
        raise OutputError(f"the compiled-program store's {kind} {path} is a symbolic link: remove it")
    if status.st_uid != os.getuid():
        raise OutputError(
            f"the compiled-program store's {kind} {path} belongs to user {status.st_uid}, not you: remove it"
        )
    if status.st_mode & 0o022:
        raise OutputError(f"the compiled-program store's {kind} {path} can be written by others: {fix}")
    return status


def read_key(path: str) -> bytes:
    """Returns this user's secret that authenticates stored files, created (mode 0600, atomically) if absent."""
    if not os.path.lexists(path):
        handle, temporary = tempfile.mkstemp(prefix=".matfit-key-", dir=os.path.dirname(path))  # mode 0600
        try:
            with os.fdopen(handle, "wb") as file:
                file.write(secrets.token_bytes(KEY_BYTES))
                file.flush()
                os.fsync(file.fileno())
            with contextlib.suppress(FileExistsError):  # another process made one first: that one is used
                os.link(temporary, path)
        finally:
            os.unlink(temporary)
    status = check_private(path, "key", f"remove {path} (a new one is made)")
    if not stat.S_ISREG(status.st_mode):
        raise OutputError(
            f"the compiled-program store's key {path} is {files.kind(status.st_mode)}: remove it (a new one is made)"
        )
    if status.st_mode & 0o077:
        raise OutputError(
            f"the compiled-program store's key {path} can be read by others: remove it (a new one is made)"
        )
    handle = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    with os.fdopen(handle, "rb") as file:
        key = file.read(KEY_BYTES + 1)
    if len(key) != KEY_BYTES:
        raise OutputError(f"the compiled-program store's key {path} is damaged: remove it (a new one is made)")
    return key


def seal(path: str, data: bytes) -> bytes:
    """Returns a stored file's bytes: the HMAC of its name and `data` under this user's key, then `data`."""
    return _seal(path, data) + data


def opened(path: str) -> bytes:
    """Returns the contents of a stored file whose HMAC is right; ValueError (nothing parsed) if it is not, or if it is
    not a regular file (a FIFO planted in the store would block the process opening it): that one with a notice."""
    try:
        with files.open_input(path) as file:
            data = file.read()
    except files.NotRegularError as error:
        if path not in _ignored:  # once: a program is looked for again under its lock
            _ignored.add(path)
            print(f"notice: ignored {path} in the compiled-program store: {error.strerror}", file=sys.stderr)
        raise ValueError(f"{path} is not a stored file") from None
    seal, contents = data[:SEAL_BYTES], data[SEAL_BYTES:]
    if len(seal) != SEAL_BYTES or not hmac.compare_digest(seal, _seal(path, contents)):
        raise ValueError(f"{path} was not written by this user's matfit")
    return contents


def _seal(path: str, data: bytes) -> bytes:
    if _key is None:
        raise ValueError("no key: the store is off")
    return hmac.new(_key, os.path.basename(path).encode() + b"\0" + data, hashlib.sha256).digest()


def disable() -> None:
    """Stops storing and reading compiled programs (`jit` functions behave as `jax.jit`)."""
    global _directory, _key
    _directory = _key = None


@functools.cache
def source_digest() -> str:
    """Returns the SHA-256 of matfit's Python source: every .py file of the package and its subpackages."""
    return tree_digest(str(shipped.PACKAGE))


def tree_digest(folder: str) -> str:
    """Returns the SHA-256 of every .py file under `folder`, at any depth, each with its path relative to `folder`."""
    digest = hashlib.sha256()
    for parent, folders, names in os.walk(folder):
        folders.sort()  # os.walk visits subfolders in this list's order: sorted, the digest is the same on any disk
        for name in sorted(names):
            if name.endswith(".py"):
                path = os.path.join(parent, name)
                digest.update(os.path.relpath(path, folder).replace(os.sep, "/").encode())
                with open(path, "rb") as file:
                    digest.update(file.read())
    return digest.hexdigest()


@functools.cache
def processor() -> str:
    """Returns what identifies this machine's processor for machine code: its architecture and feature flags."""
    digest = hashlib.sha256(platform.machine().encode())
    seen = set()
    with contextlib.suppress(OSError), open("/proc/cpuinfo", encoding="utf-8", errors="replace") as file:
        for line in file:  # the first processor's model and features (x86: "flags", ARM: "Features")
            name = line.split(":", 1)[0].strip()
            if name in ("model name", "flags", "Features") and name not in seen:
                seen.add(name)
                digest.update(line.encode())
    return digest.hexdigest()[:16]


def environment() -> tuple:
    """Returns what, besides matfit's source and the arguments, decides a compiled program."""
    import flax
    import jaxlib

    config: Any = jax.config  # its options are attributes made at run time, unknown to a type checker
    devices = jax.devices()
    return (
        jax.__version__,
        jaxlib.__version__,
        flax.__version__,
        jax.default_backend(),
        devices[0].client.platform_version,
        len(devices),
        os.environ.get("XLA_FLAGS", ""),
        processor(),
        config.jax_enable_x64,
        config.jax_numpy_dtype_promotion,
        config.jax_numpy_rank_promotion,
        config.jax_default_matmul_precision,
    )


class Program:
    """A jitted function whose compiled programs are stored and read back (see the module's docstring)."""

    def __init__(self, function: Callable, static_argnames: tuple[str, ...]):
        self.function = function
        self.static_argnames = tuple(static_argnames)
        self.signature = inspect.signature(function)
        self.dynamic_names = tuple(name for name in self.signature.parameters if name not in self.static_argnames)
        self.jitted = jax.jit(function, static_argnames=self.static_argnames)
        self.loaded: dict[tuple, Callable] = {}
        self.lock = threading.Lock()
        functools.update_wrapper(self, function)

    def __call__(self, *args, **kwargs):
        if _directory is None:
            return self.jitted(*args, **kwargs)
        bound = self.signature.bind(*args, **kwargs)
        bound.apply_defaults()
        statics = tuple((name, bound.arguments[name]) for name in self.static_argnames)
        values = tuple(bound.arguments[name] for name in self.dynamic_names)
        leaves, tree = jax.tree_util.tree_flatten(values)
        if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
            return self.jitted(*args, **kwargs)
        shapes = tuple((typed.shape, typed.dtype, typed.weak_type) for typed in map(jax.typeof, leaves))
        key = (statics, tree, shapes, _directory)
        program = self.loaded.get(key)
        if program is None:
            with self.lock:  # threads calling one new program at once (the gradient stage's workers) read it once
                program = self.loaded.get(key)
                if program is None:
                    program = self.loaded[key] = self.program(statics, tree, shapes)
        return program(*values)

    def program(self, statics: tuple, tree, shapes: tuple) -> Callable:
        """Returns a callable of the dynamic arguments: the stored executable if there is one, else one compiled now
        (and stored), or the jitted function if the statics cannot be keyed."""
        fixed = dict(statics)

        def traced(*dynamic):
            return self.function(**fixed, **dict(zip(self.dynamic_names, dynamic, strict=True)))

        traced.__name__ = traced.__qualname__ = self.function.__name__  # so that JAX's logs and profiles name it
        described = repr(statics)
        if " at 0x" in described:  # a repr naming an address: no key survives the process
            return jax.jit(traced)
        name = f"{self.function.__module__}.{self.function.__qualname__}"
        arguments = [(shape, str(dtype), weak) for shape, dtype, weak in shapes]
        path = _stored_path(name, (described, str(tree), arguments), SUFFIX)
        compiled = load(path)
        if compiled is not None:
            return compiled
        with compiling(path):  # another process compiling the same program is waited for, then read back
            compiled = load(path)
            if compiled is not None:
                return compiled
            return compile_and_store(traced, tree, shapes, path)

    def _cache_size(self) -> int:
        """Returns how many programs this function holds in this process (compiled by jax.jit or read back)."""
        return self.jitted._cache_size() + len(self.loaded)  # type: ignore[attr-defined]  # jit's private counter


def compile_and_store(traced: Callable, tree, shapes: tuple, path: str) -> Callable:
    """Returns `traced` compiled for `shapes` (with argument tree `tree`), stored at `path` where it can be, or
    jitted as usual where ahead-of-time compilation cannot take it."""
    from jax.experimental import serialize_executable

    specs = [jax.ShapeDtypeStruct(shape, dtype, weak_type=weak) for shape, dtype, weak in shapes]
    try:
        compiled = jax.jit(traced).lower(*jax.tree_util.tree_unflatten(tree, specs)).compile()
    except Exception:  # something ahead-of-time compilation cannot take: traced as usual
        return jax.jit(traced)
    if jax_cache_enabled():  # it may have come from JAX's cache, and such an executable does not survive storing
        return compiled
    # No room, no permission (OSError, OutputError), an executable that cannot be serialized or a tree without a
    # protocol-buffer form (a custom node): used, not stored.
    with contextlib.suppress(Exception):
        files.write_bytes(path, seal(path, pack(*serialize_executable.serialize(compiled))))
    return compiled


def load(path: str) -> Callable | None:
    """Returns the stored executable at `path`, or None where it is absent, damaged, unauthenticated or foreign.
    The HMAC is checked before any byte of the file is parsed or unpickled."""
    from jax.experimental import serialize_executable

    try:
        payload, in_tree, out_tree = unpack(opened(path))
        compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    except Exception:  # absent, damaged, unauthenticated or foreign: compiled (again) by the caller
        return None
    touch(path)
    return compiled


@contextlib.contextmanager
def compiling(path: str):
    """Holds an exclusive lock on `path`'s lock file (`path` + LOCK, private) while a program is compiled for it,
    so that processes sharing the store (the page and a `matfit fit`, the suite's workers) compile each program once:
    a second one waits, then reads what the first stored. The lock goes with its process (flock), so a process killed
    while compiling blocks no one. Where no lock can be taken (no fcntl, no room, no permission) it compiles alone."""
    try:
        import fcntl

        descriptor = os.open(path + LOCK, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o600)
    except (ImportError, OSError):
        yield
        return
    try:
        with contextlib.suppress(OSError):
            fcntl.flock(descriptor, fcntl.LOCK_EX)
        yield
    finally:
        os.close(descriptor)  # releases the lock


def pack(payload: bytes, in_tree, out_tree) -> bytes:
    """Returns a stored executable's file: `MAGIC`, the three sizes, the trees' protocol buffers, the executable."""
    parts = (in_tree.serialize_using_proto(), out_tree.serialize_using_proto(), bytes(payload))
    return MAGIC + struct.pack("<3Q", *map(len, parts)) + b"".join(parts)


def unpack(data: bytes) -> tuple:
    """Returns (executable, argument tree, result tree) from a stored executable's file; ValueError if damaged."""
    header = len(MAGIC) + struct.calcsize("<3Q")
    if not data.startswith(MAGIC) or len(data) < header:
        raise ValueError("not a stored executable")
    sizes = struct.unpack_from("<3Q", data, len(MAGIC))
    if header + sum(sizes) != len(data):
        raise ValueError("a stored executable of the wrong size")
    parts, offset = [], header
    for size in sizes:
        parts.append(data[offset : offset + size])
        offset += size
    in_tree, out_tree, payload = parts
    registry = jax.tree_util.default_registry
    return (
        payload,
        jax.tree_util.PyTreeDef.deserialize_using_proto(registry, in_tree),
        jax.tree_util.PyTreeDef.deserialize_using_proto(registry, out_tree),
    )


def jax_cache_enabled() -> bool:
    """Returns whether JAX's persistent compilation cache is on (by the user's JAX settings: matfit leaves it off).

    An executable that XLA's CPU backend read from that cache and that is then serialized again loads in a later
    process but fails when run ("Function wrapped_iota not found"): with the cache on, nothing is stored.
    """
    config: Any = jax.config  # its options are attributes made at run time, unknown to a type checker
    return bool(config.jax_compilation_cache_dir) and bool(config.jax_enable_compilation_cache)


def _stored_path(name: str, parts: Any, suffix: str) -> str:
    """Returns where the store keeps `name` for `parts`: hashed with the environment and matfit's source."""
    assert _directory is not None, "called only with the store on"
    key = repr((name, parts, environment(), source_digest()))
    return os.path.join(_directory, f"{name}-{hashlib.sha256(key.encode()).hexdigest()[:32]}{suffix}")


def jit(function: Callable | None = None, *, static_argnames: tuple[str, ...] = ()) -> Any:
    """Returns `function` as a `Program` (usable as a decorator, `@programs.jit(static_argnames=(...))`)."""
    if function is None:
        return functools.partial(jit, static_argnames=static_argnames)
    return Program(function, static_argnames)


def remembered(name: str, parts: Any, compute: Callable[[], Any]) -> Any:
    """Returns `compute()` (JSON data), kept in the store under `name` and the key rules of programs: `parts` (with a
    faithful repr), the environment and matfit's source. Without a store it is computed every time."""
    if _directory is None:
        return compute()
    path = _stored_path(name, repr(parts), ".json")
    try:
        value = json.loads(opened(path))
        touch(path)
        return value
    except (OSError, ValueError, RecursionError):  # absent, damaged or unauthenticated: computed again, below
        pass
    value = compute()
    with contextlib.suppress(OSError, OutputError):  # no room or no permission: computed again next time
        files.write_bytes(path, seal(path, json.dumps(value).encode()))
    return json.loads(json.dumps(value))  # the same types as read back (lists for tuples)


def prune(directory: str, max_bytes: int, *, owned: re.Pattern[str] = STORED_NAME) -> int:
    """Removes the least recently used of a cache directory's own files until the rest take at most `max_bytes`,
    then the lock files (`compiling`) whose program is gone and that no process holds; returns how many files it
    removed. Last use is a file's later access or modification time (a program read back has its time set,
    `touch`). Files another process removes meanwhile, or that cannot be removed, are skipped: a cache is never
    worth an error.

    Only what the cache itself wrote is removed: regular files whose whole name `owned` matches, in `directory`
    itself. A `directory` that is a symbolic link, or that another user owns, is left alone, and nothing inside it
    is reached through a link: the folder is opened once (O_NOFOLLOW) and every name is looked up and removed
    relative to that open folder, so a link planted in the cache (`matfit/jax -> someone's folder`) costs no file.
    """
    try:
        folder = os.open(directory, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:  # absent, a link or not a folder: nothing of ours is there
        return 0
    try:
        if os.fstat(folder).st_uid != os.getuid():
            return 0
        return _prune_open(folder, max_bytes, owned)
    finally:
        os.close(folder)


def _prune_open(folder: int, max_bytes: int, owned: re.Pattern[str]) -> int:
    """`prune` on the open folder `folder`: every name is looked up and removed relative to it (`dir_fd`)."""
    try:
        entries, locks = [], []
        with os.scandir(folder) as listing:
            for entry in listing:
                if not owned.fullmatch(entry.name) or not entry.is_file(follow_symlinks=False):
                    continue
                if entry.name.endswith(LOCK):
                    locks.append(entry.name)
                else:
                    status = entry.stat(follow_symlinks=False)
                    entries.append((max(status.st_atime, status.st_mtime), status.st_size, entry.name))
    except OSError:
        return 0
    total, removed = sum(size for _, size, _ in entries), 0
    for _, size, name in sorted(entries):
        if total <= max_bytes:
            break
        with contextlib.suppress(OSError):
            os.unlink(name, dir_fd=folder)
            removed += 1
        total -= size
    return removed + sum(remove_unheld(name, folder) for name in locks if not _present(name[: -len(LOCK)], folder))


def _present(name: str, folder: int) -> bool:
    """Returns whether `name` exists (as anything, a link included) in the open folder `folder`."""
    try:
        os.stat(name, dir_fd=folder, follow_symlinks=False)
        return True
    except OSError:
        return False


def remove_unheld(name: str, folder: int) -> bool:
    """Removes the lock file `name` of the open folder `folder` unless a process holds it (compiling its program
    now); returns whether it did."""
    try:
        import fcntl

        descriptor = os.open(name, os.O_RDWR | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, dir_fd=folder)
    except (ImportError, OSError):
        return False
    try:
        if not stat.S_ISREG(os.fstat(descriptor).st_mode):
            return False
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.unlink(name, dir_fd=folder)
        return True
    except OSError:  # held: that process is compiling the program and will store it
        return False
    finally:
        os.close(descriptor)


def touch(path: str) -> None:
    """Marks a stored file as used now (for `prune`), if it can."""
    with contextlib.suppress(OSError):
        os.utime(path)


def stored() -> list[str]:
    """Returns the stored programs' and remembered values' file names (none before `enable`)."""
    if _directory is None or not os.path.isdir(_directory):
        return []
    return sorted(name for name in os.listdir(_directory) if name.endswith((SUFFIX, ".json")))


# The most the program store may hold: the shipped model's default fit stores ~2.4 MB of executables (its four compiled
# stages and the encoders' conversion); every new matfit, JAX or model writes new entries beside the old, which only
# pruning removes.
CACHE_BYTES = {"programs": 64 * 2**20}


def enable_compilation_cache() -> None:
    """Turns on the store of compiled programs (this module) under $XDG_CACHE_HOME/matfit or ~/.cache/matfit.

    A second `matfit fit` then loads its compiled stages instead of tracing and compiling them again. The store
    does not grow without bound: each process first prunes it to `CACHE_BYTES` (least recently used first).
    JAX's own persistent compilation cache is not turned on: the store keeps the executables themselves, and an
    executable that JAX read from its cache does not survive being stored again (it fails at its next load with
    "Function ... not found"). What earlier matfit versions kept there (`matfit/jax`) is removed: JAX's own files
    only, never through a link (`prune`). A store that another user could have written (see above) is not used,
    with a one-line notice on standard error.
    """
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    stored = os.path.join(root, "matfit", "programs")
    try:
        enable(stored)
    except OSError:
        return  # no writable cache: trace and compile every time
    except OutputError as error:  # a store others could have written to is never read: said once, then compiled
        print(f"notice: compiled programs are not stored or read: {error}", file=sys.stderr)
        return
    old = os.path.join(root, "matfit", "jax")
    prune(old, 0, owned=JAX_CACHE_NAME)
    with contextlib.suppress(OSError):  # emptied (a link, or a folder holding anything else, stays)
        os.rmdir(old)
    prune(stored, CACHE_BYTES["programs"])
