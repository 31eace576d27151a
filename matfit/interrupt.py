"""Ctrl-C and `kill` end any command within about a second: one `interrupted:` line, exit 130, no temporary file left.

Python runs a signal handler only in the main thread, between two bytecodes. A main thread inside
one long compiled call (a whole XLA fit, a Mitsuba render) gets there only when the call returns,
and measured on `matfit fit --evals 200000`, a KeyboardInterrupt that finally surfaces in the middle
of JAX's work then often hung in garbage collection or crashed during the interpreter's teardown.

So `install` makes the signal end the process instead of raising KeyboardInterrupt (a
KeyboardInterrupt raised inside an import of JAX also crashed it), and has the signal's C-level
handler write to a pipe (`signal.set_wakeup_fd`) that a watchdog thread reads: if the main thread
has not ended within GRACE seconds (it is inside a compiled call), the watchdog prints the line,
removes the temporary files that `files` registered, and ends the process with `os._exit`, which
runs no more Python code and no teardown. A second Ctrl-C ends it at once. Every output is written
under a registered temporary name and renamed only when complete, and a dataset's done flag is set
only after its image row, so ending the process at any bytecode loses nothing finished. Work that
stops child processes itself (a dataset's rendering pool) asks for KeyboardInterrupt back
(`raise_on_signal`). Library code called in-process (tests, `CliRunner`) keeps Python's own.

Only the standard library is imported here: `install` runs before the command line's own imports,
so that a Ctrl-C during start-up is as quiet as one during the work.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import sys
import threading
from typing import Any

EXIT_CODE = 130
GRACE = 1.0  # seconds the main thread has to stop by itself
STOPPING = (signal.SIGINT, signal.SIGTERM)

_temporaries: set[str] = set()
_state: dict[str, Any] = {"message": "nothing was written", "announced": False}
_lock = threading.Lock()


def register(path: str) -> None:
    """Marks a temporary file, or folder (removed once its registered files are), to be removed on an interruption."""
    _temporaries.add(path)


def unregister(path: str) -> None:
    """Forgets a temporary file (renamed into place or removed)."""
    _temporaries.discard(path)


def set_message(message: str) -> None:
    """Sets what the `interrupted:` line says the interruption leaves behind."""
    _state["message"] = message


def announced() -> bool:
    """Records that the `interrupted:` line was printed; returns whether it already had been."""
    with _lock:
        before, _state["announced"] = _state["announced"], True
    return before


def announce() -> None:
    """Prints `interrupted: <message>` to standard error, unless it was printed already."""
    if not announced():
        with contextlib.suppress(Exception):
            sys.stderr.write(f"interrupted: {_state['message']}\n")
            sys.stderr.flush()


def exit_now() -> None:
    """Announces the interruption, removes the registered temporary files, ends the process (130) skipping teardown."""
    announce()
    for path in sorted(_temporaries, key=len, reverse=True):  # a folder's files before the folder
        with contextlib.suppress(OSError):
            os.rmdir(path) if os.path.isdir(path) else os.unlink(path)
    if threading.current_thread() is threading.main_thread():  # the work stopped itself: nothing left running
        release_semaphores()
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    os._exit(EXIT_CODE)


def leave(code: int) -> None:
    """Ends a finished command's process with `code`, skipping the interpreter's teardown.

    Every output is complete by then (written, fsynced and renamed by `files`), and the teardown is
    what is left: JAX's and Dr.Jit's shutdown, a noticeable share of a short command's time. Child
    processes are stopped by the work that started them.
    """
    release_semaphores()
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(code)


def release_semaphores() -> None:
    """Unlinks the named semaphores of the process pools this process made, as the interpreter's exit would.

    `os._exit` skips multiprocessing's exit finalizers; its resource tracker then found the
    semaphores of a stopped dataset's rendering pool still registered and printed a warning about
    "leaked semaphore objects" after the `interrupted:` line. Priority 0 and up are what the
    interpreter's own exit runs first: the pools (stopped by then) and their locks.
    """
    util = sys.modules.get("multiprocessing.util")
    if util is not None:
        with contextlib.suppress(Exception):
            util._run_finalizers(0)


def install() -> None:
    """Makes Ctrl-C and `kill` end the process at the main thread's next bytecode, and starts the watchdog.

    A KeyboardInterrupt raised inside an import of JAX or Mitsuba crashed the interpreter (SIGSEGV,
    measured at 0.3 s into `matfit fit`), and every output is written under a registered temporary
    name anyway, so the handler does not raise: it ends the process (`exit_now`). A main thread
    inside one long compiled call runs no bytecode until the call returns: the watchdog ends it.
    """
    read, write = os.pipe()
    os.set_blocking(write, False)
    signal.set_wakeup_fd(write, warn_on_full_buffer=False)
    for number in STOPPING:
        signal.signal(number, lambda *_: exit_now())
    sys.unraisablehook = _unraisable
    threading.Thread(target=_watch, args=(read,), name="matfit-interrupt", daemon=True).start()


def raise_on_signal() -> None:
    """Makes Ctrl-C and `kill` raise KeyboardInterrupt in the main thread again: for work that stops its children.

    A dataset's rendering processes are stopped by the parent's KeyboardInterrupt (`dataset_workers.in_worker_processes`
    kills them once the results that are in are stored).
    """
    if threading.current_thread() is threading.main_thread():
        for number in STOPPING:
            signal.signal(number, signal.default_int_handler)


def _unraisable(unraisable, default=sys.unraisablehook) -> None:
    if issubclass(unraisable.exc_type, KeyboardInterrupt):
        exit_now()
    default(unraisable)


def _stopping(data: bytes) -> bool:
    return any(byte in STOPPING for byte in data)


def _watch(read: int) -> None:
    while not _stopping(os.read(read, 64)):
        pass
    # The main thread may still stop by itself; a second signal, or GRACE seconds, end it here.
    ready, _, _ = select.select([read], [], [], GRACE)
    while ready and not _stopping(os.read(read, 64)):
        ready, _, _ = select.select([read], [], [], GRACE)
    exit_now()
