"""The processes that render a dataset's images: the chunk protocol every renderer of `dataset_writing` speaks.

A task is one chunk of `CHUNK` samples (their indices, parameter values and render seeds); its
result is (indices, float16 images). A worker makes its renderer once (`init_worker`: one Dr.Jit
thread, so every image is bit-identical whatever renders it, and deaf to the terminal's Ctrl-C)
and renders chunks with it (`render_chunk`). Three executors yield the results of a list of
tasks: this very process (`in_this_process`), child interpreters fed over pipes
(`in_worker_processes`, whose child's main is `serve_chunks`), or Ray tasks (`cluster.ray_results`).
"""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import threading
from collections.abc import Iterator

import numpy as np

from matfit.errors import DatasetError, RenderError
from matfit.model.dataset import (
    IMAGE_DTYPE,
    Settings,
)
from matfit.rendering import process

MAX_WORKERS = 64


# Render processes sharing one GPU (cuda_ad_rgb): one process leaves the GPU idle between its small launches, several
# fill it; the count with the highest steady rate at 128 px, 16 spp (docs/training.md#gpu).
GPU_WORKERS = 12


CHUNK = 16


def default_workers(variant: str) -> int:
    """Returns how many render processes a dataset renders with unless told: GPU_WORKERS on a GPU, else one per core."""
    from matfit.rendering.engine import CUDA_VARIANT

    return GPU_WORKERS if variant == CUDA_VARIANT else min(os.cpu_count() or 1, MAX_WORKERS)


# One renderer per worker process, made by `init_worker`.
_worker_renderer = None


def init_worker(
    resolution: int, spp: int, variant: str, ignore_interrupts: bool = True, new_session: bool = True
) -> None:
    """Makes this process's renderer, with one Dr.Jit thread; a worker also ignores Ctrl-C."""
    global _worker_renderer
    # Mitsuba catches SIGINT during a render, cancels it and returns an incomplete image. A worker
    # ignores SIGINT and runs in its own session (a Ray worker already runs in a process group of
    # its own), so it never sees the terminal's Ctrl-C: the parent catches it and stops the
    # workers, so no cancelled image is ever stored.
    if ignore_interrupts:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    if new_session:
        os.setsid()
    from matfit.rendering.engine import Renderer, mitsuba

    # One rendering thread per process: Dr.Jit's threads add samples into the film in an order
    # that varies from run to run, which changes the last bit of a few pixels. One thread keeps
    # every image bit-identical; several worker processes keep every core busy.
    mitsuba(variant)
    import drjit

    drjit.set_thread_count(1)
    _worker_renderer = Renderer(resolution, spp, variant)


def render_chunk(task: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Returns (indices, float16 images) of one task (indices, parameter values, render seeds)."""
    indices, values, seeds = task
    assert _worker_renderer is not None, "init_worker made it"
    images = np.stack([_worker_renderer.render(v, seed=int(s)) for v, s in zip(values, seeds, strict=True)])
    return indices, images.astype(IMAGE_DTYPE)


Task = tuple[np.ndarray, np.ndarray, np.ndarray]


Results = Iterator[tuple[np.ndarray, np.ndarray]]


@contextlib.contextmanager
def in_this_process(settings: Settings, tasks: list[Task], workers: int) -> Iterator[Results]:
    init_worker(settings.resolution, settings.spp, settings.variant, ignore_interrupts=False, new_session=False)
    yield map(render_chunk, tasks)


class _Worker:
    """One rendering child process of `render_missing`: `serve_chunks` in a new interpreter, spoken to over two pipes
    (`process.start_child`, as the render process of a fit).

    The child runs in a session of its own: the terminal's Ctrl-C reaches only the parent, which stops the workers, so
    no render cancelled by Mitsuba's own SIGINT handler is ever stored. It sees its requests end as soon as this
    process ends, however it ends (`kill -9` included): it then finishes the render in hand and leaves without a word
    (`serve_chunks`).
    """

    def __init__(self, settings: Settings):
        self.process, self.requests, self.replies = process.start_child(
            "matfit.model.dataset_workers", "serve_chunks", settings.resolution, settings.spp, settings.variant
        )

    def render(self, task: Task) -> tuple[np.ndarray, np.ndarray]:
        """Returns (indices, float16 images) of one task, rendered by the child."""
        indices, values, seeds = task
        try:
            header = {"indices": [int(i) for i in indices], "seeds": [int(s) for s in seeds]}
            process.write_message(self.requests, header, np.asarray(values, np.float64))
            reply, images = process.read_message(self.replies)
        except (OSError, EOFError, ValueError):
            raise DatasetError(
                f"a rendering process ended unexpectedly (exit code {self.process.poll()}): "
                "run the same command to resume"
            ) from None
        if "error" in reply:
            raise RenderError(reply["error"])
        if images is None:
            raise RenderError("a rendering process answered without images")
        return indices, images

    def stop(self) -> None:
        """Ends the child at once (its finished images are stored already) and waits for it."""
        self.process.kill()
        self.process.wait()

    def close(self) -> None:
        """Closes this side's pipes (after `stop`, once nothing reads or writes them)."""
        for file in (self.requests, self.replies):
            with contextlib.suppress(OSError):
                file.close()


def _render_tasks(worker: _Worker, tasks: queue.SimpleQueue, results: queue.SimpleQueue) -> None:
    """A thread's work: has `worker` render tasks until none is left, putting each result (or failure) in `results`."""
    while True:
        try:
            task = tasks.get_nowait()
        except queue.Empty:
            return
        try:
            results.put(worker.render(task))
        except BaseException as error:  # handed to the main thread, which raises it
            results.put(error)
            return


@contextlib.contextmanager
def in_worker_processes(settings: Settings, tasks: list[Task], workers: int) -> Iterator[Results]:
    """Yields the results of `tasks` rendered by `workers` child processes, each fed by a thread of this process."""
    pending: queue.SimpleQueue = queue.SimpleQueue()
    for task in tasks:
        pending.put(task)
    results: queue.SimpleQueue = queue.SimpleQueue()
    children: list[_Worker] = []
    threads: list[threading.Thread] = []

    def collected() -> Results:
        for _ in tasks:
            result = results.get()
            if isinstance(result, BaseException):
                raise result
            yield result

    try:
        for _ in range(min(workers, len(tasks))):
            children.append(_Worker(settings))
            threads.append(threading.Thread(target=_render_tasks, args=(children[-1], pending, results), daemon=True))
            threads[-1].start()
        yield collected()
    finally:
        for child in children:
            child.stop()
        for thread in threads:
            thread.join()
        for child in children:
            child.close()


def serve_chunks(requests: int, replies: int, resolution: int, spp: int, variant: str) -> None:
    """A rendering worker of `render_missing` (`_Worker`'s child): renders each chunk read from the file descriptor
    `requests` and writes its images to `replies` until the requests end, then exits.

    Its parent gone (the requests end, or a reply meets a closed pipe), it ends without a word: no traceback, and no
    teardown of Mitsuba (`os._exit`) that could print anything.
    """
    with contextlib.suppress(BrokenPipeError):
        _answer_chunks(requests, replies, resolution, spp, variant)
    os._exit(0)


def _answer_chunks(requests: int, replies: int, resolution: int, spp: int, variant: str) -> None:
    with os.fdopen(requests, "rb") as incoming, os.fdopen(replies, "wb") as outgoing:
        try:
            init_worker(resolution, spp, variant, new_session=False)
        except Exception as error:  # RenderError, or Mitsuba failing to start: the parent reports it in one line
            process.write_message(outgoing, {"error": f"a rendering process could not start: {error}"})
            return
        while True:
            try:
                header, values = process.read_message(incoming)
            except (EOFError, OSError, ValueError):  # the parent closed its end, or ended
                return
            if values is None:  # the parent sends the values with every task
                process.write_message(outgoing, {"error": "a rendering task came without parameter values"})
                continue
            task = (np.array(header["indices"], np.int64), values, np.array(header["seeds"], np.int64))
            try:
                _, images = render_chunk(task)
            except Exception as error:
                process.write_message(outgoing, {"error": f"Mitsuba failed: {type(error).__name__}: {error}"})
                continue
            process.write_message(outgoing, {"done": True}, images)
