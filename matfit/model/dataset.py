"""The on-disk training set, its format and its reading: opened memory-mapped (`open_dataset`), every field of
meta.json checked first. Writing it is `dataset_writing`'s, rendering its images `dataset_workers`'.

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
Asking for a larger count grows the arrays; asking for different settings is refused (`dataset_writing.prepare`).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from matfit import documents, files, params
from matfit.errors import DatasetError
from matfit.rendering import engine as render
from matfit.rendering import scene

FORMAT = "matfit-dataset"
FORMAT_VERSION = 1
IMAGE_DTYPE = np.float16
MIN_RESOLUTION, MAX_RESOLUTION = 8, 1024
MAX_SPP = 65536
MAX_COUNT = 10_000_000
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
    images: np.memmap
    done: np.memmap

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

    def glass_basis(self, shape: Sequence[int], progress: Callable[[int, int], None] | None = None) -> np.ndarray:
        """Returns the clear-glass basis (S, G, R, R, 3) of `scene.glass_basis_materials`, linear float32,
        rendering what is missing first; `progress(done, total)` after each render."""
        path = os.path.join(self.path, GLASS_FILE.format(specular=shape[0], roughness=shape[1]))
        return self.rendered_grid(path, scene.glass_basis_materials(shape), 0, progress)

    def medium_basis(self, shape: Sequence[int], progress: Callable[[int, int], None] | None = None) -> np.ndarray:
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
        from matfit.rendering.engine import Renderer

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


def read_meta(path: str) -> dict:
    """Returns a dataset's metadata, checking that it is a matfit dataset of a known format."""
    meta_path = os.path.join(path, "meta.json")
    if not os.path.isfile(meta_path):
        raise DatasetError(
            f"{path} is not a matfit dataset (no meta.json): make one with `matfit render-dataset {path} --count N`"
        )
    meta = documents.read(meta_path, f"delete {path} and render the dataset again", DatasetError)
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
    mode: Literal["r+", "r"] = "r+" if writable else "r"
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
            files.check_input(file)  # a FIFO planted here would block np.load's open for ever
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


def sampler_of(meta: dict) -> str:
    """Returns the sampler a dataset was drawn with (datasets made before samplers existed: uniform)."""
    return meta.get("sampler", "uniform")
