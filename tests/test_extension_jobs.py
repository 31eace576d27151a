"""The Blender extension's jobs (`blender/extension/jobs.py`, plain Python, no bpy): how long a fit is waited for.

`tests/test_blender_extension.py` runs the extension itself in bpy, where `make blender` installed it."""

from __future__ import annotations

import importlib.util
import json
import sys
import threading
import time

import pytest

from matfit import shipped

SOURCE = shipped.PACKAGE.parent / "blender" / "extension" / "jobs.py"
BASE = ["fit", "edited.png", "--size", "512", "--spp", "256"]  # what the extension sends, the fit options after it


@pytest.fixture
def jobs():
    """Returns the extension's jobs module, loaded from its file (the extension's package needs bpy); its worker
    stopped after the test."""
    spec = importlib.util.spec_from_file_location("matfit_extension_jobs", SOURCE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    yield module
    module.stop_workers()
    del sys.modules[spec.name]


def test_a_fit_is_waited_for_as_long_as_its_budgets_can_take(jobs):
    fit = jobs.FIT_SECONDS
    assert jobs.fit_seconds([*BASE, "-o", "p.json"]) == fit  # matfit's default budgets
    assert jobs.fit_seconds([*BASE, "--method", "nn", "--evals", "500", "--corrections", "0"]) == fit  # smaller ones
    assert jobs.fit_seconds([*BASE, "--evals", "101500"]) == pytest.approx(fit + 100_000 * jobs.STEPS["--evals"][1])
    assert jobs.fit_seconds([*BASE, "--refine=10", "--starts", "6"]) == pytest.approx(
        fit + 10 * jobs.STEPS["--refine"][1] + 2 * jobs.STEPS["--starts"][1]
    )
    # a --render output at --size and --spp: its samples
    assert jobs.fit_seconds([*BASE, "--render", "r.png"]) == pytest.approx(fit + 512**2 * 256 * jobs.SAMPLE_SECONDS)
    assert jobs.fit_seconds([*BASE, "--evals", "many"]) == fit  # matfit refuses it at once
    assert jobs.fit_seconds(BASE[:-1]) == fit


def test_a_worker_that_never_answers_is_given_up_after_what_the_fit_can_take_in_one_line(jobs, tmp_path, monkeypatch):
    # `bpy.ops.matfit.fit()` (a script, headless) waited 3600 s for a worker alive but never answering
    mute = tmp_path / "mute"  # says it is a worker, then answers every request with lines that are no answer
    mute.write_text(
        '#!/bin/sh\necho \'{"ready": "matfit worker", "protocol": 1}\'\n'
        'while read request; do echo \'{"id": "no such fit", "exit": 0}\'; echo \'not an answer\'; done\n'
    )
    mute.chmod(0o755)
    monkeypatch.setattr(jobs, "FIT_SECONDS", 2.0)
    job = jobs.WorkerJob(str(mute), [*BASE, "-o", str(tmp_path / "p.json")])
    worker = jobs._worker[0]
    started = time.monotonic()
    waiting = threading.Thread(target=job.wait, daemon=True)
    waiting.start()
    waiting.join(60)
    assert not waiting.is_alive(), "it still waits"
    assert 2.0 <= time.monotonic() - started < 30
    with pytest.raises(jobs.JobError) as raised:
        job.check()
    assert str(raised.value) == (
        f"matfit ({mute}) failed: error: its worker gave no answer in 2 s, the most this fit may take: it was ended, "
        "and the next fit starts a new one"
    )
    assert worker.code() is not None and jobs._worker[0] is None  # ended; the next fit starts another
    job.remove()


# A `matfit worker` that says it is ready late (a request is sent before), keeps each request, sends two stages'
# answers where asked, and its final answer once the file GO exists.
STAGED = """#!{python}
import json, os, sys, time
time.sleep(0.5)
print(json.dumps({{"ready": "matfit worker", "protocol": {protocol}}}), flush=True)
for line in sys.stdin:
    request = json.loads(line)
    with open({kept!r}, "a") as file:
        file.write(line)
    for stage, roughness in (("neural", 0.25), ("verified", 0.5)) if request.get("stages") else ():
        document = {{"params": {{"roughness": roughness}}}}
        print(json.dumps({{"id": request["id"], "stage": stage, "document": document}}), flush=True)
    while not os.path.exists({go!r}):
        time.sleep(0.05)
    print(json.dumps({{"id": request["id"], "exit": 0, "output": "done"}}), flush=True)
"""


@pytest.mark.parametrize("protocol", [1, 2])
def test_a_worker_of_protocol_2_is_asked_for_the_stages_and_each_is_handed_on_as_it_lands(jobs, tmp_path, protocol):
    kept, go = tmp_path / "requests", tmp_path / "go"
    staged = tmp_path / "staged"
    staged.write_text(STAGED.format(python=sys.executable, protocol=protocol, kept=str(kept), go=str(go)))
    staged.chmod(0o755)
    arguments = [*BASE, "-o", str(tmp_path / "p.json")]
    job = jobs.WorkerJob(str(staged), arguments)
    heard, deadline = [], time.monotonic() + 60
    while (len(heard) < 2 if protocol == 2 else not kept.exists()) and time.monotonic() < deadline:
        heard += job.stages()  # never waits
        time.sleep(0.05)
    assert job.poll() is None  # the fit runs on: its final answer waits for GO
    (request,) = map(json.loads, kept.read_text().splitlines())  # sent once, after the worker said it is ready
    if protocol == 1:  # a worker that knows no stages is not asked for them (it would refuse the field)
        assert request == {"id": 1, "arguments": arguments} and heard == [] and job.stages() == []
    else:
        assert request == {"id": 1, "arguments": arguments, "stages": True}
        assert heard == [("neural", {"params": {"roughness": 0.25}}), ("verified", {"params": {"roughness": 0.5}})]
    go.touch()
    job.wait()
    job.check()  # exit 0
    assert job.poll() == 0 and job.stages() == []
    job.remove()
