"""The matfit command line in a subprocess: started, polled or waited for, cancelled, its error as one line."""

import collections
import shlex
import subprocess
import threading
import time

FIX = "set its path in Edit > Preferences > Add-ons > matfit"


class JobError(Exception):
    """matfit could not be run or failed; the message is one line for Blender's report."""


def split(text):
    """Returns the words of a command line as a shell would split them, or raises JobError."""
    try:
        return shlex.split(text)
    except ValueError as error:
        raise JobError(f"matfit: cannot read {text!r}: {error}") from None


class Job:
    """One run of the matfit command line; a thread keeps its last lines so that polling never blocks."""

    def __init__(self, command, arguments):
        words = split(command)
        if not words:
            raise JobError(f"matfit: no matfit command: {FIX}")
        self.command, self.arguments = command, arguments
        self.outputs = {}
        self.started = time.monotonic()
        self._lines = collections.deque(maxlen=20)
        try:
            self._process = subprocess.Popen(
                [*words, *arguments], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
            )
        except OSError as error:
            raise JobError(f"matfit: cannot run {command!r} ({error.strerror or error}): {FIX}") from None
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in self._process.stdout:
            if line.strip():
                self._lines.append(line.strip())

    def poll(self):
        """Returns the exit code, or None while matfit runs."""
        return self._process.poll()

    def wait(self):
        self._process.wait()
        self._reader.join()

    def status(self):
        """Returns the status bar's text: what runs, for how long, and matfit's last line."""
        line = f": {self._lines[-1]}" if self._lines else ""
        return f"matfit {self.arguments[0]} running for {time.monotonic() - self.started:.0f} s{line}"

    def cancel(self):
        if self._process.poll() is None:
            self._process.terminate()
        self.wait()

    def check(self):
        """Raises JobError with matfit's own error line if it failed."""
        self.wait()
        code = self._process.returncode
        if code != 0:
            errors = [line for line in self._lines if line.startswith("error:")]
            last = (errors or list(self._lines) or [f"exit code {code}"])[-1]
            raise JobError(f"matfit ({self.command}) failed: {last}")
