"""`matfit worker`: fits sent as JSON lines to one process answer what `matfit fit` writes; bad lines are errors."""

import json
import subprocess
import sys
import time

import pytest

from matfit import shipped
from matfit.app import worker

EDITED = str(shipped.EXAMPLES / "recoloured.png")
FIT_OPTIONS = ["--method", "nn", "--size", "32", "--spp", "16"]  # the extension tests' settings: a fit in seconds
TIMINGS = {"seconds", "fit_seconds", "wall_time_s"}


def without_timings(document):
    if isinstance(document, dict):
        return {key: without_timings(value) for key, value in document.items() if key not in TIMINGS}
    if isinstance(document, list):
        return [without_timings(value) for value in document]
    return document


class Worker:
    """A `matfit worker` process: `ask` writes one line and returns the answer."""

    def __init__(self):
        self.process = subprocess.Popen(
            [sys.executable, "-m", "matfit", "worker"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        assert json.loads(self.process.stdout.readline()) == worker.READY

    def ask(self, line: bytes) -> dict:
        self.process.stdin.write(line + b"\n")
        self.process.stdin.flush()
        return json.loads(self.process.stdout.readline())

    def fit(self, identifier, *arguments) -> dict:
        return self.ask(json.dumps({"id": identifier, "arguments": ["fit", *map(str, arguments)]}).encode())

    def close(self, seconds=30) -> int:
        self.process.stdin.close()
        code = self.process.wait(seconds)
        self.process.stdout.close()
        self.process.stderr.close()
        return code


def test_two_fits_in_one_worker_write_what_matfit_fit_writes(tmp_path):
    running = Worker()
    first = running.fit(1, EDITED, "-o", tmp_path / "first.json", *FIT_OPTIONS)
    second = running.fit("two", EDITED, "-o", tmp_path / "second.json", *FIT_OPTIONS)
    assert running.close() == 0
    assert first["id"] == 1 and first["exit"] == 0, first["output"]
    assert second["id"] == "two" and second["exit"] == 0, second["output"]
    assert second["output"].startswith(f"{tmp_path / 'second.json'}: nn, ")
    reference = tmp_path / "reference.json"
    subprocess.run([sys.executable, "-m", "matfit", "fit", EDITED, "-o", reference, *FIT_OPTIONS], check=True)
    expected = without_timings(json.loads(reference.read_text()))
    for name in ("first", "second"):  # bit for bit: every figure and value as JSON writes it
        assert without_timings(json.loads((tmp_path / f"{name}.json").read_text())) == expected, name


def test_bad_requests_are_answered_with_one_error_line_and_the_worker_goes_on(tmp_path):
    running = Worker()
    answers = {
        "not JSON": running.ask(b"not json"),
        "not an object": running.ask(b"[1, 2]"),
        "unknown field": running.ask(b'{"id": 1, "arguments": ["fit"], "shell": "rm -rf /"}'),
        "too long": running.ask(b'{"id": 2, "arguments": ["' + b"x" * (worker.MAX_REQUEST + 10) + b'"]}'),
        "not fit": running.ask(b'{"id": 3, "arguments": ["render", "--preset", "gold"]}'),
        "no command": running.ask(b'{"id": 4, "arguments": []}'),
        "not strings": running.ask(b'{"id": 5, "arguments": ["fit", 7]}'),
        "bad id": running.ask(b'{"id": [1], "arguments": ["fit"]}'),
        "bad option": running.fit(6, EDITED, "-o", tmp_path / "p.json", "--evals", "abc"),
        "no picture": running.fit(7, tmp_path / "missing.png", "-o", tmp_path / "p.json"),
    }
    assert running.close() == 0
    for kind, answer in answers.items():
        lines = answer["output"].splitlines()
        assert answer["exit"] == 2 and len(lines) == 1 and lines[0].startswith("error: "), (kind, answer)
    assert answers["unknown field"] == {
        "id": 1,
        "exit": 2,
        "output": "error: a request holds only id, arguments, not shell\n",
    }
    assert answers["too long"]["id"] is None and str(worker.MAX_REQUEST) in answers["too long"]["output"]
    assert answers["not fit"]["output"] == "error: the worker runs fit, not 'render'\n"
    assert answers["bad option"]["id"] == 6 and "--evals abc" in answers["bad option"]["output"]
    assert answers["no picture"]["id"] == 7 and "missing.png" in answers["no picture"]["output"]
    assert not (tmp_path / "p.json").exists()


def test_the_worker_ends_when_its_input_ends_during_a_fit(tmp_path):
    running = Worker()
    line = {"id": 1, "arguments": ["fit", EDITED, "-o", str(tmp_path / "p.json"), *FIT_OPTIONS]}
    running.process.stdin.write(json.dumps(line).encode() + b"\n")
    running.process.stdin.flush()
    time.sleep(1.0)  # the fit has started
    started = time.monotonic()
    code = running.close(seconds=10)
    assert code == 130 and time.monotonic() - started < 5
    assert not (tmp_path / "p.json").exists()


@pytest.mark.parametrize(
    "line, refusal",
    [
        (b"\xff\xfe", "one JSON object a line"),
        (b'{"id": true, "arguments": ["fit"]}', "id is a number or a string"),
        (b'{"id": 1, "arguments": "fit x.png"}', "a list of strings"),
    ],
)
def test_parse_refuses_what_is_not_a_request(line, refusal):
    _, arguments, why = worker.parse(line)
    assert arguments is None and refusal in why


def test_outside_a_worker_fit_gets_the_model_path_back():
    assert worker.model("some/model") == "some/model"


def test_a_fit_that_fails_keeps_the_warm_pool_unless_a_child_ended(monkeypatch):
    from matfit.errors import ImageError

    warm = worker.Warm()
    monkeypatch.setattr(worker, "_warm", warm)
    try:
        with pytest.raises(ImageError), worker.pool("scalar_rgb") as first:
            raise ImageError("the picture cannot be read")  # the picture's fault: the children are fine
        assert warm.pools["scalar_rgb"] is first and first.healthy()
        with worker.pool("scalar_rgb") as again:
            assert again is first
            first._children[0]._child.kill()
            first._children[0]._child.wait(timeout=30)
        assert not first.healthy()
        with pytest.raises(ImageError), worker.pool("scalar_rgb") as same:
            raise ImageError("a render failed")  # a child has ended: the pool is not kept for the next fit
        assert same is first and "scalar_rgb" not in warm.pools
    finally:
        warm.close()
