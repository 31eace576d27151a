"""`matfit bench-serve`: the page's latency (a saved file to its result, a slider to its preview) and memory."""

from __future__ import annotations

import json
import os
import time

import numpy as np

from matfit import params
from matfit.model import models

EXAMPLES = ("recoloured", "desaturated", "painted-highlight")  # the shipped edits the page is timed on


def serve_speed(
    model: models.Model, model_label: str, fits: int = 100, previews: int = 200, log=print, samples: int = 10
) -> str:
    """Returns the page's figures (Markdown): file saved -> result shown, slider -> preview, memory over many fits.

    Warm fit and latency are medians of `samples` fits; memory is read after the `samples` fits of the watched file
    that the latency measures, and again after `fits` of them (`fits` >= `samples`).

    The server runs in this process (`server.running`), the client is this process too, over HTTP on
    the loopback: the latency is measured from the watched file's write to the moment the client,
    told of the job by the page's event stream, reads the finished result, as the page does.
    """
    import tempfile
    import threading

    from matfit import shipped
    from matfit.app.serve.server import running
    from matfit.app.serve.studio import Studio

    examples = [str(shipped.EXAMPLES / f"{name}.png") for name in EXAMPLES]
    contents = []
    for path in examples:
        with open(path, "rb") as file:
            contents.append(file.read())
    studio = Studio(model, model_label)
    studio.worker.submit(studio.warm_up).result()
    folder = tempfile.mkdtemp(prefix="matfit-bench-serve-")
    watched = os.path.join(folder, "edit.png")
    with open(watched, "wb") as file:
        file.write(contents[0])
    warm = warm_fits(studio, examples, samples)
    events: list[tuple[float, dict]] = []
    with running(studio, watched) as url:
        threading.Thread(target=listen, args=(url, events), daemon=True).start()
        time.sleep(0.5)
        round_trips = preview_round_trips(url, previews)
        latency, first = saved_latency(url, watched, contents, events, samples)
        memory = {samples: resident_mib()}
        log(f"{fits} fits through the page")
        memory[fits] = resident_mib_after(url, watched, contents, events, samples, fits)
    studio.close()
    return "\n".join(
        [
            "| figure | value |",
            "|---|---|",
            f"| warm fit through the library, `matfit.Fitter.fit` (median of {samples}) | {np.median(warm):.3f} s |",
            f"| watched file saved -> first answer (the neural search's) read by the page's client (median of "
            f"{samples}) | {np.median(first):.3f} s |",
            f"| watched file saved -> result read by the page's client (median of {samples}) "
            f"| {np.median(latency):.3f} s |",
            f"| the page's own: saved -> result less the library's fit of the same picture (median of {samples}) "
            f"| {np.median(np.subtract(latency, warm)):.3f} s |",
            f"| slider -> neural preview round trip (median of {previews}) | {1e3 * np.median(round_trips):.1f} ms |",
            f"| resident memory after {samples} fits / after {fits} | {memory[samples]:.0f} / {memory[fits]:.0f} MiB "
            f"({100 * (memory[fits] / memory[samples] - 1):+.1f}%) |",
        ]
    )


def warm_fits(studio, examples: list[str], samples: int) -> list[float]:
    """Returns the seconds of `samples` warm fits through the library (`matfit.Fitter.fit`, the page's own) on the
    studio's worker, the k-th of the picture that the k-th save of the watched file writes."""
    warm = []
    for k in range(samples):  # the pictures in the order the watched file is saved with them (`saved_latency`)
        started = time.perf_counter()
        picture = examples[(k + 1) % len(examples)]
        studio.worker.submit(studio.fitter.fit, picture, settings=studio.settings).result()
        warm.append(time.perf_counter() - started)
    return warm


def listen(url: str, events: list[tuple[float, dict]]) -> None:
    """Appends (arrival time, message) to `events` for every message of the page's event stream, as the page
    listens."""
    import urllib.request

    with urllib.request.urlopen(url + "api/watch", timeout=600) as stream:
        for line in stream:
            if line.startswith(b"data: "):
                events.append((time.perf_counter(), json.loads(line[6:])))


def job_done(url: str, job: str, first: list[float] | None = None) -> dict:
    """Returns a job's answer once it is no longer queued or running, polled as the page polls; appends to `first`
    the moment (perf_counter) a result, the first stage's answer, was first read."""
    import urllib.request

    while True:
        with urllib.request.urlopen(f"{url}api/jobs/{job}", timeout=60) as reply:
            answer = json.loads(reply.read())
        if first is not None and not first and answer.get("result") is not None:
            first.append(time.perf_counter())
        if answer["state"] not in ("queued", "running"):
            return answer
        time.sleep(0.02)


def saved_latency(
    url: str, watched: str, contents: list[bytes], events: list, samples: int
) -> tuple[list[float], list[float]]:
    """Returns the seconds from each of `samples` saves of the watched file to its result read by the client, and to
    its first answer (the neural search's, shown at once) read by the client."""
    latency, firsts = [], []
    for k in range(samples):
        seen = len(events)
        started = time.perf_counter()
        with open(watched, "wb") as file:  # as an editor saves: the file rewritten in place
            file.write(contents[(k + 1) % len(contents)])
        while len(events) == seen:
            time.sleep(0.005)
        first: list[float] = []
        job_done(url, events[-1][1]["job"], first)
        latency.append(time.perf_counter() - started)
        firsts.append((first[0] if first else time.perf_counter()) - started)
    return latency, firsts


def preview_round_trips(url: str, previews: int) -> list[float]:
    """Returns the seconds of `previews` neural previews of random values, each a request and its PNG."""
    import urllib.request

    rng = np.random.default_rng(0)
    round_trips = []
    for _ in range(previews):
        body = json.dumps({"values": params.from_unit(rng.uniform(size=params.COUNT)).tolist()}).encode()
        started = time.perf_counter()
        request = urllib.request.Request(url + "api/preview", body, {"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=60) as reply:
            reply.read()
        round_trips.append(time.perf_counter() - started)
    return round_trips


def resident_mib_after(url: str, watched: str, contents: list[bytes], events: list, done: int, fits: int) -> float:
    """Returns this process's resident MiB once the watched file has been fitted `fits` times, `done` of them
    already."""
    for k in range(done + 1, fits + 1):
        with open(watched, "wb") as file:
            file.write(contents[k % len(contents)])
        seen = len(events)
        while len(events) == seen:
            time.sleep(0.005)
        job_done(url, events[-1][1]["job"])
    return resident_mib()


def resident_mib() -> float:
    """Returns this process's resident memory in MiB (Linux)."""
    with open("/proc/self/status") as status:
        line = next(line for line in status if line.startswith("VmRSS:"))
    return int(line.split()[1]) / 1024
