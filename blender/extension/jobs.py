"""The matfit command line in a subprocess: started, polled or waited for, cancelled, its error as one line.

Each job owns a fresh private temporary folder (`Job.folder`, made with mkdtemp: mode 0700, a new
name) for the files it writes; the extension reads its outputs only from there, so a file that this
run did not write (left from an older fit, or planted beside a picture) is never read, and the
folder is removed when the job is done with (`Job.remove`).

A fit runs in matfit's worker (`WorkerJob`): one `matfit worker` process a Blender session (`Worker`),
started by the first fit and kept, so that the model, JAX's compiled programs and Mitsuba's scene
stay loaded; it is sent each fit's command line as one JSON line and answers with its exit code and
output. A worker of protocol 2 is asked for the stages' answers too: it sends each as it lands (the
neural search's first), before its exit code, and `WorkerJob.stages` hands them on without waiting.
A request waits until the worker has said it is ready, so that its protocol is known (an older worker
refuses a field it does not know). A worker that ends during a fit is started again once for that
fit; ending again is the fit's one error line, its last words on standard error. A matfit command that has no worker (an
older matfit: it ends without saying it is ready) runs each fit as a process of its own (`Job`),
said once in a report line. `stop_workers` ends the worker when Blender quits or the extension is
turned off; a worker whose Blender ended any other way sees its standard input end and ends too.
"""

import atexit
import collections
import contextlib
import json
import os
import shlex
import shutil
import subprocess
import tempfile
import threading
import time

FIX = "set its path in Edit > Preferences > Add-ons > matfit"

# What a fit can take, by which `WorkerJob.wait` (a script's `bpy.ops.matfit.fit()`) gives up on a worker that has
# not answered: about twenty times what matfit measures, so that only a worker that will never answer is given up on.
# FIT_SECONDS for a fit at matfit's default budgets, the worker's start included (the slowest measured took 28 s: cold,
# its programs compiled into an empty store); then, for each budget the Fit options raise above its default, STEPS'
# seconds a unit (the shipped model's: a larger model of the user's own takes longer), and SAMPLE_SECONDS for each
# pixel sample of a --render output (--size squared times --spp).
FIT_SECONDS = 600.0
STEPS = {  # option: (matfit's default, seconds each unit above it adds)
    "--evals": (1500, 0.01),  # Nelder-Mead's evaluations: a decode each, under a millisecond
    "--polish": (0, 0.02),  # Adam steps: a decode and its gradient each
    "--iterations": (60, 0.02),  # the best start's L-BFGS-B steps: a decode and its gradient each
    "--narrow-after": (35, 0.02 * 64),  # every start's L-BFGS-B steps, up to 64 starts
    "--starts": (4, 0.02 * 35),  # L-BFGS-B starts: --narrow-after steps each (35 by default)
    "--corrections": (2, 30.0),  # rounds of correction: a decoder fit and a 64-spp render each
    "--refine": (0, 20.0),  # steps through Mitsuba's differentiable renderer: 0.1-1 s each
}
SAMPLE_SECONDS = 2e-5  # a sample of a pixel of the --render output: 2-9 us on one core, measured


def fit_seconds(arguments):
    """Returns how long the fit of the `matfit fit` command line `arguments` may take (the rule above)."""
    given = {}
    for index, word in enumerate(arguments):
        name, equals, value = word.partition("=")
        if not equals:
            value = arguments[index + 1] if index + 1 < len(arguments) else ""
        with contextlib.suppress(ValueError):  # a value matfit refuses itself, at once
            given[name] = int(value)
    seconds = FIT_SECONDS
    for option, (default, each) in STEPS.items():
        seconds += max(given.get(option, default) - default, 0) * each
    if any(word == "--render" or word.startswith("--render=") for word in arguments):
        seconds += given.get("--size", 512) ** 2 * given.get("--spp", 256) * SAMPLE_SECONDS
    return seconds


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


def cannot_run(command, error):
    """Returns the JobError of a matfit command that could not be started (`error`: the OSError)."""
    quote = " (a path with spaces runs as it is only when the file exists)" if " " in command.strip() else ""
    return JobError(f"matfit: cannot run {command!r} ({error.strerror or error}){quote}: {FIX}")


def failure(command, code, lines):
    """Returns the JobError of a matfit run that ended with `code`: its last `error:` line, or its last line."""
    errors = [line for line in lines if line.startswith("error:")]
    last = (errors or list(lines) or [f"exit code {code}"])[-1]
    return JobError(f"matfit ({command}) failed: {last}")


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
            raise cannot_run(command, error) from None
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
            raise failure(self.command, code, self._lines)


class Worker:
    """One `matfit worker` process of a matfit command: requests written to it as JSON lines, its answers read by a
    thread (so that nothing waits on it), the last lines of its standard error kept for an error line."""

    LIMIT = 1 << 20  # bytes of one answer line read: a fit's output is a few lines, a stage's params.json a few KB
    STAGES = 2  # the worker protocol whose requests may ask for the stages' answers
    STOP_SECONDS = 2.0  # how long `stop` waits for the worker to end by itself before ending it
    QUICK_SECONDS = 0.2  # the same, when Blender is waiting (a worker replaced, a fit cancelled)

    def __init__(self, command):
        words = command_words(command)
        if not words:
            raise JobError(f"matfit: no matfit command: {FIX}")
        self.command = command
        self.started = time.monotonic()
        self.ready = False  # it said it is a matfit worker
        self.protocol = 1  # the protocol it said it speaks
        self.ended = False  # its standard output ended: it ended, or is ending
        self.errors = collections.deque(maxlen=20)
        self._answers = {}
        self._stages = {}  # request id: [(stage, its params.json document)] not yet taken
        self._waiting = []  # requests sent before it said it is ready
        self._lock = threading.Lock()  # the requests written, and the stages kept, from two threads
        self._next = 0
        try:
            # A session of its own: a Ctrl-C in Blender's terminal reaches Blender, whose end ends the worker.
            self._process = subprocess.Popen(
                [*words, "worker"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                start_new_session=True,
            )
        except OSError as error:
            raise cannot_run(command, error) from None
        threading.Thread(target=self._read_answers, daemon=True).start()
        self._errors_reader = threading.Thread(target=self._read_errors, daemon=True)
        self._errors_reader.start()

    @property
    def pid(self):
        return self._process.pid

    def _read_answers(self):
        stream = self._process.stdout
        while line := stream.readline(self.LIMIT):
            try:
                answer = json.loads(line)
            except ValueError:
                continue  # not an answer (a line cut at LIMIT, or something else's): the fit then has none
            if not isinstance(answer, dict):
                continue
            if answer.get("ready") == "matfit worker":
                self._ready(answer.get("protocol"))
            elif isinstance(answer.get("exit"), int) and isinstance(answer.get("output"), str):
                self._answers[answer.get("id")] = (answer["exit"], answer["output"])
            elif isinstance(answer.get("stage"), str) and isinstance(answer.get("document"), dict):
                with self._lock:
                    self._stages.setdefault(answer.get("id"), []).append((answer["stage"], answer["document"]))
        stream.close()  # its end: nothing more comes
        self.ended = True

    def _ready(self, protocol):
        """Takes the worker's word that it is ready, speaking `protocol`, and writes the requests that waited for it."""
        with self._lock:
            self.protocol = protocol if isinstance(protocol, int) and not isinstance(protocol, bool) else 1
            self.ready = True
            for request in self._waiting:
                self._write(request)
            self._waiting.clear()

    def _read_errors(self):
        for line in self._process.stderr:
            text = line.decode("utf-8", errors="replace").strip()
            if text:
                self.errors.append(text)
        self._process.stderr.close()

    def send(self, arguments):
        """Sends the command line `arguments` (["fit", ...]), once the worker has said it is ready; returns the
        request's id (no answer comes if it ended)."""
        with self._lock:
            self._next += 1
            request = {"id": self._next, "arguments": list(arguments)}
            if self.ready:
                self._write(request)
            else:
                self._waiting.append(request)
            return self._next

    def _write(self, request):
        """Writes `request`, asking for the stages' answers where the worker's protocol has them (the lock held)."""
        if self.protocol >= self.STAGES:
            request = {**request, "stages": True}
        try:
            self._process.stdin.write((json.dumps(request) + "\n").encode())
            self._process.stdin.flush()
        except (OSError, ValueError):  # it ended: the job sees it end without an answer
            pass

    def answer(self, identifier):
        """Returns (exit code, output) of the request `identifier` once answered, else None; its stages' answers not
        taken are dropped then."""
        answer = self._answers.pop(identifier, None)
        if answer is not None:
            with self._lock:
                self._stages.pop(identifier, None)
        return answer

    def stages(self, identifier):
        """Returns the stages' answers of the request `identifier` that came since the last call, [(stage, params.json
        document)], oldest first."""
        with self._lock:
            return self._stages.pop(identifier, [])

    def code(self):
        """Returns the worker's exit code, or None while it runs."""
        return self._process.poll()

    def last_error(self):
        """Returns the last line the worker wrote on standard error, or None (once read: its render children, which
        share that pipe, may hold it open a moment longer)."""
        self._errors_reader.join(1.0)
        return self.errors[-1] if self.errors else None

    def stop(self, wait=True):
        """Ends the worker: closes its standard input (it ends by itself, at once when idle), then ends it if it has
        not within STOP_SECONDS (QUICK_SECONDS without `wait`: it may be busy with a fit nobody wants)."""
        with contextlib.suppress(OSError):
            self._process.stdin.close()
        try:
            self._process.wait(self.STOP_SECONDS if wait else self.QUICK_SECONDS)
            return
        except subprocess.TimeoutExpired:
            self._process.terminate()
        try:
            self._process.wait(self.STOP_SECONDS)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()


_worker = [None]  # the session's Worker, or None
_no_worker = set()  # matfit commands that ended without saying they are a worker (an older matfit)


def worker(command, fresh=False):
    """Returns the session's worker of `command`, started if need be (`fresh`: a new one in any case); the worker of
    another command is stopped once this one has started."""
    current = _worker[0]
    if current is not None and current.command == command and not current.ended and not fresh:
        return current
    started = Worker(command)
    if current is not None:
        current.stop(wait=False)
    _worker[0] = started
    return started


def stop_workers():
    """Ends the session's worker (Blender quits, or the extension is turned off)."""
    current, _worker[0] = _worker[0], None
    if current is not None:
        current.stop()


atexit.register(stop_workers)


class WorkerJob:
    """A fit sent to the session's `Worker`, with `Job`'s methods: polled or waited for, cancelled, checked.

    `folder` as `Job`'s. A worker that ends during the fit is started again and sent the fit once more; a command
    that is no worker runs the fit as a `Job`, and `note` then says so (once a session).
    """

    READY_SECONDS = 120.0  # a worker that has not said it is ready by then is taken for no worker

    def __init__(self, command, arguments, folder=None):
        self.folder = folder or new_folder()
        self.command, self.arguments = command, arguments
        self.started = time.monotonic()
        self.note = None
        self._job = None  # the Job it runs as, with a command that has no worker
        self._worker = None
        self._answer = None  # (exit code, output lines)
        self._error = None  # the JobError of a worker that could not be started again
        self._restarted = False
        try:
            if command in _no_worker:
                self._job = Job(command, arguments, self.folder)
            else:
                self._send(worker(command))
        except BaseException:
            self.remove()
            raise

    def _send(self, chosen):
        self._worker, self._id = chosen, chosen.send(self.arguments)
        self._seconds = fit_seconds(self.arguments)  # `wait` gives up on the worker after what the fit can take
        self._deadline = time.monotonic() + self._seconds

    def path(self, name):
        """Returns the path of `name` in the job's own folder."""
        return os.path.join(self.folder, name)

    def poll(self):
        """Returns the exit code, or None while the fit runs."""
        if self._job is not None:
            return self._job.poll()
        if self._answer is None and self._error is None:
            try:
                self._step()
            except JobError as error:  # a worker that cannot be started again
                self._error = error
        if self._job is not None:
            return self._job.poll()
        return 1 if self._error is not None else None if self._answer is None else self._answer[0]

    def _step(self):
        chosen = self._worker
        ended = chosen.ended  # before the answer: a worker answers, then may end
        answer = chosen.answer(self._id)
        if answer is not None:
            code, output = answer
            self._answer = (code, [line.strip() for line in output.splitlines() if line.strip()])
            return
        if not ended:
            if not chosen.ready and time.monotonic() - chosen.started > self.READY_SECONDS:
                chosen.stop(wait=False)  # it ends; the next poll runs the fit as a process of its own
            return
        chosen.stop(wait=False)  # reaped
        if not chosen.ready:  # no `matfit worker` there: each fit is a process of its own
            _no_worker.add(self.command)
            self.note = f"matfit: {self.command!r} has no `matfit worker` (an older matfit?): each fit starts matfit"
            self._job = Job(self.command, self.arguments, self.folder)
            return
        if not self._restarted:
            self._restarted = True
            self._send(worker(self.command, fresh=True))
            return
        said = chosen.last_error()
        self._answer = (
            chosen.code() or 1,
            [f"error: its worker ended during the fit, twice (exit code {chosen.code()}){f': {said}' if said else ''}"],
        )

    def wait(self):
        if self._job is not None:
            return self._job.wait()
        while self.poll() is None:
            if self._job is not None:
                return self._job.wait()
            if time.monotonic() > self._deadline:  # alive, but no answer in what the fit can take: it never will
                if _worker[0] is self._worker:
                    _worker[0] = None  # the next fit starts a new worker
                self._worker.stop(wait=False)
                self._answer = (
                    1,
                    [
                        f"error: its worker gave no answer in {self._seconds:.0f} s, the most this fit may take: it "
                        "was ended, and the next fit starts a new one"
                    ],
                )
                return
            time.sleep(0.05)

    def stages(self):
        """Returns the answers of the fit's stages that came since the last call, [(stage, its params.json document)],
        oldest first: the neural search's, then Mitsuba's ("verified", "clean", "refined"); none from a worker that
        has no stages (protocol 1), a fit run as a process of its own, or once the fit has ended."""
        if self._job is not None or self._answer is not None or self._error is not None:
            return []
        return self._worker.stages(self._id)

    def status(self):
        """Returns the status bar's text: what runs, for how long."""
        if self._job is not None:
            return self._job.status()
        return f"matfit {self.arguments[0]} running for {time.monotonic() - self.started:.0f} s: in matfit's worker"

    def cancel(self):
        if self._job is not None:
            self._job.cancel()
            return
        if self._answer is None and self._error is None:  # it is busy with this fit: end it, the next starts one
            if _worker[0] is self._worker:
                _worker[0] = None
            self._worker.stop(wait=False)
        self.remove()

    def remove(self):
        """Removes the job's folder and what matfit wrote there."""
        shutil.rmtree(self.folder, ignore_errors=True)

    def check(self):
        """Raises JobError with matfit's own error line if the fit failed."""
        self.wait()
        if self._job is not None:
            return self._job.check()
        if self._error is not None:
            raise self._error
        code, lines = self._answer
        if code != 0:
            raise failure(self.command, code, lines)
