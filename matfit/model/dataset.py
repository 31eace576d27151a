"""The on-disk training set: rendered resumably, read memory-mapped.

A dataset is a directory:

    meta.json    what the arrays hold: format version, count, resolution, spp, Mitsuba variant and
                 versions, seed, and the parameter table it was sampled from
    params.npy   float32 (count, 19): the physical parameter values of every sample
                 (`matfit.params.to_unit` maps them onto the unit cube the networks see)
    images.npy   float16 (count, resolution, resolution, 3): linear (HDR) RGB renders
    done.npy     uint8 (count,): 1 where the image has been rendered and written

All three arrays are plain NumPy files, so `numpy.load(path, mmap_mode="r")` reads them without
matfit. Sample i's parameters come from `params.sample_index(seed, i)` and its image is rendered
with a seed derived from (seed, i): a sample never depends on the order, chunking or number of
workers that produced it, so an interrupted run (Ctrl-C or kill -9) is resumed by running the same
command again, and the result is byte for byte that of an uninterrupted run. An image row is
written and flushed before its done flag, so a flag never claims an image that is not on disk.
Asking for a larger count grows the arrays; asking for different settings is refused.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from matfit import documents, files, interrupt, params, shipped
from matfit.errors import DatasetError, RenderError
from matfit.render import engine as render
from matfit.render import process, scene

FORMAT = "matfit-dataset"
FORMAT_VERSION = 1
IMAGE_DTYPE = np.float16
MIN_RESOLUTION, MAX_RESOLUTION = 8, 1024
MAX_SPP = 65536
MAX_COUNT = 10_000_000
MAX_WORKERS = 64
# Render processes sharing one GPU (cuda_ad_rgb): one process leaves the GPU idle between its small launches, several
# fill it; the count with the highest steady rate at 128 px, 16 spp (docs/training.md#gpu).
GPU_WORKERS = 12
CHUNK = 16
ARRAYS = ("params.npy", "images.npy", "done.npy")
# The scene without its sphere: rendered once, clean.
SCENE_FILE = "scene.npy"
SCENE_SPP = 4096
# The refracting decoder's clear-glass and scattering bases (`scene.glass_basis_materials`,
# `scene.medium_basis_materials`): rendered on first use, one file per grid point while under way
# (resumable), then one array per grid shape (the scattering one without its thickness-0 row).
GLASS_FILE = "glass-{specular}x{roughness}.npy"
MEDIUM_FILE = "medium-{thickness}x{albedo}.npy"
BASIS_SPP = 1024


@dataclass(frozen=True)
class Settings:
    """What a dataset is rendered with; two runs may only add to one dataset if these agree."""

    resolution: int
    spp: int
    seed: int
    variant: str
    sampler: str = "uniform"  # `params.SAMPLERS`: how the parameters are drawn

    def check(self) -> None:
        """Raises DatasetError for values no dataset should be made with."""
        if not MIN_RESOLUTION <= self.resolution <= MAX_RESOLUTION:
            raise DatasetError(
                f"resolution {self.resolution} is out of range: use {MIN_RESOLUTION} to {MAX_RESOLUTION} pixels",
                field="resolution",
            )
        if not 1 <= self.spp <= MAX_SPP:
            raise DatasetError(f"spp {self.spp} is out of range: use 1 to {MAX_SPP} samples per pixel", field="spp")
        if not 0 <= self.seed <= params.MAX_SEED:
            raise DatasetError(f"seed {self.seed} is out of range: use 0 to {params.MAX_SEED}", field="seed")
        if self.sampler not in params.SAMPLERS:
            raise DatasetError(
                f"sampler {self.sampler!r} is unknown: use {' or '.join(params.SAMPLERS)}", field="sampler"
            )


def default_workers(variant: str) -> int:
    """Returns how many render processes a dataset renders with unless told: GPU_WORKERS on a GPU, else one per core."""
    from matfit.render.engine import CUDA_VARIANT

    return GPU_WORKERS if variant == CUDA_VARIANT else min(os.cpu_count() or 1, MAX_WORKERS)


def check_count(count: int) -> None:
    """Raises DatasetError unless 1 <= count <= MAX_COUNT."""
    if not 1 <= count <= MAX_COUNT:
        raise DatasetError(f"count {count} is out of range: use 1 to {MAX_COUNT}", field="count")


def image_seed(seed: int, index: int) -> int:
    """Returns the Mitsuba render seed of sample `index` in the dataset drawn with `seed`."""
    return int(np.random.SeedSequence([seed, index, 1]).generate_state(1)[0])


@dataclass
class Dataset:
    """An opened dataset: metadata and memory-mapped arrays."""

    path: str
    meta: dict
    params: np.ndarray
    images: np.ndarray
    done: np.ndarray

    @property
    def count(self) -> int:
        """Returns the number of samples the dataset holds room for."""
        return int(self.meta["count"])

    @property
    def resolution(self) -> int:
        """Returns the image side length in pixels."""
        return int(self.meta["resolution"])

    @property
    def finished(self) -> int:
        """Returns how many samples have been rendered."""
        return int(np.count_nonzero(self.done))

    def scene_image(self) -> np.ndarray | None:
        """Returns the linear float32 (R, R, 3) render of the scene without its sphere, or None if not rendered."""
        path = os.path.join(self.path, SCENE_FILE)
        return np.load(path).astype(np.float32) if os.path.isfile(path) else None

    def glass_basis(self, shape: tuple[int, int], progress: Callable[[int, int], None] | None = None) -> np.ndarray:
        """Returns the clear-glass basis (S, G, R, R, 3) of `scene.glass_basis_materials`, linear float32,
        rendering what is missing first; `progress(done, total)` after each render."""
        path = os.path.join(self.path, GLASS_FILE.format(specular=shape[0], roughness=shape[1]))
        return self.rendered_grid(path, scene.glass_basis_materials(shape), 0, progress)

    def medium_basis(self, shape: tuple[int, int], progress: Callable[[int, int], None] | None = None) -> np.ndarray:
        """Returns the scattering basis (T, A, R, R, 3) of `scene.medium_basis_materials`, linear float32: each
        grid point's render less that of its thickness at albedo 0 (the last column), so only the light the
        medium scatters; zero at thickness 0 (not rendered). Renders what is missing first."""
        path = os.path.join(self.path, MEDIUM_FILE.format(thickness=shape[0], albedo=shape[1]))
        materials = scene.medium_basis_materials(shape)[1:]
        rendered = self.rendered_grid(path, materials, 2**16, progress)  # seeds apart from any glass grid's
        scattered = rendered - rendered[:, -1:]
        return np.concatenate([np.zeros_like(scattered[:1]), scattered])

    def rendered_grid(
        self, path: str, materials: np.ndarray, offset: int, progress: Callable[[int, int], None] | None
    ) -> np.ndarray:
        """Returns Mitsuba renders (K, L, R, R, 3) of a grid of materials (K, L, 19), kept in `path`.

        Each grid point is rendered at BASIS_SPP with a seed no sample has (`offset` keeps the seeds
        of two grids apart) and kept in a file of its own until all are there, so an interrupted
        call loses at most one render.
        """
        if os.path.isfile(path):
            return np.load(path)
        from matfit.render.engine import Renderer

        shape = materials.shape[:2]
        parts = path[: -len(".npy")] + ".parts"
        os.makedirs(parts, exist_ok=True)
        grid = np.zeros((*shape, self.resolution, self.resolution, 3), np.float32)
        renderer = None
        for done, (i, j) in enumerate(np.ndindex(*shape)):
            part = os.path.join(parts, f"{i}-{j}.npy")
            if not os.path.isfile(part):
                renderer = renderer or Renderer(self.resolution, BASIS_SPP, self.meta["variant"])
                seed = image_seed(int(self.meta["seed"]), 2**32 - 2 - offset - done)  # indices no sample has
                with files.atomic_path(part) as temporary, open(temporary, "wb") as file:
                    np.save(file, renderer.render(materials[i, j], seed=seed))
            grid[i, j] = np.load(part)
            if progress is not None:
                progress(done + 1, shape[0] * shape[1])
        with files.atomic_path(path) as temporary, open(temporary, "wb") as file:
            np.save(file, grid)
        shutil.rmtree(parts, ignore_errors=True)
        return grid

    def unit_params(self) -> np.ndarray:
        """Returns every sample's parameters on the unit cube, float32 (count, 19)."""
        return params.to_unit(self.params).astype(np.float32)


def _meta(settings: Settings, count: int, versions: dict) -> dict:
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "count": count,
        "resolution": settings.resolution,
        "spp": settings.spp,
        "seed": settings.seed,
        "variant": settings.variant,
        "sampler": settings.sampler,
        "integrator": scene.INTEGRATOR["type"],
        "versions": versions,
        "image_dtype": np.dtype(IMAGE_DTYPE).name,
        "images": "linear RGB, (count, resolution, resolution, 3)",
        "parameter_table": params.table_fingerprint(),
    }


def read_meta(path: str) -> dict:
    """Returns a dataset's metadata, checking that it is a matfit dataset of a known format."""
    meta_path = os.path.join(path, "meta.json")
    if not os.path.isfile(meta_path):
        raise DatasetError(
            f"{path} is not a matfit dataset (no meta.json): make one with `matfit render-dataset {path} --count N`"
        )
    try:
        with open(meta_path) as file:
            meta = json.load(file)
    except (OSError, json.JSONDecodeError) as error:
        raise DatasetError(f"{meta_path} is corrupt ({error}): delete {path} and render the dataset again") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise DatasetError(f"{meta_path} does not describe a matfit dataset: delete {path} and render it again")
    if meta.get("format_version") != FORMAT_VERSION:
        raise DatasetError(
            f"{path} has dataset format {meta.get('format_version')}, this matfit reads {FORMAT_VERSION}: "
            "render it again"
        )
    for field, check in META_FIELDS.items():
        if field in meta or field in REQUIRED_META:
            problem = check(meta.get(field, _MISSING))
            if problem is not None:
                shown = "missing" if field not in meta else f"{json.dumps(meta[field])[:40]}, {problem}"
                raise DatasetError(
                    f"{meta_path}: field {field!r} is {shown}: "
                    f"delete {path} and render it again with `matfit render-dataset`"
                )
    return meta


_MISSING = object()


def _whole(low: int, high: int) -> Callable[[object], str | None]:
    """Returns a check that a value is a whole number in [low, high] (what is wrong, or None)."""

    def check(value: object) -> str | None:
        if value is _MISSING or isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            return f"not a whole number from {low} to {high}"
        return None

    return check


def _one_of(choices: Iterable[str]) -> Callable[[object], str | None]:
    """Returns a check that a value is one of `choices`."""
    names = tuple(choices)

    def check(value: object) -> str | None:
        return None if value in names else f"not one of {', '.join(names)}"

    return check


def _of_type(kind: type, description: str) -> Callable[[object], str | None]:
    """Returns a check that a value is of type `kind`."""

    def check(value: object) -> str | None:
        return None if isinstance(value, kind) else f"not {description}"

    return check


def _parameter_table(value: object) -> str | None:
    parameters = value.get("parameters") if isinstance(value, dict) else None
    if not isinstance(parameters, list) or not all(isinstance(entry, dict) for entry in parameters):
        return "not a parameter table"
    return None


# What every field of meta.json must hold: a dataset is only opened once all of them are right, so no
# later use of a field can fail. `sampler`, `integrator` and `versions` are absent from old datasets.
REQUIRED_META = ("count", "resolution", "spp", "seed", "variant", "parameter_table")
META_FIELDS: dict[str, Callable[[object], str | None]] = {
    "count": _whole(1, MAX_COUNT),
    "resolution": _whole(MIN_RESOLUTION, MAX_RESOLUTION),
    "spp": _whole(1, MAX_SPP),
    "seed": _whole(0, params.MAX_SEED),
    "variant": _one_of(render.VARIANTS),
    "sampler": _one_of(params.SAMPLERS),
    "integrator": _of_type(str, "a name"),
    "versions": _of_type(dict, "an object"),
    "parameter_table": _parameter_table,
}


def open_dataset(path: str, writable: bool = False) -> Dataset:
    """Returns the dataset at `path` with its arrays memory-mapped (read-only unless `writable`)."""
    meta = read_meta(path)
    difference = params.describe_table_difference(meta.get("parameter_table", {}))
    if difference is not None:
        raise DatasetError(f"{path} was made with another parameter table ({difference}): render a new dataset")
    mode = "r+" if writable else "r"
    count, resolution = int(meta["count"]), int(meta["resolution"])
    expected = {
        "params.npy": (count, params.COUNT),
        "images.npy": (count, resolution, resolution, 3),
        "done.npy": (count,),
    }
    arrays = {}
    for name, shape in expected.items():
        file = os.path.join(path, name)
        try:
            arrays[name] = np.load(file, mmap_mode=mode)
        except (OSError, ValueError) as error:
            raise DatasetError(
                f"{file} is missing or corrupt ({error}): delete {path} and render the dataset again"
            ) from None
        if arrays[name].shape != shape:
            raise DatasetError(
                f"{file} has shape {arrays[name].shape}, meta.json says {shape}: delete {path} and render it again"
            )
    return Dataset(path, meta, arrays["params.npy"], arrays["images.npy"], arrays["done.npy"])


def _check_output_directory(path: str) -> None:
    parent = os.path.dirname(os.path.abspath(path))
    if os.path.exists(path) and not os.path.isdir(path):
        raise DatasetError(f"{path} is a file, not a dataset directory: choose another output path")
    if not os.path.isdir(parent):
        raise DatasetError(f"cannot create {path}: directory {parent} does not exist (create it first)")
    target = path if os.path.isdir(path) else parent
    try:
        files.check_writable(os.path.join(target, "meta.json"))
    except files.OutputError:
        raise DatasetError(f"cannot write to {target}: it is read-only (choose another output path)") from None


def _check_disk(path: str, settings: Settings, count: int) -> None:
    needed = count * (settings.resolution**2 * 3 * np.dtype(IMAGE_DTYPE).itemsize + params.COUNT * 4 + 1)
    free = shutil.disk_usage(path if os.path.isdir(path) else os.path.dirname(os.path.abspath(path))).free
    if needed > free:
        raise DatasetError(
            f"{count} images at {settings.resolution} px need {needed / 2**30:.1f} GiB, only {free / 2**30:.1f} GiB "
            "are free: lower --count or --resolution"
        )


def sampler_of(meta: dict) -> str:
    """Returns the sampler a dataset was drawn with (datasets made before samplers existed: uniform)."""
    return meta.get("sampler", "uniform")


def _sampled_params(settings: Settings, start: int, stop: int) -> np.ndarray:
    samples = [params.sample_index(settings.seed, i, settings.sampler) for i in range(start, stop)]
    return np.stack([params.from_unit(unit) for unit in samples]).astype(np.float32)


def _write_arrays(directory: str, settings: Settings, count: int, old: Dataset | None, meta: dict) -> None:
    """Creates the three arrays for `count` samples, copying over what `old` already holds, and their meta.json.

    Every byte of the arrays is allocated on the disk before anything is written through their memory maps: a disk
    that fills up then fails here with a DatasetError, not later with a SIGBUS in the middle of a render. All four
    files are written under temporary names and renamed into place only once all of them are complete.
    """
    start = old.count if old is not None else 0
    shapes = {
        "params.npy": ((count, params.COUNT), np.float32),
        "images.npy": ((count, settings.resolution, settings.resolution, 3), IMAGE_DTYPE),
        "done.npy": ((count,), np.uint8),
    }
    meta_path = os.path.join(directory, "meta.json")
    try:
        with files.together() as batch:
            for name, (shape, dtype) in shapes.items():
                temporary = batch.path(os.path.join(directory, name))
                array = np.lib.format.open_memmap(temporary, mode="w+", dtype=dtype, shape=shape)
                _reserve(temporary)
                if old is not None:
                    array[:start] = getattr(old, name.removesuffix(".npy"))
                if name == "params.npy":
                    array[start:] = _sampled_params(settings, start, count)
                array.flush()
                del array
            files.fill(batch.path(meta_path), documents.dumps(meta).encode(), meta_path)
    except (OSError, files.OutputError) as error:
        reason = error.strerror if isinstance(error, OSError) and error.strerror else str(error).rpartition(": ")[2]
        raise DatasetError(
            f"cannot make the files of {count} samples in {directory}: {reason}: "
            "free some space on the disk, or lower --count or --resolution"
        ) from None


def _reserve(path: str) -> None:
    """Allocates every byte of a file on the disk now (raises OSError if the disk has no room for them)."""
    with open(path, "r+b") as file:
        try:
            os.posix_fallocate(file.fileno(), 0, os.fstat(file.fileno()).st_size)
        except OSError as error:
            if error.errno not in (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOSYS):  # else: no fallocate here
                raise


def prepare(path: str, settings: Settings, count: int, versions: dict) -> Dataset:
    """Returns the dataset at `path` ready to hold `count` samples: created, reused or grown.

    Refuses (DatasetError) an existing dataset made with other settings or parameters, and a
    count lower than what the dataset already holds.
    """
    settings.check()
    check_count(count)
    _check_output_directory(path)
    existing = os.path.isfile(os.path.join(path, "meta.json"))
    if not existing and os.path.isdir(path) and any(not n.startswith(".") for n in os.listdir(path)):
        raise DatasetError(f"{path} exists and is not a matfit dataset: choose an empty or new directory")
    old = None
    if existing:
        old = open_dataset(path)
        for field in ("resolution", "spp", "seed", "variant"):
            theirs, ours = old.meta[field], getattr(settings, field)
            if theirs != ours:
                flag = f"--{field} {theirs}"
                raise DatasetError(
                    f"{path} was rendered with {field} {theirs}, not {ours}: "
                    f"pass {flag} to add to it, or choose a new directory"
                )
        if sampler_of(old.meta) != settings.sampler:
            raise DatasetError(
                f"{path} was drawn with sampler {sampler_of(old.meta)}, not {settings.sampler}: "
                f"pass --sampler {sampler_of(old.meta)} to add to it, or choose a new directory"
            )
        if old.meta.get("integrator") != scene.INTEGRATOR["type"]:
            raise DatasetError(
                f"{path} was rendered with integrator {old.meta.get('integrator')}, this matfit renders with "
                f"{scene.INTEGRATOR['type']}: choose a new directory"
            )
        if count < old.count:
            raise DatasetError(f"{path} already holds {old.count} samples: pass --count {old.count} or more")
        if count == old.count:
            return open_dataset(path, writable=True)
    _check_disk(
        path, settings, count - (old.count if old else 0)
    )  # before the folder is made: a refusal leaves nothing
    created = not os.path.isdir(path)
    os.makedirs(path, exist_ok=True)
    try:
        _write_arrays(path, settings, count, old, _meta(settings, count, versions))
    except BaseException:
        if created:  # nothing of a refused new dataset is left
            shutil.rmtree(path, ignore_errors=True)
        raise
    return open_dataset(path, writable=True)


def _chunks(indices: np.ndarray, size: int) -> Iterator[np.ndarray]:
    for start in range(0, len(indices), size):
        yield indices[start : start + size]


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
    from matfit.render.engine import Renderer, mitsuba

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
    images = np.stack([_worker_renderer.render(v, seed=int(s)) for v, s in zip(values, seeds, strict=True)])
    return indices, images.astype(IMAGE_DTYPE)


Task = tuple[np.ndarray, np.ndarray, np.ndarray]
Results = Iterator[tuple[np.ndarray, np.ndarray]]


@contextlib.contextmanager
def _in_this_process(settings: Settings, tasks: list[Task], workers: int) -> Iterator[Results]:
    init_worker(settings.resolution, settings.spp, settings.variant, ignore_interrupts=False, new_session=False)
    yield map(render_chunk, tasks)


class _Worker:
    """One rendering child process of `render_missing`: `serve_chunks` in a new interpreter, spoken to over two pipes.

    The child holds only its own ends of the pipes, so it sees its requests end as soon as this process ends, however
    it ends (`kill -9` included): it then finishes the render in hand and leaves without a word (`serve_chunks`).
    Nothing of multiprocessing is used, so no semaphore or resource tracker outlives a killed parent either.
    """

    def __init__(self, settings: Settings):
        requests_read, requests_write = os.pipe()
        replies_read, replies_write = os.pipe()
        package = str(shipped.PACKAGE.parent)  # this very matfit, wherever it lies
        code = (
            f"import sys; sys.path.insert(0, {package!r}); from matfit.model import dataset; dataset.serve_chunks("
            f"{requests_read}, {replies_write}, {settings.resolution}, {settings.spp}, {settings.variant!r})"
        )
        try:
            # A session of its own: the terminal's Ctrl-C reaches only the parent, which stops the workers, so no
            # render cancelled by Mitsuba's own SIGINT handler is ever stored.
            self.process = subprocess.Popen(
                [sys.executable, "-c", code], pass_fds=(requests_read, replies_write), start_new_session=True
            )
        except BaseException:
            for descriptor in (requests_write, replies_read):
                os.close(descriptor)
            raise
        finally:
            os.close(requests_read)
            os.close(replies_write)
        self.requests = os.fdopen(requests_write, "wb")
        self.replies = os.fdopen(replies_read, "rb")

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
def _in_worker_processes(settings: Settings, tasks: list[Task], workers: int) -> Iterator[Results]:
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
            task = (np.array(header["indices"], np.int64), values, np.array(header["seeds"], np.int64))
            try:
                _, images = render_chunk(task)
            except Exception as error:
                process.write_message(outgoing, {"error": f"Mitsuba failed: {type(error).__name__}: {error}"})
                continue
            process.write_message(outgoing, {"done": True}, images)


def render_scene_image(dataset: Dataset, settings: Settings) -> None:
    """Writes the dataset's render of the scene without its sphere, unless it is there already."""
    path = os.path.join(dataset.path, SCENE_FILE)
    if os.path.isfile(path):
        return
    from matfit.render.engine import render_without_sphere

    image = render_without_sphere(
        settings.resolution, SCENE_SPP, settings.variant, seed=image_seed(settings.seed, 2**32 - 1)
    )  # an index no sample has
    with files.atomic_path(path) as temporary, open(temporary, "wb") as file:
        np.save(file, image)


def render_missing(
    dataset: Dataset,
    workers: int = 1,
    progress: Callable[[int, int, float], None] | None = None,
    ray_address: str | None = None,
) -> int:
    """Renders every sample not yet done; returns how many were rendered in this call.

    `workers` rendering processes do the work while this process stores the results, so that an
    interruption (Ctrl-C, or KeyboardInterrupt from `progress`) keeps everything written so far;
    the same call later continues from there. `workers=0` renders in this process instead (no
    start-up cost, but a Ctrl-C that lands inside a render is swallowed by Mitsuba). With
    `ray_address` the chunks are Ray tasks on that cluster instead (`matfit.model.cluster`; "local"
    starts a Ray of `workers` CPUs for this call); this process still stores every result, so the
    protocol and the bytes are the same. `progress(done, total, images_per_second)` is called
    after each chunk. The scene without its sphere (`SCENE_FILE`, `SCENE_SPP` samples) is
    rendered first, in this process, if missing.
    """
    settings = Settings(
        dataset.resolution, int(dataset.meta["spp"]), int(dataset.meta["seed"]), dataset.meta["variant"]
    )
    render_scene_image(dataset, settings)
    missing = np.flatnonzero(dataset.done == 0)
    tasks = [
        (
            chunk,
            np.asarray(dataset.params[chunk], dtype=np.float64),
            np.array([image_seed(settings.seed, int(i)) for i in chunk]),
        )
        for chunk in _chunks(missing, CHUNK)
    ]
    total, finished, rendered, started = dataset.count, dataset.finished, 0, time.perf_counter()
    if progress is not None:
        progress(finished, total, 0.0)
    if not tasks:
        return 0
    if ray_address is not None:
        from matfit.model import cluster

        executor = functools.partial(cluster.ray_results, address=ray_address)
    else:
        executor = _in_worker_processes if workers > 0 else _in_this_process
    if executor is not _in_this_process:
        interrupt.raise_on_signal()  # the workers or Ray are stopped by this process's KeyboardInterrupt
    with executor(settings, tasks, workers) as results:
        for indices, images in results:
            # The image rows reach the disk before their done flags: a flag never claims an
            # image that a kill -9 could still lose.
            dataset.images[indices] = images
            dataset.images.flush()
            dataset.done[indices] = 1
            dataset.done.flush()
            finished += len(indices)
            rendered += len(indices)
            if progress is not None:
                progress(finished, total, rendered / max(time.perf_counter() - started, 1e-9))
    return rendered


def render_dataset(
    path: str,
    count: int,
    resolution: int = 64,
    spp: int = 16,
    seed: int = 0,
    workers: int | None = 1,
    variant: str | None = None,
    progress: Callable[[int, int, float], None] | None = None,
    ray_address: str | None = None,
    sampler: str = "uniform",
) -> tuple[Dataset, int, list[str]]:
    """Creates, resumes or grows the dataset at `path` to `count` rendered samples.

    Returns (the dataset, how many were rendered in this call, notices such as the renderer's
    fallback). Every argument is checked before anything is written. With `ray_address` the
    images are rendered as Ray tasks (`render_missing`). `workers` None: `default_workers` of the variant.
    """
    if workers is not None and not 1 <= workers <= MAX_WORKERS:
        raise DatasetError(f"workers {workers} is out of range: use 1 to {MAX_WORKERS}", field="workers")
    if ray_address is not None:
        from matfit.model import cluster

        cluster.check(ray_address)
    chosen, notice = render.choose_variant(variant)
    workers = default_workers(chosen) if workers is None else workers
    settings = Settings(resolution, spp, seed, chosen, sampler)
    settings.check()
    check_count(count)
    render.mitsuba(chosen)
    data = prepare(path, settings, count, render.versions())
    return data, render_missing(data, workers, progress, ray_address), [notice] if notice else []
