"""Writing a dataset: its files created or grown (`prepare`), then its missing images rendered into them
(`render_missing`), resumably; `render_dataset` does both for `matfit render-dataset`.

The arrays are allocated on the disk before anything is written through their memory maps, and
an image row reaches the disk before its done flag, so an interruption at any point (Ctrl-C or
kill -9) keeps everything written so far and the same call continues from there
(`dataset.py` describes the format). The images are rendered by the executors of
`dataset_workers` (a local pool of processes, or this process) or by Ray (`cluster`); this
process alone stores them, so the bytes are the same whatever renders them.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import shutil
import time
from collections.abc import Callable, Iterator

import numpy as np

from matfit import documents, files, interrupt, params
from matfit.errors import DatasetError
from matfit.model.dataset import (
    FORMAT,
    FORMAT_VERSION,
    IMAGE_DTYPE,
    SCENE_FILE,
    SCENE_SPP,
    Dataset,
    Settings,
    check_count,
    image_seed,
    open_dataset,
    sampler_of,
)
from matfit.model.dataset_workers import (
    CHUNK,
    MAX_WORKERS,
    Results,
    Task,
    default_workers,
    in_this_process,
    in_worker_processes,
)
from matfit.rendering import engine as render
from matfit.rendering import scene


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
            f"{count} images at {settings.resolution} px need {byte_size(needed)}, only {byte_size(free)} are free: "
            "lower --count or --resolution"
        )


def byte_size(size: int) -> str:
    """Returns a size in bytes as people read it: "1.5 GiB", "12.3 MiB", "0.4 KiB" (a nearly full disk's free space
    read "0.0 GiB")."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20)):
        if size >= scale:
            return f"{size / scale:.1f} {unit}"
    return f"{size / 2**10:.1f} KiB"


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


def render_scene_image(dataset: Dataset, settings: Settings) -> None:
    """Writes the dataset's render of the scene without its sphere, unless it is there already."""
    path = os.path.join(dataset.path, SCENE_FILE)
    if os.path.isfile(path):
        return
    from matfit.rendering.engine import render_without_sphere

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
    executor: Callable[[Settings, list[Task], int], contextlib.AbstractContextManager[Results]]
    if ray_address is not None:
        from matfit.model import cluster

        executor = functools.partial(cluster.ray_results, address=ray_address)
    else:
        executor = in_worker_processes if workers > 0 else in_this_process
    if executor is not in_this_process:
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
