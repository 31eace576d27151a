"""Rendering a dataset's chunks as Ray tasks, on a Ray started for the run or on a cluster.

`render_missing(dataset, ray_address=...)` hands its chunks here instead of to a local process
pool. Each Ray task renders one chunk (16 indices) exactly as a pool worker does, in a worker
process with one Dr.Jit thread that ignores SIGINT, and returns the images; the driver (the
process that runs `render_missing`) stores them through the dataset's done-flag protocol as it
does for the pool. So the bytes are the same whatever renders them, and:

- kill -9 of a worker (or a lost node): Ray runs the task again elsewhere, up to RETRIES times;
  the task is a pure function of (settings, indices), so the retry gives the same images;
- kill -9 of the driver or of the whole cluster: what was stored is on disk with its flags, the
  chunks in flight are rendered again by the next run.

Why the images travel through Ray's object store rather than being written by the workers into
shared storage: the driver is the dataset's only writer, so the done flags need no locking, the
dataset can live on the driver's local disk (no shared file system on the cluster), and two
workers never write the same memory page of done.npy, which on NFS would lose flags. The cost is
the transfer into the driver, measured by `python -m matfit.model.cluster` (docs/training.md#ray): far below what one
driver can absorb until a cluster has hundreds of cores.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import socket
import time
from collections.abc import Iterator
from types import ModuleType

import numpy as np

from matfit.model import dataset, dataset_workers
from matfit.model.dataset import DatasetError, Settings
from matfit.model.dataset_workers import Results, Task

# A task whose worker dies (kill -9, out of memory, a node lost) is run again this many times.
RETRIES = 3
# Tasks queued per CPU of the cluster: enough to keep every worker busy while the driver stores,
# few enough that a killed driver loses little work and the object store stays small.
IN_FLIGHT_PER_CPU = 2
LOCAL, AUTO = "local", "auto"
CONNECT_TIMEOUT = 5.0
WORKER_NICENESS = "RAY_worker_niceness"

# The settings the renderer of this worker process was made with (see `_render_task`).
_worker_settings: Settings | None = None


def require_ray() -> ModuleType:
    """Returns the `ray` module, or raises DatasetError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise DatasetError(
            "--ray needs Ray, an optional extra: pip install -e '.[cluster]' (or pip install 'ray>=2.60,<3')"
        ) from None
    return ray


def check(address: str) -> None:
    """Raises DatasetError unless Ray is installed and something listens at `address`.

    Ray itself retries an unreachable address for minutes; a plain TCP connection answers in
    seconds, before the command has written anything.
    """
    require_ray()
    if address in (LOCAL, AUTO):
        return
    host, colon, port = address.split("://")[-1].rpartition(":")
    if not colon or not host or not port.isdigit():
        raise DatasetError(
            f"--ray {address!r} is not a Ray address: use {LOCAL}, {AUTO}, HOST:PORT (e.g. 10.0.0.5:6379) or ray://HOST:10001"
        )
    try:
        with socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT):
            pass
    except OSError as error:
        raise DatasetError(
            f"no Ray answers at {address} ({error.strerror or error}): "
            f"start one there with `ray start --head`, or pass --ray {LOCAL}"
        ) from None


def _render_task(settings: Settings, task: Task) -> tuple[np.ndarray, np.ndarray]:
    """Runs in a Ray worker: renders one chunk, making the worker's renderer on its first chunk."""
    global _worker_settings
    if _worker_settings != settings:
        dataset_workers.init_worker(settings.resolution, settings.spp, settings.variant, new_session=False)
        _worker_settings = settings
    return dataset_workers.render_chunk(task)


@contextlib.contextmanager
def connect(address: str, workers: int) -> Iterator[ModuleType]:
    """Connects to the Ray at `address` ("local": a new one of `workers` CPUs) for the block."""
    ray = require_ray()
    if ray.is_initialized():  # the caller's own connection: use it, leave it open
        yield ray
        return
    options = {"num_cpus": workers, "include_dashboard": False} if address == LOCAL else {}
    # Ray lowers its workers' priority by 15 nice levels from that of the process starting Ray (its
    # worker_niceness): on a busy machine they would then fall far behind a local pool's workers,
    # which run at the caller's priority. A Ray started for the run keeps them at that priority
    # (unless RAY_worker_niceness says otherwise); a cluster's own setting is left alone.
    niceness = os.environ.get(WORKER_NICENESS)
    if address == LOCAL and niceness is None:
        os.environ[WORKER_NICENESS] = "0"
    try:
        ray.init(address=address, logging_level=logging.ERROR, log_to_driver=False, **options)
    except (ConnectionError, ValueError, RuntimeError) as error:
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise DatasetError(
            f"cannot connect to Ray at {address!r} ({first_line}): start one with `ray start --head`, "
            f"pass its address, or pass --ray {LOCAL}"
        ) from None
    finally:
        if niceness is None:
            os.environ.pop(WORKER_NICENESS, None)
    try:
        yield ray
    finally:
        ray.shutdown()


@contextlib.contextmanager
def ray_results(settings: Settings, tasks: list[Task], workers: int, address: str = LOCAL) -> Iterator[Results]:
    """Yields the (indices, images) of every task as Ray finishes them, in any order."""
    with connect(address, workers) as ray:
        yield _submit_and_collect(ray, settings, tasks)


def _submit_and_collect(ray, settings: Settings, tasks: list[Task]) -> Results:
    render = ray.remote(num_cpus=1, max_retries=RETRIES)(_render_task)
    queue = iter(tasks)
    pending: list = []
    while True:
        # Read again after every chunk, so that nodes that join (an autoscaler) get work too.
        limit = IN_FLIGHT_PER_CPU * max(1, int(ray.cluster_resources().get("CPU", 1)))
        pending.extend(render.remote(settings, task) for task in itertools.islice(queue, max(0, limit - len(pending))))
        if not pending:
            return
        ready, pending = ray.wait(pending, num_returns=1)
        try:
            result = ray.get(ready[0])
        except ray.exceptions.RayTaskError as error:
            raise DatasetError(
                f"a Ray worker could not render: {error.cause!r}; fix it on that node and run the same command"
            ) from None
        except ray.exceptions.RayError as error:
            raise DatasetError(
                f"Ray lost a chunk {RETRIES + 1} times ({type(error).__name__}); what was rendered is saved: "
                "run the same command to resume"
            ) from None
        yield result


def measure_transfer(resolution: int, chunks: int = 200, workers: int = 2) -> dict:
    """Returns how fast one driver takes chunks of float16 images from Ray workers (no rendering).

    The figure bounds the cluster a single driver can serve: chunks/s x CHUNK images per second.
    """
    shape = (dataset_workers.CHUNK, resolution, resolution, 3)
    with connect(LOCAL, workers) as ray:

        @ray.remote(num_cpus=1)
        def chunk(index: int) -> tuple[np.ndarray, np.ndarray]:
            return np.arange(index, index + dataset_workers.CHUNK), np.full(shape, index % 7, dataset.IMAGE_DTYPE)

        ray.get([chunk.remote(i) for i in range(workers)])  # workers started before the clock
        store = np.zeros((chunks * dataset_workers.CHUNK, *shape[1:]), dataset.IMAGE_DTYPE)
        started = time.perf_counter()
        pending = [chunk.remote(i * dataset_workers.CHUNK) for i in range(chunks)]
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            indices, images = ray.get(ready[0])
            store[indices] = images
        seconds = time.perf_counter() - started
    megabytes = store.nbytes / 2**20
    return {
        "resolution": resolution,
        "chunks": chunks,
        "seconds": seconds,
        "images_per_s": len(store) / seconds,
        "mib_per_s": megabytes / seconds,
    }


if __name__ == "__main__":
    for side in (64, 128, 256):
        figures = measure_transfer(side)
        print(
            f"Ray object store into the driver, {side} px: {figures['images_per_s']:.0f} img/s, "
            f"{figures['mib_per_s']:.0f} MiB/s ({figures['chunks']} chunks of {dataset_workers.CHUNK} in "
            f"{figures['seconds']:.2f} s)"
        )
