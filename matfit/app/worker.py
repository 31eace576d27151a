"""`matfit worker`: one process that runs `matfit fit` again and again, its model and Mitsuba kept warm.

The Blender extension starts it once a session and sends it each fit (docs/blender.md#the-extension).
It reads one JSON request a line on standard input, `{"id": 1, "arguments": ["fit", PICTURE, "-o", OUT,
...]}`, runs exactly what `matfit fit` with those arguments runs (the same Typer app, in this process),
and answers one JSON line on standard output, `{"id": 1, "exit": code, "output": what matfit fit printed}`.
A request with `"stages": true` (protocol 2) also hears each stage's answer as it lands, before that final line:
`{"id": 1, "stage": "neural", "document": {...}}`, then "verified", "clean" ("refined"), as many as the fit runs
(none for a `--scene` fit or several pictures), `document` the stage's params.json as if the fit ended there
(`matfit.Fit.document`; the last stage's is the params.json written, but for its timings). A stage line has no
"exit", and a request without "stages" hears the final line alone, as in protocol 1.
Its first line, before any request, is `{"ready": "matfit worker", "protocol": 2}`. Between requests it
keeps (`Warm`) the model loaded (by path, as long as its files are unchanged) and one `matfit.Fitter` (and
so one render pool) per variant, so only the first fit pays for loading them; a fit that fails keeps the
pool while every child runs (the picture was at fault) and closes it otherwise (the next fit starts another).
Only `fit` is run; anything else, or a line that is not such a request (not JSON, unknown fields, longer
than MAX_REQUEST), is answered with exit code 2 and one `error:` line, never a crash. The worker ends when
its standard input ends: between fits at once, during a fit at once too (`on_close`: the `matfit` process
ends as Ctrl-C would end it).

Nothing heavy is imported here: `fit_command` asks `fitter` for the `matfit.Fitter` to fit with, the
worker's warm one while `serve` runs (its model loaded, its render pool running), and a new one (closed
after the fit) otherwise.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import queue
import threading
import traceback
from collections.abc import Callable, Iterator
from typing import IO, Any

PROTOCOL = 2  # 2: a request may ask for the stages' answers ("stages": true)
READY = {"ready": "matfit worker", "protocol": PROTOCOL}
MAX_REQUEST = 1 << 20  # bytes of one request line: a fit's arguments are a few hundred
COMMANDS = ("fit",)
FIELDS = ("id", "arguments", "stages")


@dataclasses.dataclass(frozen=True)
class Request:
    """One request line read: the command line to run, and whether each stage's answer is written as it lands."""

    arguments: list[str]
    stages: bool = False


class Warm:
    """What the worker keeps between fits: the model by (path, its files' sizes and times), a `matfit.Fitter` a
    variant (its render pool running, its model the one kept)."""

    def __init__(self) -> None:
        self.models: dict[tuple[str, tuple[Any, ...]], Any] = {}
        self.fitters: dict[str | None, Any] = {}

    def close(self) -> None:
        for each in self.fitters.values():
            each.close()
        self.fitters.clear()
        self.models.clear()


_warm: Warm | None = None  # set while `serve` runs
_heard: Callable[[Any], None] | None = None  # writes a stage's answer line, while a request that asked for them runs


@contextlib.contextmanager
def fitter(path: str, variant: str | None, *, verify: bool) -> Iterator[Any]:
    """Yields the `matfit.Fitter` of one `matfit fit` with the model folder `path`: in a worker, its warm one (the
    model loaded once, the render pool kept between fits: `Fitter` ends a pool that lost a child and starts another);
    outside a worker, or for a model that cannot be loaded (the fit says why, in its own order), a new fitter closed
    after the fit, its render pool started now when `verify`."""
    import matfit

    loaded = model(path)
    if _warm is None or isinstance(loaded, str):
        with matfit.Fitter(path, verify=verify and _warm is None, variant=variant) as made:
            yield made
        return
    for kept, each in list(_warm.fitters.items()):  # one model at a time: a fitter of another is ended
        if each.model is not loaded:
            each.close()
            del _warm.fitters[kept]
    warm = _warm.fitters.get(variant)
    if warm is None:
        warm = _warm.fitters[variant] = matfit.Fitter(loaded, verify=verify, variant=variant)
    yield warm


def model(path: str) -> Any:
    """Returns the model to fit with: in a worker, the loaded model of `path` (loaded once, again when its files
    change); otherwise, or when it cannot be loaded, the path itself, which the fit loads and reports on as ever."""
    if _warm is None:
        return path
    key = (path, _stamp(path))
    if key not in _warm.models:
        import matfit
        from matfit.errors import MatfitError

        try:
            loaded = matfit.load_model(path)
        except (MatfitError, OSError):  # the fit itself says what is wrong, in its own order
            return path
        _warm.models = {key: loaded}  # one model at a time: a model's weights are hundreds of MB
    return _warm.models[key]


def _stamp(path: str) -> tuple:
    """Returns the names, sizes and modification times of the files in the model directory `path` (() if none)."""
    try:
        with os.scandir(path) as entries:
            found = [(e.name, e.stat().st_size, e.stat().st_mtime_ns) for e in entries if e.is_file()]
    except OSError:
        return ()
    return tuple(sorted(found))


def answers(printed: Callable[[Any], None]) -> Callable[[Any], None]:
    """Returns what `matfit fit` hears each stage's answer (a `matfit.Fit`) with: `printed`, which prints its line,
    and in a worker whose request asked for the stages, the stage's line written to the worker's replies too."""
    heard = _heard
    if heard is None:
        return printed

    def both(fitted: Any) -> None:
        printed(fitted)
        heard(fitted)

    return both


def error_reply(identifier: Any, message: str) -> dict:
    return {"id": identifier, "exit": 2, "output": f"error: {message}\n"}


def parse(line: bytes) -> tuple[Any, Request | None, str | None]:
    """Returns (the request's id, the `Request`, None), or (id or None, None, why it is refused) for a bad line."""
    if len(line) > MAX_REQUEST:
        return None, None, f"a request line is longer than {MAX_REQUEST} bytes"
    try:
        request = json.loads(line)
    except (ValueError, RecursionError):  # not JSON, not UTF-8, nested too deeply
        return None, None, 'a request is one JSON object a line: {"id": 1, "arguments": ["fit", ...]}'
    if not isinstance(request, dict):
        return None, None, 'a request is one JSON object a line: {"id": 1, "arguments": ["fit", ...]}'
    identifier = request.get("id")
    if isinstance(identifier, bool) or not isinstance(identifier, (int, str, type(None))):
        return None, None, "a request's id is a number or a string"
    unknown = sorted(set(request) - set(FIELDS))
    if unknown:
        return identifier, None, f"a request holds only {', '.join(FIELDS)}, not {', '.join(unknown)}"
    arguments = request.get("arguments")
    if not isinstance(arguments, list) or not all(isinstance(word, str) for word in arguments):
        return identifier, None, 'a request\'s "arguments" is a list of strings, such as ["fit", "edited.png"]'
    if not arguments or arguments[0] not in COMMANDS:
        named = repr(arguments[0]) if arguments else "nothing"
        return identifier, None, f"the worker runs {' or '.join(COMMANDS)}, not {named}"
    stages = request.get("stages", False)
    if not isinstance(stages, bool):
        return identifier, None, "a request's \"stages\" is true (write each stage's answer as it lands) or false"
    return identifier, Request(arguments, stages), None


def run(app: Callable[..., Any], arguments: list[str]) -> tuple[int, str]:
    """Returns (exit code, standard output and error together) of the command line `arguments` run in this process."""
    buffer = io.BytesIO()
    captured = io.TextIOWrapper(buffer, encoding="utf-8", errors="replace", write_through=True)
    with contextlib.redirect_stdout(captured), contextlib.redirect_stderr(captured):
        try:
            code = app(arguments, standalone_mode=False)
        except SystemExit as exit:  # what Click raises where standalone_mode has no say
            code = exit.code if isinstance(exit.code, int) else (0 if exit.code is None else 1)
        except Exception:  # a bug, not the user's error: `matfit fit` would print its traceback and exit 1
            captured.write(traceback.format_exc())
            code = 1
    captured.flush()
    return (code if isinstance(code, int) else 0), buffer.getvalue().decode("utf-8", errors="replace")


def lines(requests: IO[bytes]) -> Iterator[bytes]:
    """Yields the lines of `requests`, a line longer than MAX_REQUEST cut to MAX_REQUEST + 1 bytes (the rest read
    and dropped), until it ends."""
    while True:
        line = requests.readline(MAX_REQUEST + 1)
        if not line:
            return
        if len(line) > MAX_REQUEST and not line.endswith(b"\n"):
            rest = line
            while rest and not rest.endswith(b"\n"):
                rest = requests.readline(MAX_REQUEST)
        yield line


def serve(
    app: Callable[..., Any], requests: IO[bytes], replies: IO[str], on_close: Callable[[], None] | None = None
) -> int:
    """Answers each request line of `requests` on `replies` until `requests` ends; returns 0.

    A thread reads the requests, so their end is seen during a fit too: `on_close` is then called from that thread
    (the command line's ends the process at once; None: the fit in hand is finished first).
    """
    global _warm, _heard
    incoming: queue.Queue[bytes | None] = queue.Queue()
    busy = threading.Event()

    def read() -> None:
        for line in lines(requests):
            incoming.put(line)
        incoming.put(None)
        if busy.is_set() and on_close is not None:
            on_close()

    _warm = Warm()
    try:
        write(replies, READY)
        threading.Thread(target=read, name="matfit-worker-requests", daemon=True).start()
        while (line := incoming.get()) is not None:
            if not line.strip():
                continue
            busy.set()
            identifier, request, refusal = parse(line)
            if request is None:
                reply = error_reply(identifier, refusal or "a bad request")
            else:
                _heard = stage_writer(replies, identifier) if request.stages else None
                try:
                    code, output = run(app, request.arguments)
                finally:
                    _heard = None
                reply = {"id": identifier, "exit": code, "output": output}
            busy.clear()
            write(replies, reply)
    finally:
        _warm.close()
        _warm = None
    return 0


def stage_writer(replies: IO[str], identifier: Any) -> Callable[[Any], None]:
    """Returns what writes a stage's answer (a `matfit.Fit`) of the request `identifier` as one line on `replies`: the
    stage's name and its params.json document, as the file would hold it (`Fit.to_json`)."""

    def heard(fitted: Any) -> None:
        write(replies, {"id": identifier, "stage": fitted.stage, "document": json.loads(fitted.to_json())})

    return heard


def write(replies: IO[str], reply: dict) -> None:
    replies.write(json.dumps(reply) + "\n")
    replies.flush()
