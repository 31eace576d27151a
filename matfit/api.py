"""matfit's public API, re-exported by the package: fit a picture, edit and render a material, export it (docs/api.md).

`fit` fits one picture (a file or a NumPy array) and returns a `Fit`; a `Fitter` keeps the model and the
render processes loaded for many fits; `Material` is the 19 parameters by name, with their params.json,
Mitsuba and Blender forms; `render` renders one in the test scene. Bad input raises `MatfitError` with the
command line's one-line message. JAX, Mitsuba and OpenImageIO are imported by the functions that need them,
so `import matfit` loads NumPy and the parameter table alone.

`fit` and `render` share their names with the subpackages `matfit/fit/` and `matfit/render/`, and Python
sets a package's attribute to its subpackage whenever that is imported: so the two functions are those
subpackages made callable (`_callable`), and `matfit.fit.search` still names the module.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import os
import time
import types
import warnings
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import numpy as np
import numpy.typing as npt

from matfit import documents, params, shipped
from matfit.errors import (
    FitError,
    ImageError,
    MatfitError,
    OutputError,
    ParameterError,
    RenderError,
    WeightsError,
    check_range,
)
from matfit.fit.methods import Method, Settings

if TYPE_CHECKING:
    from matfit.fit import search
    from matfit.fit.outcome import Outcome
    from matfit.fit.request import Outputs as RequestOutputs
    from matfit.fit.request import Request
    from matfit.model.models import Model
    from matfit.render.engine import Renderer
    from matfit.render.process import Pool

__all__ = [
    "Fit",
    "Fitter",
    "Material",
    "MatfitError",
    "Outputs",
    "Settings",
    "fit",
    "fit_sequence",
    "load_model",
    "render",
]

Picture = str | os.PathLike[str] | npt.NDArray[Any]  # a picture file's path, or its pixels (`fit`)
Array = npt.NDArray[np.float64]
Image = npt.NDArray[np.float32]
ARRAY = "array"  # params.json's `target` (and `mask`) of pixels given as an array
MAX_SIZE = 4096  # pixels a side of a render (`render`, `Outputs.render_size`): `matfit render --size`'s


def _default(name: str) -> float:
    return float(params.DEFAULTS[params.INDEX[name]])


@dataclass(frozen=True)
class Material:
    """A material: the 19 shader parameters by name, in physical units (`matfit params` lists their ranges).

    Names left out take their defaults; a value out of its range raises `MatfitError`. Edit one with
    `dataclasses.replace(material, roughness=0.1)`.
    """

    base_color_r: float = _default("base_color_r")
    base_color_g: float = _default("base_color_g")
    base_color_b: float = _default("base_color_b")
    metallic: float = _default("metallic")
    roughness: float = _default("roughness")
    anisotropic: float = _default("anisotropic")
    specular: float = _default("specular")
    spec_tint: float = _default("spec_tint")
    sheen: float = _default("sheen")
    sheen_tint: float = _default("sheen_tint")
    clearcoat: float = _default("clearcoat")
    clearcoat_gloss: float = _default("clearcoat_gloss")
    spec_trans: float = _default("spec_trans")
    medium_color_r: float = _default("medium_color_r")
    medium_color_g: float = _default("medium_color_g")
    medium_color_b: float = _default("medium_color_b")
    density: float = _default("density")
    scattering: float = _default("scattering")
    phase_g: float = _default("phase_g")

    def __post_init__(self) -> None:
        for name in params.NAMES:
            value = getattr(self, name)
            if isinstance(value, np.generic):  # a NumPy scalar (np.float32 is no float)
                value = value.item()
            object.__setattr__(self, name, params.check_value(name, value))

    @classmethod
    def from_array(cls, values: npt.ArrayLike) -> Material:
        """Returns the material of 19 physical values in `params.NAMES` order (`array()`'s)."""
        array = np.asarray(values, dtype=np.float64)
        if array.shape != (params.COUNT,):
            raise ParameterError(
                f"a material is {params.COUNT} values, got shape {array.shape}: give one value a parameter, in the "
                "order `matfit params` lists them"
            )
        return cls(*(float(value) for value in array))

    @classmethod
    def from_unit(cls, unit: npt.ArrayLike) -> Material:
        """Returns the material of 19 unit-cube coordinates (each parameter's range mapped onto [0, 1])."""
        return cls.from_array(params.from_unit(np.asarray(unit, dtype=np.float64)))

    @classmethod
    def from_dict(cls, values: Mapping[str, float]) -> Material:
        """Returns the material of named values; names left out take their defaults, unknown names are refused."""
        plain = {name: value.item() if isinstance(value, np.generic) else value for name, value in values.items()}
        return cls.from_array(params.from_mapping(plain))

    @classmethod
    def from_json(cls, text: str | bytes) -> Material:
        """Returns the material of a params.json text (what `to_json` and `matfit fit` write, or a flat object)."""
        return cls.from_array(params.parse_params_json(text))

    @classmethod
    def read(cls, path: str | os.PathLike[str]) -> Material:
        """Returns the material of a params.json file."""
        return cls.from_array(params.read_file(os.fspath(path)))

    @classmethod
    def preset(cls, name: str) -> Material:
        """Returns a named material (`presets()` lists them)."""
        from matfit.render import presets

        return cls.from_array(presets.preset(name))

    @classmethod
    def presets(cls) -> dict[str, Material]:
        """Returns every named material: gold, glass, jade, milk and the others of `matfit presets`."""
        from matfit.render import presets

        return {name: cls.preset(name) for name in presets.PRESETS}

    def array(self) -> Array:
        """Returns the 19 physical values, float64, in `params.NAMES` order."""
        return np.array([getattr(self, name) for name in params.NAMES], dtype=np.float64)

    def unit(self) -> Array:
        """Returns the 19 unit-cube coordinates the networks and optimisers see."""
        return np.asarray(params.to_unit(self.array()), dtype=np.float64)

    def to_dict(self) -> dict[str, float]:
        """Returns the named values."""
        return {name: float(getattr(self, name)) for name in params.NAMES}

    def to_json(self) -> str:
        """Returns the material as params.json text: values rounded to 6 decimals, with their units."""
        return documents.dumps(params.params_document(self.array()))

    def to_mitsuba(self) -> dict[str, Any]:
        """Returns {"bsdf": the principled BSDF, "interior": the homogeneous medium} as plain `mi.load_dict` data.

        Spread it into a shape (`{"type": "sphere", **material.to_mitsuba()}`); the medium shows with a volumetric
        integrator (`volpath`, `volpathmis`) on a closed shape, and only where the BSDF transmits (`spec_trans`).
        """
        from matfit.render import scene

        values = self.array()
        return {"bsdf": scene.bsdf(values), "interior": scene.medium(values)}

    def to_mitsuba_xml(self) -> str:
        """Returns a Mitsuba 3 XML scene to `<include>`: ids `matfit-material` (the BSDF) and `matfit-interior`."""
        from matfit.render import export

        return export.mitsuba_xml(self.array())

    def to_blender_script(self, name: str = "matfit") -> str:
        """Returns a Python script that builds the material, named `name`, on Blender 4.x's selected meshes."""
        from matfit.render import export

        try:
            return export.blender_script(self.array(), name)
        except MatfitError:
            raise
        except ValueError as error:  # the name
            raise ParameterError(str(error), field="name") from None


@dataclass(frozen=True)
class Outputs:
    """The files a fit writes (`Fitter.fit(..., outputs=...)`): params.json always, the others where named.

    Every path is checked before any work (a folder that cannot be written, a wrong extension, a path named twice,
    an input it would overwrite, a file of the model) and all are written together once the fit is done, so a
    failed or interrupted fit leaves none of them. `report`: the report picture (target, start, fit, Mitsuba's render,
    difference, ranges); `render`: Mitsuba's render of the answer, `render_size` pixels a side at `render_spp`
    samples a pixel; `mitsuba_xml` and `blender`: the exports (`Material.to_mitsuba_xml`, `to_blender_script`).
    In `Fitter.fit_all`, each picture's files go into the folder given, named after the picture:
    `<stem>.params.json`, and `<stem>.<name>` for each other file named here (`params` is not used there).
    """

    params: str | os.PathLike[str] = "params.json"
    report: str | os.PathLike[str] | None = None
    render: str | os.PathLike[str] | None = None
    render_size: int = 512
    render_spp: int = 256
    mitsuba_xml: str | os.PathLike[str] | None = None
    blender: str | os.PathLike[str] | None = None

    def _request(self) -> RequestOutputs:
        """Returns the outputs as the fit's request holds them (paths as `matfit fit` passes them on)."""
        from matfit.fit.request import Outputs as RequestOutputs
        from matfit.model import dataset

        named = {}
        for name in ("params", "report", "render", "mitsuba_xml", "blender"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, str | os.PathLike):
                raise OutputError(f"{name} {_shown(value)} is no path: give a file's path or None", field=name)
            named[name] = None if value is None else _text(value)
        size = _whole("render_size", self.render_size, dataset.MIN_RESOLUTION, MAX_SIZE, OutputError)
        spp = _whole("render_spp", self.render_spp, 1, dataset.MAX_SPP, OutputError)
        return RequestOutputs(
            str(named["params"]),
            named["report"],
            named["render"],
            size,
            spp,
            named["mitsuba_xml"],
            named["blender"],
        )


@dataclass(frozen=True, eq=False)
class Fit:
    """What a fit of a picture found: the material, how well it matches, and its params.json.

    `mitsuba_rmse` is None and `verification` empty for a fit without verification; `ranges` is what the
    picture decides about each parameter and `answer` how the clean answer was chosen (docs/fitting.md),
    both as params.json holds them. RMSE on 0-255 sRGB values. The pictures are sRGB, (R, R, 3) at the
    model's resolution: `target` as fitted, `image` the decoder's picture of the material, `rendered`
    Mitsuba's (None where nothing was rendered), `start_image` the decoder's picture of the best-of-n start
    (`start`, among the encoders' guesses and the init's material) the search began from.
    """

    material: Material
    neural_rmse: float
    mitsuba_rmse: float | None
    verification: dict[str, Any]
    ranges: dict[str, Any]
    answer: dict[str, Any]
    notices: tuple[str, ...]
    summary: str
    target: Image = field(repr=False)
    image: Image = field(repr=False)
    rendered: Image | None = field(repr=False)
    document: dict[str, Any] = field(repr=False)
    start: str = ""  # which guess best-of-n started from ("encoder-4", "extra-1": the init's material, ...)
    start_rmse: float = float("nan")  # its neural RMSE
    evaluations: int = 0  # the search's objective evaluations
    start_image: Image | None = field(default=None, repr=False)
    _outcome: Outcome | None = field(default=None, repr=False)

    def to_json(self) -> str:
        """Returns the fit's params.json text: for a picture file, what `matfit fit` writes, but for the timings."""
        return documents.dumps(self.document)

    def report(self) -> Image:
        """Returns `matfit fit --report`'s picture, sRGB (target | start | fit (neural) | fit (Mitsuba) | difference |
        ranges): for a fit with Mitsuba's render (verified, the default), else MatfitError."""
        from matfit.fit import document

        if self._outcome is None or self._outcome.rendered is None:
            raise FitError("a fit without Mitsuba's render has no report: fit with verify=True", field="report")
        return np.asarray(document.report_picture(self._outcome), np.float32)


def _fit_of(outcome: Outcome, name: str) -> Fit:
    """Returns the `Fit` of a finished fit (its document's timings set)."""
    document = outcome.document
    rendered = None if outcome.rendered is None else np.asarray(outcome.rendered, np.float32)
    return Fit(
        Material.from_array(outcome.values),
        float(outcome.neural_rmse),
        document.get("mitsuba_rmse"),
        dict(document.get("verification") or {}),
        dict(document.get("ranges") or {}),
        dict(document.get("answer") or {}),
        tuple(outcome.notices),
        outcome.summary(name),
        np.asarray(outcome.target, np.float32),
        np.asarray(outcome.image, np.float32),
        rendered,
        document,
        outcome.result.chosen,
        float(outcome.result.start_rmse),
        int(outcome.result.evaluations),
        np.asarray(outcome.result.start_image, np.float32),
        outcome,
    )


def load_model(path: str | os.PathLike[str] | None = None) -> Model:
    """Returns the decoder and encoders of a model folder (None: the shipped model), for `Fitter` or `fit`."""
    from matfit.fit import fitfile

    if path is not None and not isinstance(path, str | os.PathLike):
        raise WeightsError(
            f"model {_shown(path)} is no model folder: give a folder's path, load_model()'s model, or None for the "
            "shipped one",
            field="model",
        )
    return fitfile.load_model(str(shipped.MODEL) if path is None else os.fspath(path))


def _linear(picture: npt.ArrayLike, name: str, *, linear: bool) -> tuple[Image, list[str]]:
    """Returns (linear RGB float32 (H, W, 3), notices) of pixels given as an array, as `images.load` reads a file."""
    try:
        array = np.asarray(picture)
    except (ValueError, TypeError) as error:
        raise ImageError(
            f"the {name} array cannot be read ({error}): give an (H, W, 3) NumPy array", field=name
        ) from None
    shapes = "(H, W, 3) RGB, (H, W, 4) with alpha, or (H, W) grey"
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] not in (1, 2, 3, 4)) or 0 in array.shape:
        raise ImageError(f"the {name} array has shape {array.shape}: give {shapes}", field=name)
    kinds = "float sRGB in 0-1, uint8 0-255, uint16 0-65535, or linear float with linear=True"
    if array.dtype.kind == "u" and array.dtype.itemsize in (1, 2) and not linear:
        scaled = array.astype(np.float32) / np.float32(np.iinfo(array.dtype).max)
    elif array.dtype.kind == "f":
        scaled = array.astype(np.float32)
    else:
        raise ImageError(f"the {name} array holds {array.dtype} values: give {kinds}", field=name)
    from matfit import images

    if array.shape[0] * array.shape[1] > images.MAX_PIXELS:
        raise ImageError(
            f"the {name} array is {array.shape[1]}x{array.shape[0]}, more than {images.MAX_PIXELS / 1e6:.0f} Mpixel: "
            "scale it down first",
            field=name,
        )
    if not np.all(np.isfinite(scaled)):
        raise ImageError(f"the {name} array contains NaN or infinite values: fix or clamp them first", field=name)
    if not linear and (scaled.min() < 0 or scaled.max() > 1):
        raise ImageError(
            f"the {name} array's values run from {scaled.min():g} to {scaled.max():g}, outside sRGB's 0-1: divide "
            "0-255 values by 255, or pass linear=True for linear (HDR) values",
            field=name,
        )
    notices = []
    channels = 1 if array.ndim == 2 else array.shape[2]
    if channels in (1, 2):
        notices.append(f"the {name} array is grey: replicated to RGB")
        scaled = np.repeat(scaled.reshape(*array.shape[:2], -1)[:, :, :1], 3, axis=2)
    elif channels == 4:
        notices.append(f"the {name} array's alpha dropped (the colour is used as it is, not composited)")
    pixels = scaled[:, :, :3]
    return np.ascontiguousarray(pixels if linear else images.srgb_decode(pixels), np.float32), notices


def _text(path: str | os.PathLike[str]) -> str:
    """Returns a path as the command line passes it on: `str(Path(...))`, so that params.json names it alike."""
    return str(Path(path))


def _shown(value: object) -> str:
    """Returns how an error message names a value: its repr if that is short and one line, else its type."""
    text = repr(value)
    return text if len(text) <= 40 and "\n" not in text else f"of type {type(value).__name__}"


def _whole(field: str, value: object, low: int, high: int, error: type[MatfitError]) -> int:
    """Returns `value` as an int: a whole number in [low, high], else `error` naming it and the range."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise error(f"{field} {_shown(value)} is not a whole number: use {low} to {high}", field=field)
    check_range(field, int(value), low, high, error)
    return int(value)


class Fitter:
    """The model and the render processes loaded once, for many fits (the warm path); a context manager.

    `model`: a model folder (None: the shipped model) or a loaded `load_model()`. A folder's model loads at the first
    fit, once that fit's inputs and outputs were checked (a bad picture is refused without loading anything), or at
    the first use of `fitter.model`. `verify`: whether fits let Mitsuba choose among their candidates by default; the
    render processes (one a core) start here when it does, so that Mitsuba loads in them while the model loads here.
    A fit that fails keeps them while every one runs (the picture was at fault); one that lost a render process
    ends them, and the next fit starts new ones. `close()` (or leaving the `with` block) ends them.
    """

    def __init__(
        self, model: str | os.PathLike[str] | Model | None = None, *, verify: bool = True, variant: str | None = None
    ) -> None:
        from matfit.render import engine

        engine.check_request(variant)
        if model is not None and not isinstance(model, str | os.PathLike):
            from matfit.model import models  # a loaded model's module is imported already

            if not isinstance(model, models.Model):
                raise WeightsError(
                    f"model {_shown(model)} is no model folder: give a folder's path, load_model()'s model, or None "
                    "for the shipped one",
                    field="model",
                )
        self.variant = variant
        self.verify = verify
        self._pool: Pool | None = None
        self._model: Model | None = None
        if model is None:
            self.model_path = str(shipped.MODEL)
        elif isinstance(model, str | os.PathLike):
            self.model_path = os.fspath(model)
        else:
            self._model, self.model_path = model, model.path
        if verify:
            self._renderer()  # Mitsuba starts in the children while JAX and the model load here

    @property
    def model(self) -> Model:
        """The model the fits use (`load_model(model_path)`, loaded at the first use)."""
        if self._model is None:
            self._model = load_model(self.model_path)
        return self._model

    def _renderer(self) -> Pool:
        if self._pool is None:
            from matfit.render.process import Pool

            self._pool = Pool(self.variant)
        return self._pool

    def close(self) -> None:
        """Ends the render processes; a later verified fit starts new ones."""
        if self._pool is not None:
            self._pool.close()
            self._pool = None

    def __enter__(self) -> Fitter:
        return self

    def __exit__(self, *exception: object) -> None:
        self.close()

    def render(self, material: Material, *, seed: int = 0, spp: int = 64) -> Image:
        """Returns the linear float32 (R, R, 3) render of a material at the model's resolution R on this fitter's
        render processes (those that verify its fits: started here if not yet), bit-identical whatever their count."""
        from matfit.fit import verify
        from matfit.model import dataset

        if not isinstance(material, Material):
            raise ParameterError(f"material {_shown(material)} is no matfit.Material: give one", field="material")
        seed = _whole("seed", seed, 0, params.MAX_SEED, RenderError)
        spp = _whole("spp", spp, 1, dataset.MAX_SPP, RenderError)
        pool = self._renderer()
        pool.load(self.model.resolution, verify.SPP)
        return np.asarray(pool.render(material.array(), seed=seed, spp=spp), np.float32)

    def fit(
        self,
        picture: Picture,
        *,
        mask: Picture | None = None,
        init: str | os.PathLike[str] | Material | None = None,
        settings: Settings | None = None,
        linear: bool = False,
        verify: bool | None = None,
        corrections: int | None = None,
        answer: Literal["clean", "best"] = "clean",
        refine: int = 0,
        seed: int = 0,
        outputs: Outputs | None = None,
    ) -> Fit:
        """Returns the fit of one picture with this fitter's model: `matfit.fit`, warm. `outputs`: the files to write
        (checked before any work, written together at the end: what `matfit fit` writes), or None to write nothing."""
        from matfit.fit import fitfile  # noqa: F401  # JAX imported before the fit's wall time starts

        started = time.perf_counter()
        verified = self.verify if verify is None else verify
        request, notices = self._request(
            picture, mask, init, settings, linear, verified, corrections, answer, refine, seed, outputs
        )
        return self._fit_request(request, notices, started)

    def fit_all(
        self,
        pictures: Iterable[str | os.PathLike[str]],
        folder: str | os.PathLike[str],
        *,
        mask: str | os.PathLike[str] | None = None,
        init: str | os.PathLike[str] | None = None,
        settings: Settings | None = None,
        verify: bool | None = None,
        corrections: int | None = None,
        answer: Literal["clean", "best"] = "clean",
        refine: int = 0,
        seed: int = 0,
        outputs: Outputs | None = None,
        done: Callable[[str, str, Fit | MatfitError | None], None] | None = None,
    ) -> int:
        """Fits picture files into `folder`, resumably: `matfit fit a.png b.png -o folder/`. Returns how many failed.

        Each picture writes `<folder>/<stem>.params.json` and the other files `outputs` names (`Outputs`), every
        path checked before the first fit (two pictures of one name are refused). A picture that cannot be fitted
        (a MatfitError: unreadable, a mask of another size) is handed to `done` and the others go on. Stopped part
        way (Ctrl-C, kill -9), the same call again keeps the pictures fitted already (unchanged, their files there,
        the same settings and model) and fits the rest; once all are fitted, the folder's journal of them is
        removed. `done(picture, its params.json, the Fit, its MatfitError, or None for one kept)` hears of each.
        """
        from matfit.fit import batch

        targets = [_text(picture) for picture in _paths(pictures)]
        if not isinstance(folder, str | os.PathLike):
            raise OutputError(f"folder {_shown(folder)} is no path: give the folder to write into", field="output")
        into = os.fspath(folder)
        if not targets:
            raise FitError("fit_all was given no pictures: give a list of picture files", field="target")
        if mask is not None and not isinstance(mask, str | os.PathLike):
            raise ImageError(f"mask {_shown(mask)} is no path: give a picture file's path or None", field="mask")
        verified = self.verify if verify is None else verify
        template = dataclasses.replace(outputs or Outputs(), params=os.path.join(into, "params.json"))
        request, _ = self._request(
            targets[0], mask, init, settings, False, verified, corrections, answer, refine, seed, template
        )
        # the model loaded after the checks (a folder that is no model is said before any fit, and leaves no folder)
        requests = batch.plan(targets, into, request, then=lambda: self.model)

        def fit_one(request: Request, written: Callable[[str], None]) -> Fit:
            return self._fit_request(request, [], time.perf_counter(), written)

        def heard(request: Request, result: Fit | MatfitError | None) -> None:
            if done is not None:
                done(request.target, request.outputs.params if request.outputs else into, result)

        return batch.fit_all(requests, self.model_path, fit_one, done=heard)

    def _fit_request(
        self, request: Request, notices: list[str], started: float, written: Callable[[str], None] | None = None
    ) -> Fit:
        """Returns the fit of a request made by `_request`: checked before the model loads, its outputs written, then
        `written(the SHA-256 of the picture fitted)` called (`fit_all`'s journal)."""
        from matfit.fit import fitfile

        renderer = self._renderer() if request.verified and not request.refine_steps else None  # refinement: here
        try:  # fitfile checks the request, then asks this fitter for its model (a folder's loads at the first fit)
            if request.outputs is None:
                outcome, _ = fitfile.fit_file(request, self, renderer=renderer)
                outcome.document["wall_time_s"] = round(time.perf_counter() - started, 3)
            else:
                outcome = fitfile.run(request, self, renderer=renderer, started=started)
                if written is not None:
                    written(str(outcome.document["target_sha256"]))
        except BaseException:
            if self._pool is not None and not self._pool.healthy():  # a render process ended: the next fit starts new
                self.close()
            raise
        outcome = dataclasses.replace(outcome, notices=(*notices, *outcome.notices))
        return _fit_of(outcome, request.outputs.params if request.outputs else request.target)

    def _request(
        self,
        picture: Picture,
        mask: Picture | None,
        init: str | os.PathLike[str] | Material | None,
        settings: Settings | None,
        linear: bool,
        verified: bool,
        corrections: int | None,
        answer: str,
        refine: int,
        seed: int,
        outputs: Outputs | None = None,
    ) -> tuple[Request, list[str]]:
        """Returns (the request of one fit, notices of the pixels read here): a picture file's as `matfit fit` makes
        it, an array's with its pixels as the model's target."""
        from matfit.fit import search
        from matfit.fit.request import Request

        _check_choices(settings, init)
        if outputs is not None and not isinstance(outputs, Outputs):
            raise OutputError(
                f"outputs {_shown(outputs)} is no matfit.Outputs: give Outputs(params, ...) or None", field="output"
            )
        seed = _whole("seed", seed, 0, params.MAX_SEED, FitError)
        initial = (
            None if init is None else "Material" if isinstance(init, Material) else _text(init),
            init.array() if isinstance(init, Material) else None,
        )
        target, pixels, digest, notices = ARRAY, None, None, list[str]()
        size: tuple[int, int] | None = None  # an array's (height, width)
        if isinstance(picture, str | os.PathLike):
            if linear:
                raise ImageError(
                    "linear=True describes an array's values; a picture file says itself how it is encoded "
                    "(EXR and HDR linear, the others sRGB): leave linear out",
                    field="linear",
                )
            target = _text(picture)
        else:
            linear_pixels, notices = _linear(picture, "picture", linear=linear)
            size = (linear_pixels.shape[0], linear_pixels.shape[1])
            pixels, more = search.prepare_target(linear_pixels, self.model.resolution, "the picture array")
            digest = hashlib.sha256(np.ascontiguousarray(np.asarray(picture)).tobytes()).hexdigest()
            notices += more
        named_mask, weights = None, None
        if isinstance(mask, str | os.PathLike):
            named_mask = _text(mask)
            if size is not None:  # the mask of an array is sized by the array: read here
                weights = search.prepare_mask(_read(named_mask, "mask"), size, self.model.resolution, named_mask)
        elif mask is not None:
            named_mask = ARRAY
            mask_pixels = _linear(mask, "mask", linear=False)[0]
            weights = search.prepare_mask(mask_pixels, size or _size(target), self.model.resolution, "array")
        request = Request(
            target,
            named_mask,
            initial[0],
            init_values=initial[1],
            seed=seed,
            settings=settings or Settings(),
            verified=verified,
            corrections=corrections,
            refine_steps=refine,
            variant=self.variant,
            answer=answer,
            pixels=pixels,
            weights=weights,
            target_sha256=digest,
            outputs=None if outputs is None else outputs._request(),
        )
        return request, notices


def _check_choices(settings: object, init: object) -> None:
    """Raises the MatfitError of `settings` that is no `Settings` or `init` that is no path or `Material`."""
    if settings is not None and not isinstance(settings, Settings):
        raise FitError(
            f"settings {_shown(settings)} is no matfit.Settings: give Settings(...) or None", field="settings"
        )
    if init is not None and not isinstance(init, str | os.PathLike | Material):
        raise ParameterError(
            f"init {_shown(init)} is no params.json path or matfit.Material: give one, or "
            "Material.from_array(values) of the 19 values in `matfit params` order",
            field="init",
        )


def _paths(pictures: object) -> list[str | os.PathLike[str]]:
    """Returns the picture paths of `fit_all`'s `pictures` (FitError for anything but an iterable of paths)."""
    if isinstance(pictures, str | os.PathLike) or not isinstance(pictures, Iterable):
        raise FitError(f"pictures {_shown(pictures)} is no list of paths: give a list of picture files", field="target")
    listed = list(pictures)
    for picture in listed:
        if not isinstance(picture, str | os.PathLike):
            raise FitError(f"picture {_shown(picture)} is no path: fit_all fits picture files", field="target")
    return listed


def _read(path: str, name: str) -> Image:
    """Returns a picture file's linear pixels (the one-line ImageError of a missing or unreadable one)."""
    from matfit import images

    if not os.path.isfile(path):
        raise ImageError(f"{name} {path} is not a file: give the picture's path", field=name)
    return np.asarray(images.load(path).pixels, np.float32)


def _size(path: str) -> tuple[int, int]:
    """Returns (height, width) of a picture file (the one-line ImageError of a missing or unreadable one)."""
    from matfit import images

    if not os.path.isfile(path):
        raise ImageError(f"target {path} is not a file: give the picture's path", field="target")
    width, height = images.header(path)[:2]
    return height, width


def fit(
    picture: Picture,
    *,
    mask: Picture | None = None,
    init: str | os.PathLike[str] | Material | None = None,
    model: str | os.PathLike[str] | Model | None = None,
    settings: Settings | None = None,
    linear: bool = False,
    verify: bool = True,
    corrections: int | None = None,
    answer: Literal["clean", "best"] = "clean",
    refine: int = 0,
    seed: int = 0,
    variant: str | None = None,
    outputs: Outputs | None = None,
) -> Fit:
    """Returns the fit of the material whose render looks most like `picture`: what `matfit fit` finds.

    `picture`: a file's path (PNG, JPEG, TIFF, EXR) or its pixels, an (H, W, 3) array (or (H, W, 4), alpha
    dropped): float sRGB in 0-1, uint8 0-255 or uint16, or linear float with `linear=True`. `mask`: the same
    kinds, white where the fit looks. `init`: a params.json or a `Material` that joins the candidates.
    `model`: a model folder or `load_model()`'s (None: the shipped one). `settings`, `verify`, `corrections`,
    `answer`, `refine`, `seed`, `variant`: `matfit fit`'s options of those names, with its defaults. A picture
    file gives the parameters of `matfit fit PICTURE -o params.json` bit for bit. `outputs`: the files to write
    (`Outputs`: checked before any work, written together once the fit is done), or None to write nothing. For many
    pictures, a `Fitter` loads the model once.
    """
    with Fitter(model, verify=verify and not refine, variant=variant) as fitter:
        return fitter.fit(
            picture,
            mask=mask,
            init=init,
            settings=settings,
            linear=linear,
            verify=verify,
            corrections=corrections,
            answer=answer,
            refine=refine,
            seed=seed,
            outputs=outputs,
        )


def fit_sequence(
    frames: Iterable[Picture] | str | os.PathLike[str],
    *,
    model: str | os.PathLike[str] | Model | None = None,
    settings: Settings | None = None,
    reinit: bool = True,
    init: str | os.PathLike[str] | Material | None = None,
    linear: bool = False,
    out: str | os.PathLike[str] | None = None,
    render: tuple[int, int] | None = None,
    progress: Callable[[int, int, float], None] | None = None,
) -> list[Fit]:
    """Returns the fits of a sequence of frames in order: `matfit sequence`'s.

    Each frame is fitted by the neural search alone (no Mitsuba stage), from the encoders' guesses plus, with
    `reinit`, the previous frame's answer (the first frame: `init`'s). `settings` None: `matfit sequence`'s
    (hybrid, 100 evaluations). `frames`: pictures (paths or arrays), written nowhere; or, with `out`, the folder
    of the frames (in natural order: frame_2 before frame_10), which `matfit sequence FRAMES -o OUT` fits: each
    frame's result written at once to `OUT/<frame>.json` (its `Fit.to_json()`), then summary.md and preview.png,
    and with `render=(size, spp)` each frame's Mitsuba render `OUT/<frame>-render.png`. Every output is checked
    before the first fit, and the same call again resumes: frames whose results are there, for the same frames,
    settings and model, are read back, not fitted again. `progress(frames done, frames in all, frames a second)`
    hears of each frame (with `out`).
    """
    if not isinstance(reinit, bool):
        raise FitError(f"reinit {_shown(reinit)} is not True or False", field="reinit")
    _check_choices(settings, init)
    settings = settings or Settings(Method.hybrid, 100)
    if out is not None:
        return _written_sequence(frames, model, settings, reinit, init, out, render, progress, linear)
    if isinstance(frames, str | os.PathLike) or render is not None or progress is not None:
        raise FitError(
            "a folder of frames, render= and progress= are for a sequence written to a folder: give out= too, or "
            "give the frames as a list",
            field="out",
        )
    from matfit.fit import fitfile, stages

    fitter = Fitter(model, verify=False)
    start = None if init is None else (init if isinstance(init, Material) else Material.read(init)).unit()
    previous = None if start is None else np.asarray(start, np.float32)
    fits: list[Fit] = []
    for frame in frames:
        request, notices = fitter._request(frame, None, None, settings, linear, False, None, "best", 0, 0)
        if request.pixels is None:  # a file: read as `matfit sequence` reads a frame
            pixels, _, _ = fitfile.request_target(request, fitter.model.resolution)
            request = dataclasses.replace(request, pixels=pixels)
        candidates = None if previous is None else previous[None]
        request = dataclasses.replace(request, candidates=candidates)
        result: search.Result = fitfile.fit_neural(request, fitter.model)
        outcome = stages.neural_outcome(request, result, np.asarray(request.pixels), fitter.model.path, notices)
        fits.append(_fit_of(outcome, request.target))
        previous = np.asarray(result.unit, np.float32) if reinit else None
    return fits


def _written_sequence(
    frames: object,
    model: str | os.PathLike[str] | Model | None,
    settings: Settings,
    reinit: bool,
    init: str | os.PathLike[str] | Material | None,
    out: str | os.PathLike[str],
    render: tuple[int, int] | None,
    progress: Callable[[int, int, float], None] | None,
    linear: bool,
) -> list[Fit]:
    """Returns `fit_sequence`'s fits of a folder of frames written into `out` (`fit/sequence.run`)."""
    from matfit.fit import sequence
    from matfit.model import dataset

    if not isinstance(frames, str | os.PathLike):
        raise FitError(
            f"frames {_shown(frames)} is no folder: with out=, give the folder that holds the frames", field="frames"
        )
    if not isinstance(out, str | os.PathLike):
        raise OutputError(f"out {_shown(out)} is no path: give the folder to write into", field="out")
    if linear:
        raise ImageError(
            "linear=True describes arrays; frame files say how they are encoded: leave it out", field="linear"
        )
    rendered = None
    if render is not None:
        if not isinstance(render, tuple) or len(render) != 2:
            raise RenderError(f"render {_shown(render)} is not (size, spp): give render=(256, 64)", field="render")
        rendered = (
            _whole("size", render[0], dataset.MIN_RESOLUTION, MAX_SIZE, RenderError),
            _whole("spp", render[1], 1, dataset.MAX_SPP, RenderError),
        )
    fitter = Fitter(model, verify=False)
    written = os.fspath(out)
    frames_found = sequence.run(
        fitter,
        os.fspath(frames),
        out=written,
        settings=settings,
        reinit=reinit,
        render=rendered,
        progress=progress,
        init=_text(init) if isinstance(init, str | os.PathLike) else None,
        init_values=init.array() if isinstance(init, Material) else None,
    )
    fits = []
    for frame in frames_found:
        path = sequence.frame_json_path(written, frame.path)
        document = documents.read(path, "delete it to fit that frame again", FitError)
        image = frame.image if frame.image is not None else fitter.model.decode(np.asarray(frame.unit)[None])[0]
        summary = (
            f"{path}: {settings.method.value}, {frame.evaluations} evaluations, neural RMSE {frame.rmse:.2f} "
            f"(start {frame.start} {frame.start_rmse:.2f}), {frame.seconds:.1f} s"
        )
        fits.append(
            Fit(
                Material.from_array(params.from_unit(np.asarray(frame.unit, np.float64))),
                float(frame.rmse),
                None,
                {},
                {},
                {},
                (frame.note,) if frame.note else (),
                summary,
                np.asarray(frame.target, np.float32),
                np.asarray(image, np.float32),
                None,
                document,
                frame.start,
                float(frame.start_rmse),
                int(frame.evaluations),
            )
        )
    return fits


_renderers: dict[tuple[int, str | None], Renderer] = {}


def render(material: Material, *, size: int = 256, spp: int = 256, seed: int = 0, variant: str | None = None) -> Image:
    """Returns the material rendered by Mitsuba in the test scene: linear RGB float32 (size, size, 3).

    `seed` makes the noise: the same arguments give the same picture. The scene is loaded once a size and kept.
    Where no libLLVM >= 19 is found (and no GPU), it renders with the slower scalar_rgb and warns once
    (RuntimeWarning, the notice `matfit render` prints).
    `images.srgb_encode` (or `fit(..., linear=True)`) takes it from there.
    """
    from matfit.model import dataset
    from matfit.render import engine

    if not isinstance(material, Material):
        raise ParameterError(
            f"render takes a matfit.Material, got {type(material).__name__}: use Material.read(path), "
            "Material.preset(name) or Material.from_dict(...)",
            field="material",
        )
    size = _whole("size", size, dataset.MIN_RESOLUTION, MAX_SIZE, RenderError)
    spp = _whole("spp", spp, 1, dataset.MAX_SPP, RenderError)
    seed = _whole("seed", seed, 0, params.MAX_SEED, RenderError)
    key = (size, variant)
    if key not in _renderers:
        made = engine.Renderer(size, spp, variant)
        if made.notice:  # the slower scalar_rgb: said once a scene, as `matfit render` says it
            warnings.warn(made.notice.removeprefix("notice: "), RuntimeWarning, stacklevel=2)
        _renderers[key] = made
    return _renderers[key].render(material.array(), seed=seed, spp=spp)


F = TypeVar("F", bound=Callable[..., Any])


def _callable(package: str, function: F) -> F:
    """Returns the subpackage `package` made callable as `function` (see the module docstring): the same object
    whichever of the two an import binds to the name."""
    module = importlib.import_module(package)  # the subpackage's __init__ is its docstring alone: cheap

    class CallablePackage(types.ModuleType):
        def __call__(self, *args: Any, **kwargs: Any) -> Any:
            return function(*args, **kwargs)

    module.__class__ = CallablePackage
    module.__wrapped__ = function  # type: ignore[attr-defined]  # inspect.signature and help() read the function's
    module.__doc__ = f"{function.__doc__}\n\nAlso the package {package}: {module.__doc__}"
    return module  # type: ignore[return-value]


if not TYPE_CHECKING:
    fit = _callable("matfit.fit", fit)
    render = _callable("matfit.render", render)
