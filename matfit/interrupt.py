"""Ctrl-C and `kill` end any command within about a second: one `interrupted:` line, exit code 130, no temporary file left.

Python runs a signal handler only in the main thread, between two bytecodes. A main thread inside
one long compiled call (a whole XLA fit, a Mitsuba render) gets there only when the call returns,
and measured on `matfit fit --evals 200000`, a KeyboardInterrupt that finally surfaces in the middle
of JAX's work then often hung in garbage collection or crashed during the interpreter's teardown.

So `install` also has the signal's C-level handler write to a pipe (`signal.set_wakeup_fd`), which
a watchdog thread reads: the main thread gets GRACE seconds to end the usual way (its
KeyboardInterrupt and the command's own clean-up); if it has not, the watchdog prints the line,
removes the temporary files that `files` registered, and ends the process with `os._exit`, which
runs no more Python code and no teardown. A second Ctrl-C ends it at once. A KeyboardInterrupt
that lands in a callback that cannot raise (JAX's garbage-collection callback, measured: Python
prints "Exception ignored" and carries on with the fit) ends the process the same way, at once. A command that ends by
interruption on its own also leaves through `exit_now`, never through the teardown.

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

EXIT_CODE = 130
GRACE = 1.0  # seconds the main thread has to stop by itself
STOPPING = (signal.SIGINT, signal.SIGTERM)

_temporaries: set[str] = set()
_state = {"message": "nothing was written", "announced": False}
_lock = threading.Lock()


def register(path: str) -> None:
    """Marks a temporary file to be removed if the process is ended by an interruption."""
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
    """Announces the interruption, removes the registered temporary files and ends the process (130), skipping teardown."""
    announce()
    for path in list(_temporaries):
        with contextlib.suppress(OSError):
            os.unlink(path)
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    os._exit(EXIT_CODE)


def install() -> None:
    """Makes Ctrl-C and `kill` raise KeyboardInterrupt in the main thread and starts the watchdog that enforces them."""
    read, write = os.pipe()
    os.set_blocking(write, False)
    signal.set_wakeup_fd(write, warn_on_full_buffer=False)
    for number in STOPPING:
        signal.signal(number, signal.default_int_handler)
    sys.unraisablehook = _unraisable
    threading.Thread(target=_watch, args=(read,), name="matfit-interrupt", daemon=True).start()


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
