"""`matfit bench-serve`: the page's latency (a saved file to its result, a slider to its preview) and memory."""

from __future__ import annotations

import json
import os
import time

import numpy as np

from matfit import params
from matfit.model import models


def serve_speed(
    model: models.Model, model_label: str, fits: int = 100, previews: int = 200, log=print, samples: int = 10
) -> str:
    """Returns the page's figures (Markdown): file saved -> result shown, slider -> preview, memory over many fits.

    Warm fit and latency are medians of `samples` fits; memory is read after `samples` fits and after `fits`.

    The server runs in this process (`server.running`), the client is this process too, over HTTP on
    the loopback: the latency is measured from the watched file's write to the moment the client,
    told of the job by the page's event stream, reads the finished result, as the page does.
    """
    import tempfile
    import threading
    import urllib.request

    from matfit import shipped
    from matfit.app.serve.server import running
    from matfit.app.serve.studio import Studio
    from matfit.fit import fitfile

    examples = [str(shipped.EXAMPLES / f"{name}.png") for name in ("recoloured", "desaturated", "painted-highlight")]
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
    warm = []
    for k in range(samples):
        started = time.perf_counter()
        renderer = studio.renderer(model.resolution)
        studio.worker.submit(fitfile.fit_file, examples[k % 3], model, studio.settings, renderer=renderer).result()
        warm.append(time.perf_counter() - started)
    events: list[tuple[float, dict]] = []

    def listen(url: str) -> None:
        with urllib.request.urlopen(url + "api/watch", timeout=600) as stream:
            for line in stream:
                if line.startswith(b"data: "):
                    events.append((time.perf_counter(), json.loads(line[6:])))

    def job_done(url: str, job: str) -> dict:
        while True:
            with urllib.request.urlopen(f"{url}api/jobs/{job}", timeout=60) as reply:
                answer = json.loads(reply.read())
            if answer["state"] not in ("queued", "running"):
                return answer
            time.sleep(0.02)

    with running(studio, watched) as url:
        threading.Thread(target=listen, args=(url,), daemon=True).start()
        time.sleep(0.5)
        latency = []
        for k in range(samples):
            seen = len(events)
            started = time.perf_counter()
            with open(watched, "wb") as file:  # as an editor saves: the file rewritten in place
                file.write(contents[(k + 1) % len(contents)])
            while len(events) == seen:
                time.sleep(0.005)
            job_done(url, events[-1][1]["job"])
            latency.append(time.perf_counter() - started)
        rng = np.random.default_rng(0)
        round_trips = []
        for _ in range(previews):
            body = json.dumps({"values": params.from_unit(rng.uniform(size=params.COUNT)).tolist()}).encode()
            started = time.perf_counter()
            request = urllib.request.Request(url + "api/preview", body, {"Content-Type": "application/json"})
            with urllib.request.urlopen(request, timeout=60) as reply:
                reply.read()
            round_trips.append(time.perf_counter() - started)
        log(f"{fits} fits through the page")
        memory = {}
        for k in range(1, fits + 1):
            with open(watched, "wb") as file:
                file.write(contents[k % len(contents)])
            seen = len(events)
            while len(events) == seen:
                time.sleep(0.005)
            job_done(url, events[-1][1]["job"])
            if k in (samples, fits):
                memory[k] = resident_mib()
    studio.close()
    return "\n".join(
        [
            "| figure | value |",
            "|---|---|",
            f"| warm fit through the library, the CLI's path (median of {samples}) | {np.median(warm):.3f} s |",
            f"| watched file saved -> result read by the page's client (median of {samples}) "
            f"| {np.median(latency):.3f} s |",
            f"| slider -> neural preview round trip (median of {previews}) | {1e3 * np.median(round_trips):.1f} ms |",
            f"| resident memory after {samples} fits / after {fits} | {memory[samples]:.0f} / {memory[fits]:.0f} MiB "
            f"({100 * (memory[fits] / memory[samples] - 1):+.1f}%) |",
        ]
    )


def resident_mib() -> float:
    """Returns this process's resident memory in MiB (Linux)."""
    with open("/proc/self/status") as status:
        line = next(line for line in status if line.startswith("VmRSS:"))
    return int(line.split()[1]) / 1024
