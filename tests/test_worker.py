"""`matfit worker`: fits sent as JSON lines to one process answer what `matfit fit` writes, each stage's answer first
where asked; bad lines are errors."""

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
    """A `matfit worker` process: `ask` writes one line and returns the answer (the stage lines before it: `stages`)."""

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
        self.stages = []
        while "exit" not in (answer := json.loads(self.process.stdout.readline())):
            self.stages.append(answer)
        return answer

    def fit(self, identifier, *arguments, **fields) -> dict:
        request = {"id": identifier, "arguments": ["fit", *map(str, arguments)], **fields}
        return self.ask(json.dumps(request).encode())

    def close(self, seconds=30) -> int:
        self.process.stdin.close()
        code = self.process.wait(seconds)
        self.process.stdout.close()
        self.process.stderr.close()
        return code


def test_two_fits_in_one_worker_write_what_matfit_fit_writes_and_one_asking_hears_each_stage_first(tmp_path):
    running = Worker()
    first = running.fit(1, EDITED, "-o", tmp_path / "first.json", *FIT_OPTIONS)
    assert running.stages == []  # not asked for: the final line alone, as a client of protocol 1 reads it
    second = running.fit("two", EDITED, "-o", tmp_path / "second.json", *FIT_OPTIONS, stages=True)
    heard = running.stages
    assert running.close() == 0
    assert first["id"] == 1 and first["exit"] == 0, first["output"]
    assert second["id"] == "two" and second["exit"] == 0, second["output"]
    *landed, summary = second["output"].splitlines()  # what matfit fit prints: each stage's answer, then the summary
    assert summary.startswith(f"{tmp_path / 'second.json'}: nn, ")
    assert [line.split(" answer: ")[0] for line in landed] == ["neural", "verified", "clean"], landed
    reference = tmp_path / "reference.json"
    subprocess.run([sys.executable, "-m", "matfit", "fit", EDITED, "-o", reference, *FIT_OPTIONS], check=True)
    expected = without_timings(json.loads(reference.read_text()))
    for name in ("first", "second"):  # bit for bit: every figure and value as JSON writes it
        assert without_timings(json.loads((tmp_path / f"{name}.json").read_text())) == expected, name
    # each stage's answer came as it landed, in order, before the final line
    assert [(line["id"], line["stage"]) for line in heard] == [("two", "neural"), ("two", "verified"), ("two", "clean")]
    neural, verified, clean = (line["document"] for line in heard)
    written = json.loads((tmp_path / "second.json").read_text())
    assert without_timings(clean) == without_timings(written)  # the last stage's is the params.json written
    kept = written["verification"]["kept"]
    assert without_timings(verified["verification"]) == without_timings(written["verification"])
    assert verified["mitsuba_rmse"] == written["verification"]["mitsuba_rmse"][kept]
    assert "mitsuba_rmse" not in neural and "verification" not in neural  # not yet checked in Mitsuba
    assert neural["neural_rmse"] == written["start_rmse"]  # --method nn: the search's answer is its best start
    assert neural["params"] != verified["params"] != clean["params"]  # each stage changed the answer here


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
        "no picture given": running.ask(b'{"id": 8, "arguments": ["fit"]}'),
    }
    assert running.close() == 0
    for kind, answer in answers.items():
        lines = answer["output"].splitlines()
        assert answer["exit"] == 2 and len(lines) == 1 and lines[0].startswith("error: "), (kind, answer)
    assert answers["unknown field"] == {
        "id": 1,
        "exit": 2,
        "output": "error: a request holds only id, arguments, stages, not shell\n",
    }
    assert answers["too long"]["id"] is None and str(worker.MAX_REQUEST) in answers["too long"]["output"]
    assert answers["not fit"]["output"] == "error: the worker runs fit, not 'render'\n"
    assert answers["bad option"]["id"] == 6 and "--evals abc" in answers["bad option"]["output"]
    assert answers["no picture"]["id"] == 7 and "missing.png" in answers["no picture"]["output"]
    assert answers["no picture given"]["output"] == (
        "error: matfit fit needs the edited picture: give its path (`matfit fit --help` says more)\n"
    )
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
        (b'{"id": 1, "arguments": ["fit", "x.png"], "stages": "yes"}', '"stages" is true'),
    ],
)
def test_parse_refuses_what_is_not_a_request(line, refusal):
    _, arguments, why = worker.parse(line)
    assert arguments is None and refusal in why


def test_outside_a_worker_fit_gets_the_model_path_back():
    assert worker.model("some/model") == "some/model"


def test_outside_a_worker_each_fit_gets_a_new_fitter_of_the_model_path_closed_after_it():
    with worker.fitter("some/model", "scalar_rgb", verify=False) as made:
        assert made.model_path == "some/model" and made._model is None and made._pool is None  # nothing loaded yet
    with worker.fitter("some/model", "scalar_rgb", verify=True) as started:
        assert started._pool is not None  # Mitsuba starts while the fit checks and loads
    assert started._pool is None


@pytest.fixture(scope="module")
def small_model(tmp_path_factory):
    """Returns a model folder of a random 32 px decoder and one random encoder: fits in a second, not well."""
    import dataclasses

    from matfit.model import architectures, weight_files
    from tests.helpers import random_model

    model = random_model()
    folder = tmp_path_factory.mktemp("small-model")
    weight_files.save(str(folder / "decoder.msgpack"), model.decoder)
    description = architectures.architecture("encoder-8", model.resolution)
    encoder = dataclasses.replace(model.encoders[8], description=description)
    weight_files.save(str(folder / "encoder-8.msgpack"), encoder)
    return str(folder)


def test_a_fit_that_fails_keeps_the_warm_fitter_and_its_pool_unless_a_child_ended(monkeypatch, small_model, tmp_path):
    from matfit.errors import ImageError, RenderError

    warm = worker.Warm()
    monkeypatch.setattr(worker, "_warm", warm)
    picture = str(shipped.EXAMPLES / "recoloured.png")
    try:
        with worker.fitter(small_model, "scalar_rgb", verify=True) as first:
            pool = first._pool
            with pytest.raises(ImageError, match="not a file"):
                first.fit(str(tmp_path / "missing.png"))  # the picture's fault: the children are fine
        assert warm.fitters["scalar_rgb"] is first and first._pool is pool and pool.healthy()
        with worker.fitter(small_model, "scalar_rgb", verify=True) as again:
            assert again is first and again.model is next(iter(warm.models.values()))  # the model loaded once
        for child in pool._children:
            child._child.kill()
            child._child.wait(timeout=30)
        with worker.fitter(small_model, "scalar_rgb", verify=True) as same, pytest.raises(RenderError):
            same.fit(picture)  # its renders fail: the children ended
        assert same is first and first._pool is None  # ended: the next verified fit starts another pool
        assert first.fit(picture, corrections=0).mitsuba_rmse is not None and first._pool.healthy()
    finally:
        warm.close()


def test_a_changed_model_ends_every_fitter_of_the_one_before(monkeypatch, small_model):
    import os
    from pathlib import Path

    warm = worker.Warm()
    monkeypatch.setattr(worker, "_warm", warm)
    try:
        with worker.fitter(small_model, "scalar_rgb", verify=False) as first:
            pass
        with worker.fitter(small_model, None, verify=False) as other:
            assert other.model is first.model  # loaded once for every variant
        later = time.time_ns() + 10**9
        os.utime(Path(small_model) / "decoder.msgpack", ns=(later, later))  # trained again: its files changed
        with worker.fitter(small_model, "scalar_rgb", verify=False) as second:
            assert second is not first and second.model is not first.model
        assert list(warm.fitters) == ["scalar_rgb"] and len(warm.models) == 1  # the old model is held by nothing
    finally:
        warm.close()
