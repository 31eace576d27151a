"""The matfit command line in a subprocess: started, polled or waited for, cancelled, its error as one line.

Each job owns a fresh private temporary folder (`Job.folder`, made with mkdtemp: mode 0700, a new
name) for the files it writes; the extension reads its outputs only from there, so a file that this
run did not write (left from an older fit, or planted beside a picture) is never read, and the
folder is removed when the job is done with (`Job.remove`).
"""

import collections
import os
import shlex
import shutil
import subprocess
import tempfile
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


def command_words(command):
    """Returns the words of the matfit command: an existing file is one program, spaces in its path and all."""
    path = os.path.expanduser(command.strip())
    if os.path.isfile(path):
        return [path]
    return split(command)


def new_folder():
    """Returns a new private temporary folder for a job's files (the Job given it removes it)."""
    return tempfile.mkdtemp(prefix="matfit-job-")


class Job:
    """One run of the matfit command line; a thread keeps its last lines so that polling never blocks.

    `folder` (from `new_folder()`, or None for a new one) is the job's own: matfit's outputs go there,
    and `remove` (or `cancel`, or a start that fails) deletes it.
    """

    def __init__(self, command, arguments, folder=None):
        self.folder = folder or new_folder()
        try:
            words = command_words(command)
        except JobError:
            self.remove()
            raise
        if not words:
            self.remove()
            raise JobError(f"matfit: no matfit command: {FIX}")
        self.command, self.arguments = command, arguments
        self.started = time.monotonic()
        self._lines = collections.deque(maxlen=20)
        try:
            self._process = subprocess.Popen(
                [*words, *self.arguments], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
            )
        except OSError as error:
            self.remove()
            quote = " (a path with spaces runs as it is only when the file exists)" if " " in command.strip() else ""
            raise JobError(f"matfit: cannot run {command!r} ({error.strerror or error}){quote}: {FIX}") from None
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def path(self, name):
        """Returns the path of `name` in the job's own folder."""
        return os.path.join(self.folder, name)

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
        self.remove()

    def remove(self):
        """Removes the job's folder and what matfit wrote there."""
        shutil.rmtree(self.folder, ignore_errors=True)

    def check(self):
        """Raises JobError with matfit's own error line if it failed."""
        self.wait()
        code = self._process.returncode
        if code != 0:
            errors = [line for line in self._lines if line.startswith("error:")]
            last = (errors or list(self._lines) or [f"exit code {code}"])[-1]
            raise JobError(f"matfit ({self.command}) failed: {last}")
