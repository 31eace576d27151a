"""The public API (`import matfit`, docs/api.md): the command line's answers and errors, arrays, the page's examples."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import matfit
from matfit import errors, images, params, shipped
from matfit.app.cli import app
from matfit.model import architectures, weight_files
from matfit.rendering import export, process, scene
from tests.helpers import random_model

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "api.md"
PICTURE = shipped.EXAMPLES / "recoloured.png"
TIMINGS = ("fit_seconds", "wall_time_s", "seconds")
NO_LLVM = (
    "no libLLVM >= 19 found, rendering with the slower scalar_rgb variant (install Debian's libllvm19 or set "
    "DRJIT_LIBLLVM_PATH for llvm_ad_rgb)"
)


def without_timings(document: object) -> object:
    """Returns a params.json document with every timing left out: the rest is the same run to run."""
    if isinstance(document, dict):
        return {key: without_timings(value) for key, value in document.items() if key not in TIMINGS}
    return document


def cli_error(*arguments: object) -> str:
    """Returns the one-line message (after `error: `) of a `matfit` command that fails with exit code 2."""
    result = CliRunner().invoke(app, [str(argument) for argument in arguments])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1, result.output
    return lines[0].removeprefix("error: ")


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> Path:
    """Returns a model folder holding a random 32 px decoder and one random encoder: fits in a second, not well."""
    model = random_model()
    folder = tmp_path_factory.mktemp("tiny-model")
    weight_files.save(str(folder / "decoder.msgpack"), model.decoder)
    encoder = model.encoders[8]
    description = architectures.architecture("encoder-8", model.resolution)
    weight_files.save(str(folder / "encoder-8.msgpack"), dataclasses.replace(encoder, description=description))
    return folder


@pytest.fixture(scope="module")
def fitter(tiny_model):
    """Returns a Fitter of the tiny model without render processes (the checks of a picture run before any work)."""
    with matfit.Fitter(tiny_model, verify=False) as warm:
        yield warm


def test_import_matfit_loads_neither_jax_nor_mitsuba_and_names_only_its_api():
    code = (
        "import sys, matfit; heavy = ('jax', 'mitsuba', 'drjit', 'OpenImageIO', 'flax', 'typer');"
        "print([name for name in heavy if name in sys.modules]); print(sorted(matfit.__all__))"
    )
    loaded, names = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.splitlines()
    assert loaded == "[]"
    assert names == str(sorted(["Fit", "Fitter", "Material", "MatfitError", "Outputs", "Scene", "Settings", "fit",
                                "fit_sequence", "load_model", "render"]))  # fmt: skip


def test_fit_and_render_are_plain_functions_beside_the_fitting_and_rendering_packages():
    import inspect

    import matfit.fitting.search
    import matfit.rendering.engine

    assert inspect.isfunction(matfit.fit) and inspect.isfunction(matfit.render)
    assert "matfit.fit" not in sys.modules and "matfit.render" not in sys.modules
    assert matfit.fitting.search.neural_search and matfit.rendering.engine.Renderer
    assert next(iter(inspect.signature(matfit.fit).parameters)) == "picture"
    assert next(iter(inspect.signature(matfit.render).parameters)) == "material"
    assert (
        matfit.fit.__doc__.startswith("Returns the fit of the material")
        and matfit.fit.__module__ == "matfit.api.fitter"
    )
    package = Path(matfit.__file__).parent
    assert [path for path in package.rglob("*.py") if "__class__ =" in path.read_text(encoding="utf-8")] == []


def test_material_names_the_19_parameters_with_their_defaults_and_ranges():
    fields = dataclasses.fields(matfit.Material)
    assert tuple(field.name for field in fields) == params.NAMES
    default = matfit.Material()
    np.testing.assert_array_equal(default.array(), params.DEFAULTS)
    gold = matfit.Material.preset("gold")
    assert gold.metallic == 1.0 and gold.roughness == 0.25
    assert set(matfit.Material.presets()) >= {"gold", "glass", "jade", "milk"}
    assert matfit.Material.from_json(gold.to_json()) == gold
    assert matfit.Material.from_unit(gold.unit()) == pytest.approx(gold)
    assert matfit.Material.from_dict({"roughness": np.float32(0.25)}).roughness == 0.25
    assert json.loads(gold.to_json())["params"] == params.to_mapping(gold.array())
    with pytest.raises(matfit.MatfitError, match=r"parameter 'roughness' = 2.0 is out of range: use a value in"):
        dataclasses.replace(gold, roughness=2.0)
    with pytest.raises(matfit.MatfitError, match="unknown parameter 'rougness': did you mean 'roughness'"):
        matfit.Material.from_dict({"rougness": 0.2})
    with pytest.raises(matfit.MatfitError, match=r"a material is 19 values, got shape \(3,\)"):
        matfit.Material.from_array([0.1, 0.2, 0.3])


def test_material_exports_are_the_command_lines(tmp_path):
    jade = matfit.Material.preset("jade")
    assert jade.to_mitsuba() == {"bsdf": scene.bsdf(jade.array()), "interior": scene.medium(jade.array())}
    assert jade.to_mitsuba_xml() == export.mitsuba_xml(jade.array())
    assert jade.to_blender_script("jade") == export.blender_script(jade.array(), "jade")
    with pytest.raises(matfit.MatfitError, match="material name"):
        jade.to_blender_script('a "quoted" name')
    (tmp_path / "params.json").write_text(jade.to_json())
    assert matfit.Material.read(tmp_path / "params.json") == jade


MATERIAL_ORDER = "one value a parameter, in the order `matfit params` lists them"


@pytest.mark.parametrize(
    ("call", "message"),
    [
        pytest.param(
            lambda: matfit.Material.from_dict(None),
            'values None is no mapping of names to values: give a dict like {"roughness": 0.2}',
            id="from-dict-none",
        ),
        pytest.param(
            lambda: matfit.Material.from_dict({1: 0.2}),
            "parameter name 1 is not text: give the names `matfit params` lists",
            id="from-dict-number-name",
        ),
        pytest.param(
            lambda: matfit.Material.from_array(["a"] * 19),
            f"values of type list holds <U1 values: give 19 real numbers, {MATERIAL_ORDER}",
            id="from-array-text",
        ),
        pytest.param(
            lambda: matfit.Material.from_array([[0.1, 0.2], [0.3]]),
            f"values [[0.1, 0.2], [0.3]] is no list of numbers: give 19 numbers, {MATERIAL_ORDER}",
            id="from-array-ragged",
        ),
        pytest.param(
            lambda: matfit.Material.from_array(np.array([None] * 19)),
            f"values of type ndarray holds object values: give 19 real numbers, {MATERIAL_ORDER}",
            id="from-array-objects",
        ),
        pytest.param(  # its imaginary part was dropped without a word (NumPy's ComplexWarning only)
            lambda: matfit.Material.from_array(np.full(19, 0.1 + 0.5j)),
            f"values of type ndarray holds complex128 values: give 19 real numbers, {MATERIAL_ORDER}",
            id="from-array-complex",
        ),
        pytest.param(
            lambda: matfit.Material.from_unit([0.5] * 5),
            f"a material is 19 values, got shape (5,): give {MATERIAL_ORDER}",
            id="from-unit-5",
        ),
        pytest.param(
            lambda: matfit.Material.from_json(None),
            "text None is no params.json text: give its str or bytes (Material.read reads a file)",
            id="from-json-none",
        ),
        pytest.param(
            lambda: matfit.Material.read(5), "path 5 is no path: give a params.json file's path", id="read-number"
        ),
        pytest.param(
            lambda: matfit.Material().to_blender_script(5),
            "name 5 is not text: give the material's name, like 'matfit'",
            id="blender-name-number",
        ),
    ],
)
def test_bad_values_of_a_material_raise_one_line_parameter_errors(call, message):
    with pytest.raises(matfit.MatfitError) as error:
        call()
    assert isinstance(error.value, errors.ParameterError) and str(error.value) == message


def test_render_checks_its_arguments_before_rendering():
    with pytest.raises(matfit.MatfitError, match="size 4 is out of range: use 8 to 4096"):
        matfit.render(matfit.Material(), size=4)
    with pytest.raises(matfit.MatfitError, match=r"^size 16.5 is not a whole number: use 8 to 4096$"):
        matfit.render(matfit.Material(), size=16.5)  # type: ignore[arg-type]
    with pytest.raises(matfit.MatfitError, match=r"^seed '0' is not a whole number: use 0 to 4294967295$"):
        matfit.render(matfit.Material(), seed="0")  # type: ignore[arg-type]
    with pytest.raises(matfit.MatfitError, match=r"render takes a matfit.Material, got str:"):
        matfit.render("gold")  # type: ignore[arg-type]


def test_render_warns_once_where_it_falls_back_to_scalar_rgb():
    # a new process: one Mitsuba variant a process. The machine is made one without libLLVM and GPU.
    code = (
        "import json, os, warnings, matfit\n"
        "from matfit.rendering import engine\n"
        "engine.find_libllvm = lambda: None\n"
        "engine.cuda_problem = lambda: 'no GPU here'\n"
        "os.environ['DRJIT_LIBLLVM_PATH'] = ''\n"
        "with warnings.catch_warnings(record=True) as caught:\n"
        "    warnings.simplefilter('always')\n"
        "    gold = matfit.Material.preset('gold')\n"
        "    shapes = [matfit.render(gold, size=16, spp=1, seed=seed).shape for seed in (0, 1)]\n"
        "print(json.dumps([[w.category.__name__, str(w.message)] for w in caught]), shapes)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    warned, shapes = run.stdout.rstrip().split("] ", 1)
    assert json.loads(warned + "]") == [["RuntimeWarning", NO_LLVM]]  # once for the scene, not each render
    assert shapes == "[(16, 16, 3), (16, 16, 3)]"


def test_render_is_the_renderers_picture(renderer):
    gold = matfit.Material.preset("gold")
    image = matfit.render(gold, size=16, spp=4, seed=3, variant=renderer.variant)
    assert image.shape == (16, 16, 3) and image.dtype == np.float32
    # rendered on every core: the same picture up to the last bits the threads' order changes (docs/fitting.md)
    again = matfit.render(gold, size=16, spp=4, seed=3, variant=renderer.variant)
    np.testing.assert_allclose(image, again, rtol=0, atol=1e-5)
    assert not np.allclose(image, matfit.render(gold, size=16, spp=4, seed=4, variant=renderer.variant), atol=1e-3)


def raised(call: Callable[[], object]) -> str:
    """Returns the message of the MatfitError that `call()` raises (no other exception), checked to be one line."""
    with pytest.raises(matfit.MatfitError) as error:
        call()
    message = str(error.value)
    assert message and "\n" not in message, message
    return message


KINDS = "give float sRGB in 0-1, uint8 0-255, uint16 0-65535, or linear float with linear=True"
SHAPES = "give (H, W, 3) RGB, (H, W, 4) with alpha, or (H, W) grey"
FINITE = "contains NaN or infinite values: fix or clamp them first"
NEGATIVE = (
    "values run from -0.5 to -0.5, outside sRGB's 0-1: divide 0-255 values by 255, or pass "
    "linear=True for linear (HDR) values"
)


@pytest.mark.parametrize(
    ("picture", "linear", "message"),
    [
        pytest.param(np.zeros((64, 64, 5), np.float32), False, f"has shape (64, 64, 5): {SHAPES}", id="5-channels"),
        pytest.param(np.zeros((0, 0, 3), np.float32), False, f"has shape (0, 0, 3): {SHAPES}", id="empty"),
        pytest.param(np.zeros(4, np.float32), False, f"has shape (4,): {SHAPES}", id="1-d"),
        pytest.param(None, False, f"has shape (): {SHAPES}", id="none"),
        pytest.param([[1, 2], [3]], False, "cannot be read (", id="ragged"),
        pytest.param(np.zeros((4, 4, 3), object), False, f"holds object values: {KINDS}", id="object"),
        pytest.param(np.zeros((4, 4, 3), complex), False, f"holds complex128 values: {KINDS}", id="complex"),
        pytest.param(np.zeros((4, 4, 3), bool), False, f"holds bool values: {KINDS}", id="bool"),
        pytest.param(np.full((4, 4, 3), "0"), False, f"holds <U1 values: {KINDS}", id="str"),
        pytest.param(np.zeros((4, 4, 3), np.int64), False, f"holds int64 values: {KINDS}", id="int64"),
        pytest.param(np.zeros((4, 4, 3), np.uint16), True, f"holds uint16 values: {KINDS}", id="uint16-linear"),
        pytest.param(np.full((4, 4, 3), np.nan, np.float32), False, FINITE, id="nan"),
        pytest.param(np.full((4, 4, 3), np.inf, np.float32), False, FINITE, id="inf"),
        pytest.param(np.full((4, 4, 3), -np.inf, np.float32), True, FINITE, id="inf-linear"),
        pytest.param(np.full((4, 4, 3), -0.5, np.float32), False, NEGATIVE, id="negative"),
        pytest.param(
            np.linspace(0, 255, 48).reshape(4, 4, 3),
            False,
            "values run from 0 to 255, outside sRGB's 0-1: divide 0-255 values by 255",
            id="0-255",
        ),
    ],
)
def test_a_bad_array_raises_a_matfit_error_naming_it_and_the_fix(fitter, picture, linear, message):
    assert re.search(
        f"^the picture array('s)? {re.escape(message)}", raised(lambda: fitter.fit(picture, linear=linear))
    )


def test_a_grey_array_is_fitted_as_its_rgb(fitter):
    grey = np.linspace(0.2, 0.8, 64 * 64, dtype=np.float32).reshape(64, 64)
    as_grey = fitter.fit(grey, answer="best")
    assert as_grey.notices[0] == "the picture array is grey: replicated to RGB"
    assert as_grey.material == fitter.fit(np.repeat(grey[:, :, None], 3, axis=2), answer="best").material


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        pytest.param(
            {"mask": np.ones((8, 8), np.float32)},
            "the mask array is 8x8, the target is 16x16: make the mask the same",
            id="mask-array-size",
        ),
        pytest.param(
            {"mask": "mask.png"},
            "the mask mask.png is 8x8, the target is 16x16: make the mask the same size",
            id="mask-file-size",
        ),
        pytest.param({"mask": "folder"}, "mask folder is not a file: give the picture's path", id="mask-folder"),
        pytest.param(
            {"mask": np.full((16, 16), np.nan, np.float32)},
            "the mask array contains NaN or infinite values",
            id="mask-nan",
        ),
        pytest.param(
            {"init": [0.1, 0.2]},
            "init [0.1, 0.2] is no params.json path or matfit.Material: give one, or",
            id="init-list",
        ),
        pytest.param(
            {"init": np.zeros(19)}, "init of type ndarray is no params.json path or matfit.Material", id="init-array"
        ),
        pytest.param(
            {"init": "init.json"}, 'init.json: "params" must be a JSON object of names and values', id="init-length"
        ),
        pytest.param(
            {"init": "folder"},
            "cannot read folder: it is a folder, not a regular file: give a params.json",
            id="init-folder",
        ),
        pytest.param({"seed": -1}, "seed -1 is out of range: use 0 to 4294967295", id="seed-negative"),
        pytest.param({"seed": "1"}, "seed '1' is not a whole number: use 0 to 4294967295", id="seed-text"),
        pytest.param(
            {"settings": np.zeros((9, 9))},
            "settings of type ndarray is no matfit.Settings: give Settings(",
            id="settings",
        ),
    ],
)
def test_bad_arguments_of_an_array_raise_matfit_errors_naming_them_and_the_fix(
    fitter, tmp_path, monkeypatch, arguments, message
):
    monkeypatch.chdir(tmp_path)
    images.write("mask.png", np.ones((8, 8, 3), np.float32))
    Path("init.json").write_text('{"params": [0.1, 0.2, 0.3]}')  # a material of 3 values, not 19 named
    Path("folder").mkdir()
    assert message in raised(lambda: fitter.fit(np.full((16, 16, 3), 0.5, np.float32), **arguments))


@pytest.fixture
def work(monkeypatch) -> list[str]:
    """Returns the work begun while a test runs, as it begins: "search" for each neural search, "pool" for each start
    of render processes (both the real ones, recorded on the way in)."""
    from matfit.fitting import search
    from matfit.rendering import process

    begun: list[str] = []
    neural_search, start_pool = search.neural_search, process.Pool.__init__

    def searched(*arguments, **keywords):
        begun.append("search")
        return neural_search(*arguments, **keywords)

    def started(pool, *arguments, **keywords):
        begun.append("pool")
        start_pool(pool, *arguments, **keywords)

    monkeypatch.setattr(search, "neural_search", searched)
    monkeypatch.setattr(process.Pool, "__init__", started)
    return begun


NN = {"settings": matfit.Settings(method="nn")}
ARRAY = np.full((16, 16, 3), 0.5, np.float32)


@pytest.mark.parametrize(
    ("call", "error", "message"),
    [
        pytest.param(
            lambda f, g: matfit.fit(g, model=f.model, refine="3", verify=False, **NN),
            errors.FitError,
            "refine '3' is not a whole number: use 0 to 10000",
            id="refine-text",
        ),
        pytest.param(  # verified by default: refused before the render processes start
            lambda f, g: matfit.fit(g, model=f.model, corrections="2", **NN),
            errors.FitError,
            "corrections '2' is not a whole number: use 0 to 100",
            id="corrections-text",
        ),
        pytest.param(  # was verified
            lambda f, g: matfit.fit(g, model=f.model, verify="no", **NN),
            errors.FitError,
            "verify 'no' is not True or False: give verify=True or verify=False",
            id="verify-text",
        ),
        pytest.param(
            lambda f, g: matfit.Fitter(f.model, verify="no"),
            errors.FitError,
            "verify 'no' is not True or False",
            id="fitter-verify-text",
        ),
        pytest.param(  # was read as linear
            lambda f, g: f.fit(ARRAY, linear="no", **NN),
            errors.ImageError,
            "linear 'no' is not True or False: give linear=True or linear=False",
            id="linear-text",
        ),
        pytest.param(
            lambda f, g: f.fit(g, answer=5, **NN),
            errors.FitError,
            "answer 5 is not one of clean, best: give answer='clean' or answer='best'",
            id="answer-number",
        ),
        pytest.param(
            lambda f, g: f.fit(g, settings=matfit.Settings(evaluations="abc")),
            errors.FitError,
            "evaluations 'abc' is not a whole number: use 21 to 1000000",
            id="evaluations-text",
        ),
        pytest.param(  # failed after seconds of work
            lambda f, g: f.fit(g, settings=matfit.Settings(method="hybrid", evaluations=60.5)),
            errors.FitError,
            "evaluations 60.5 is not a whole number: use 21 to 1000000",
            id="evaluations-fraction",
        ),
        pytest.param(
            lambda f, g: f.fit(g, settings=matfit.Settings(starts=2.5)),
            errors.FitError,
            "starts 2.5 is not a whole number: use 1 to 64",
            id="starts-fraction",
        ),
        pytest.param(
            lambda f, g: f.fit(g, settings=matfit.Settings(adaptive="no")),
            errors.FitError,
            "adaptive 'no' is not True or False",
            id="adaptive-text",
        ),
        pytest.param(
            lambda f, g: f.fit(g, settings=matfit.Settings(initial_step=-1.0)),
            errors.FitError,
            "initial_step -1.0 is out of range: use above 0 up to 1",
            id="initial-step-negative",
        ),
        pytest.param(
            lambda f, g: f.fit(g, settings=matfit.Settings(polish_rate=float("nan"))),
            errors.FitError,
            "polish_rate nan is out of range: use above 0 up to 1",
            id="polish-rate-nan",
        ),
        pytest.param(  # was said only after the first picture was fitted and written
            lambda f, g: f.fit_all([g], "fits", done=5, **NN),
            errors.FitError,
            "done 5 is not callable: give a function or None",
            id="fit-all-done-number",
        ),
        pytest.param(
            lambda f, g: f.fit_all([g], "fits", outputs="p.json", **NN),
            errors.OutputError,
            "outputs 'p.json' is no matfit.Outputs: give Outputs(params, ...) or None",
            id="fit-all-outputs-text",
        ),
        pytest.param(
            lambda f, g: f.fit(g, answers=5, **NN),
            errors.FitError,
            "answers 5 is not callable: give a function or None",
            id="answers-number",
        ),
        pytest.param(  # a scene fit has no stages of the test scene's: its steps go to progress
            lambda f, g: f.fit(g, scene=matfit.Scene("scene.xml", "ball"), answers=print),
            errors.FitError,
            "answers hears the stages of a fit in the test scene; a scene fit reports its steps to progress",
            id="answers-of-a-scene-fit",
        ),
        pytest.param(
            lambda f, g: matfit.fit_sequence([g], model=f.model, progress=5, **NN),
            errors.FitError,
            "progress 5 is not callable: give a function or None",
            id="sequence-progress-number",
        ),
        pytest.param(
            lambda f, g: matfit.fit_sequence(5, model=f.model, **NN),
            errors.FitError,
            "frames 5 is no list of pictures: give the frames' paths or arrays, or their folder with out=",
            id="sequence-frames-number",
        ),
        pytest.param(
            lambda f, g: matfit.fit_sequence([ARRAY], model=f.model, linear="no", **NN),
            errors.ImageError,
            "linear 'no' is not True or False",
            id="sequence-linear-text",
        ),
    ],
)
def test_a_value_of_the_wrong_kind_is_refused_with_one_line_before_any_work(
    fitter, tmp_path, monkeypatch, work, call, error, message
):
    monkeypatch.chdir(tmp_path)
    shutil.copy(PICTURE, "g.png")
    with pytest.raises(matfit.MatfitError) as raised:
        call(fitter, "g.png")
    assert type(raised.value) is error and str(raised.value).startswith(message), raised.value
    assert "\n" not in str(raised.value)
    assert work == [] and os.listdir(tmp_path) == ["g.png"]  # no search, no render process, nothing written


def test_fit_all_takes_a_material_as_init_and_keys_its_journal_on_the_materials_values(fitter, tmp_path):
    # init=Material was read as a file named 'Material' (FileNotFoundError) after the checks
    shutil.copy(PICTURE, tmp_path / "a.png")
    (tmp_path / "b.png").write_text("no picture")  # fails: the journal stays, and says what the next call keeps
    pictures, folder, gold = [tmp_path / "a.png", tmp_path / "b.png"], tmp_path / "fits", matfit.Material.preset("gold")
    heard: list[str] = []

    def done(picture: str, params_json: str, fit: object) -> None:
        heard.append(f"{os.path.basename(picture)} {type(fit).__name__}")

    assert fitter.fit_all(pictures, folder, init=gold, answer="best", done=done, **NN) == 1
    written = json.loads((folder / "a.params.json").read_text())
    alone = fitter.fit(tmp_path / "a.png", init=gold, answer="best", **NN)
    assert written["params"] == alone.document["params"] and written["init"] == "Material"
    assert fitter.fit_all(pictures, folder, init=gold, answer="best", done=done, **NN) == 1  # the same material: kept
    assert fitter.fit_all(pictures, folder, init=matfit.Material(), answer="best", done=done, **NN) == 1  # another
    assert heard == ["a.png Fit", "b.png ImageError", "a.png NoneType", "b.png ImageError", "a.png Fit",
                     "b.png ImageError"]  # fmt: skip


@pytest.mark.parametrize(
    ("folder", "option", "name"),
    [(True, "model", None), (False, "init", "init.json"), (False, "model", "model.txt"), (False, "model", "empty")],
    ids=["folder-picture", "init-length", "model-file", "model-empty-folder"],
)
def test_bad_files_raise_the_command_lines_message(tiny_model, tmp_path, folder, option, name):
    (tmp_path / "init.json").write_text("[0.1, 0.2, 0.3]")  # three values: no params.json
    (tmp_path / "model.txt").write_text("no model")
    (tmp_path / "empty").mkdir()
    picture = tmp_path if folder else PICTURE
    given = {"model": tiny_model, option: tiny_model if name is None else tmp_path / name}
    options = [argument for key, value in given.items() for argument in (f"--{key}", value)]
    expected = cli_error("fit", picture, "-o", tmp_path / "p.json", "--no-verify", *options)
    assert raised(lambda: matfit.fit(picture, verify=False, **given)) == expected
    assert not (tmp_path / "p.json").exists()


def test_a_model_that_is_no_folder_raises_a_matfit_error():
    expected = "model 3 is no model folder: give a folder's path, load_model()'s model, or None for the shipped one"
    assert raised(lambda: matfit.load_model(3)) == expected  # type: ignore[arg-type]
    assert raised(lambda: matfit.fit(PICTURE, model=3, verify=False)) == expected  # type: ignore[arg-type]


def test_bad_pictures_raise_matfit_errors_with_the_command_lines_messages(fitter, tmp_path):
    missing = tmp_path / "missing.png"
    with pytest.raises(matfit.MatfitError) as error:
        fitter.fit(missing)
    assert str(error.value) == cli_error("fit", missing, "-o", tmp_path / "p.json", "--no-verify")
    with pytest.raises(matfit.MatfitError, match="linear=True describes an array's values"):
        fitter.fit(PICTURE, linear=True)
    with pytest.raises(matfit.MatfitError, match=r"settings 3 is no matfit\.Settings"):
        fitter.fit(PICTURE, settings=3)  # type: ignore[arg-type]


def test_a_mask_of_another_size_is_the_command_lines_error(fitter, tmp_path):
    mask = tmp_path / "mask.png"
    images.write(str(mask), np.ones((8, 8, 3), np.float32))
    with pytest.raises(matfit.MatfitError) as error:
        fitter.fit(PICTURE, mask=mask)
    expected = cli_error(
        "fit", PICTURE, "-o", tmp_path / "p.json", "--no-verify", "--mask", mask, "--model", fitter.model.path
    )
    assert str(error.value) == expected  # fmt: skip
    with pytest.raises(matfit.MatfitError, match="the mask array is 8x8, the target is 256x256"):
        fitter.fit(PICTURE, mask=np.ones((8, 8), np.float32))


@pytest.mark.parametrize(
    ("outputs", "options"),
    [
        ({"params": "p.txt"}, ["-o", "p.txt"]),
        ({"params": "p.json", "report": "r.bmp"}, ["-o", "p.json", "--report", "r.bmp"]),
        ({"params": "p.json", "report": "p.png", "render": "p.png"}, ["-o", "p.json", "--report", "p.png",
                                                                     "--render", "p.png"]),
        ({"params": "p.json", "mitsuba_xml": "m.txt"}, ["-o", "p.json", "--mitsuba-xml", "m.txt"]),
        ({"params": "p.json", "render": str(PICTURE)}, ["-o", "p.json", "--render", str(PICTURE)]),
    ],
    ids=["params-suffix", "report-format", "named-twice", "xml-suffix", "overwrites-the-picture"],
)  # fmt: skip
def test_bad_outputs_are_refused_before_the_model_loads_with_the_command_lines_message(
    tiny_model, tmp_path, monkeypatch, outputs, options
):
    monkeypatch.chdir(tmp_path)
    expected = cli_error("fit", PICTURE, "--no-verify", "--model", tiny_model, *options)
    with matfit.Fitter(tiny_model, verify=False) as fitter:
        message = raised(lambda: fitter.fit(PICTURE, outputs=matfit.Outputs(**outputs)))
        assert message.endswith(expected.split(" ", 1)[1])  # the command line names its option, `--report ...`
        assert fitter._model is None  # refused before the model loaded
    assert list(tmp_path.iterdir()) == []


def test_outputs_that_are_no_outputs_raise_matfit_errors_naming_them(fitter):
    with pytest.raises(matfit.MatfitError, match=r"outputs 'p\.json' is no matfit\.Outputs: give Outputs\(params"):
        fitter.fit(PICTURE, outputs="p.json")  # type: ignore[arg-type]
    with pytest.raises(matfit.MatfitError, match="report 3 is no path: give a file's path or None"):
        fitter.fit(PICTURE, outputs=matfit.Outputs(report=3))  # type: ignore[arg-type]
    with pytest.raises(matfit.MatfitError, match="render_size 100000 is out of range: use 8 to 4096"):
        fitter.fit(PICTURE, outputs=matfit.Outputs(render_size=100_000))
    with pytest.raises(matfit.MatfitError, match=r"render_spp 2\.5 is not a whole number"):
        fitter.fit(PICTURE, outputs=matfit.Outputs(render_spp=2.5))  # type: ignore[arg-type]


def test_a_fit_with_outputs_writes_them_together_and_the_fit_is_named_by_its_params_json(fitter, tmp_path):
    outputs = matfit.Outputs(tmp_path / "p.json", mitsuba_xml=tmp_path / "m.xml", blender=tmp_path / "b.py")
    fit = fitter.fit(PICTURE, answer="best", outputs=outputs)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["b.py", "m.xml", "p.json"]
    written = json.loads((tmp_path / "p.json").read_text())
    assert written == fit.document and written["wall_time_s"] > 0
    assert (tmp_path / "m.xml").read_text() == fit.material.to_mitsuba_xml()
    assert fit.summary.startswith(f"{tmp_path / 'p.json'}: lbfgsb")


def test_a_fit_checks_its_request_once(fitter, tmp_path, monkeypatch):
    from matfit.fitting.request import Request

    checked = []
    check = Request.check
    monkeypatch.setattr(Request, "check", lambda self, model=None: (checked.append(model), check(self, model))[1])
    fitter.fit(PICTURE, answer="best")
    fitter.fit(PICTURE, answer="best", outputs=matfit.Outputs(tmp_path / "p.json"))
    assert checked == [fitter.model_path, fitter.model_path]  # each fit's outputs probed once, not twice


def test_fit_all_writes_each_picture_goes_on_past_a_bad_one_and_a_second_call_fits_only_that(fitter, tmp_path):
    shutil.copy(PICTURE, tmp_path / "a.png")
    (tmp_path / "b.png").write_text("no picture")
    pictures, folder = [tmp_path / "a.png", tmp_path / "b.png"], tmp_path / "fits"
    heard: list[tuple[str, str, object]] = []

    def done(picture: str, params_json: str, fit: object) -> None:
        heard.append((os.path.basename(picture), os.path.basename(params_json), type(fit).__name__))

    assert fitter.fit_all(pictures, folder, answer="best", done=done) == 1
    assert heard == [("a.png", "a.params.json", "Fit"), ("b.png", "b.params.json", "ImageError")]
    assert sorted(os.listdir(folder)) == [".matfit-fit-journal.json", "a.params.json"]
    first = (folder / "a.params.json").read_bytes()
    shutil.copy(PICTURE, tmp_path / "b.png")
    heard.clear()
    assert fitter.fit_all(pictures, folder, answer="best", done=done) == 0
    assert heard == [("a.png", "a.params.json", "NoneType"), ("b.png", "b.params.json", "Fit")]
    assert sorted(os.listdir(folder)) == ["a.params.json", "b.params.json"]  # the journal ends with the last
    assert (folder / "a.params.json").read_bytes() == first  # kept, not fitted again
    with pytest.raises(matfit.MatfitError, match="fit_all was given no pictures"):
        fitter.fit_all([], folder)
    with pytest.raises(matfit.MatfitError, match="is no list of paths"):
        fitter.fit_all(str(PICTURE), folder)  # type: ignore[arg-type]
    with pytest.raises(matfit.MatfitError, match="have one name"):
        fitter.fit_all([PICTURE, tmp_path / "recoloured.png"], folder)
    with (
        matfit.Fitter(tmp_path / "no-model", verify=False) as nothing,
        pytest.raises(matfit.MatfitError, match="no-model"),
    ):
        nothing.fit_all(pictures, tmp_path / "new" / "fits")  # refused after the checks, before any fit
    assert not (tmp_path / "new").exists()  # the folders made for the checks are gone


def test_fit_all_never_replaces_a_picture_or_a_users_file_and_keeps_only_matfits_own_fit(fitter, tmp_path):
    # a's report would be the picture a.report.png: refused before any fit, nothing written
    shutil.copy(PICTURE, tmp_path / "a.png")
    shutil.copy(shipped.EXAMPLES / "desaturated.png", tmp_path / "a.report.png")
    pictures = [tmp_path / "a.png", tmp_path / "a.report.png"]
    before = (tmp_path / "a.report.png").read_bytes()
    with pytest.raises(matfit.MatfitError, match=r"report .*a\.report\.png is the target"):
        fitter.fit_all(pictures, tmp_path, answer="best", outputs=matfit.Outputs(report="report.png"))
    assert sorted(os.listdir(tmp_path)) == ["a.png", "a.report.png"]
    assert (tmp_path / "a.report.png").read_bytes() == before
    # a file the user keeps under a picture's params.json name is not replaced
    (tmp_path / "b.png").write_text("no picture")
    pictures, folder = [tmp_path / "a.png", tmp_path / "b.png"], tmp_path / "fits"
    folder.mkdir()
    (folder / "a.params.json").write_text("notes")
    with pytest.raises(matfit.MatfitError, match="matfit did not write it"):
        fitter.fit_all(pictures, folder, answer="best")
    assert os.listdir(folder) == ["a.params.json"] and (folder / "a.params.json").read_text() == "notes"
    (folder / "a.params.json").unlink()
    # a run that stopped part way: its journal keeps a only while a's params.json is matfit's of that picture
    heard: list[tuple[str, str]] = []

    def done(picture: str, params_json: str, fit: object) -> None:
        heard.append((os.path.basename(picture), type(fit).__name__))

    assert fitter.fit_all(pictures, folder, answer="best", done=done) == 1
    written = json.loads((folder / "a.params.json").read_text())
    (folder / "a.params.json").write_text(json.dumps({**written, "target_sha256": "0" * 64}))
    heard.clear()
    assert fitter.fit_all(pictures, folder, answer="best", done=done) == 1
    assert heard == [("a.png", "Fit"), ("b.png", "ImageError")]  # fitted again, not "kept"
    assert json.loads((folder / "a.params.json").read_text())["target_sha256"] == written["target_sha256"]
    heard.clear()
    assert fitter.fit_all(pictures, folder, answer="best", done=done) == 1
    assert heard == [("a.png", "NoneType"), ("b.png", "ImageError")]  # now kept


def test_a_folder_that_is_no_model_is_the_command_lines_error(tmp_path):
    (tmp_path / "empty").mkdir()
    for folder in (tmp_path / "none", tmp_path / "empty"):
        with pytest.raises(matfit.MatfitError) as error:
            matfit.load_model(folder)
        assert str(error.value) == cli_error(
            "fit", PICTURE, "-o", tmp_path / "p.json", "--no-verify", "--model", folder
        )
    assert not (tmp_path / "p.json").exists()


def test_an_array_is_fitted_as_its_file_is_and_named_by_the_hash_of_its_pixels(fitter, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    linear = images.load(str(PICTURE)).pixels  # what a fit of the file reads
    from_file = fitter.fit(PICTURE, answer="best")
    from_array = fitter.fit(linear, linear=True, answer="best")
    assert from_array.material == from_file.material and from_array.neural_rmse == from_file.neural_rmse
    document = json.loads(from_array.to_json())
    assert document["target"] == "array" and from_file.document["target"] == str(PICTURE)
    assert document["target_sha256"] == hashlib.sha256(linear.tobytes()).hexdigest()
    srgb = (images.srgb_encode(linear) * 255).round().astype(np.uint8)
    as_bytes, as_floats = fitter.fit(srgb, answer="best"), fitter.fit(srgb / np.float32(255), answer="best")
    assert as_bytes.material == as_floats.material
    assert list(tmp_path.iterdir()) == []  # nothing written anywhere but the program store


def test_a_sequence_is_fitted_frame_by_frame(fitter):
    linear = images.load(str(PICTURE)).pixels
    frames = [linear, linear * np.float32(0.8)]
    fits = matfit.fit_sequence(frames, model=fitter.model, linear=True, settings=matfit.Settings(evaluations=30))
    assert [fit.document["target"] for fit in fits] == ["array", "array"]
    assert all(fit.mitsuba_rmse is None and fit.verification == {} for fit in fits)


def test_a_sequence_written_to_a_folder_is_matfit_sequences_and_a_second_call_reads_it_back(fitter, tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("frame_2.png", "frame_10.png"):  # natural order: frame_2 first
        shutil.copy(PICTURE, frames / name)
    settings = matfit.Settings(evaluations=30)
    out = tmp_path / "out"
    fits = matfit.fit_sequence(frames, model=fitter.model, settings=settings, out=out)
    assert sorted(os.listdir(out)) == ["frame_10.json", "frame_2.json", "preview.png", "summary.md"]
    assert [fit.document["sequence"]["index"] for fit in fits] == [0, 1]
    assert [fit.to_json() for fit in fits] == [(out / name).read_text() for name in ("frame_2.json", "frame_10.json")]
    in_memory = matfit.fit_sequence(
        [frames / "frame_2.png", frames / "frame_10.png"], model=fitter.model, settings=settings
    )
    assert [fit.material for fit in fits] == [fit.material for fit in in_memory]  # one search, either way
    assert fits[1].start == "previous frame" and fits[1].summary.startswith(f"{out / 'frame_10.json'}: lbfgsb")
    written = {name: (out / name).read_bytes() for name in os.listdir(out)}
    again = matfit.fit_sequence(frames, model=fitter.model, settings=settings, out=out)  # read back, not fitted
    assert [fit.material for fit in again] == [fit.material for fit in fits]
    assert [fit.evaluations for fit in again] == [fit.evaluations for fit in fits]
    np.testing.assert_allclose(again[1].image, fits[1].image, atol=1e-6)  # decoded again from the answer read back
    assert {name: (out / name).read_bytes() for name in os.listdir(out)} == written
    with pytest.raises(matfit.MatfitError, match="with out=, give the folder that holds the frames"):
        matfit.fit_sequence([PICTURE], model=fitter.model, out=out)
    with pytest.raises(matfit.MatfitError, match="give out= too"):
        matfit.fit_sequence(frames, model=fitter.model)


@pytest.mark.slow
def test_fit_of_a_file_gives_the_command_lines_params_json_bit_for_bit(tiny_model, tmp_path, monkeypatch):
    # The defaults of both: verification on a render Pool, two rounds of correction, the clean answer.
    monkeypatch.chdir(tmp_path)
    command = ["fit", str(PICTURE), "-o", "p.json", "--report", "r.png", "--model", str(tiny_model)]
    result = CliRunner().invoke(app, command)
    assert result.exit_code == 0, result.output
    fit = matfit.fit(PICTURE, model=Path(tiny_model))
    written = json.loads((tmp_path / "p.json").read_text())
    assert written["verification"]["corrections"] == 2 and "answer" in written
    assert without_timings(json.loads(fit.to_json())) == without_timings(written)
    assert fit.material == matfit.Material.from_array(params.from_unit(params.to_unit(fit.material.array())))
    assert sorted(path.name for path in tmp_path.iterdir()) == ["p.json", "r.png"]
    # the report the command writes (8-bit), and where the search started
    report = images.srgb_encode(images.load(str(tmp_path / "r.png")).pixels)
    np.testing.assert_allclose(fit.report(), report, atol=0.51 / 255)
    assert fit.start == written["start"] and round(fit.start_rmse, 3) == written["start_rmse"]
    assert fit.evaluations == written["evaluations"] > 0 and fit.start_image.shape == fit.image.shape


def render_children() -> set[int]:
    """Returns the ids of this process's render children (`process.Process`) that still run, from /proc."""
    found = set()
    for entry in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            command = Path(f"/proc/{entry}/cmdline").read_bytes()
        except OSError:  # ended meanwhile
            continue
        if int(stat[1]) == os.getpid() and stat[0] != "Z" and b"serve_requests" in command:
            found.add(int(entry))
    return found


def ended(children: set[int], seconds: float = 60.0) -> bool:
    """Returns whether each of `children` has ended within `seconds` (each ends once its render in hand is done)."""
    deadline = time.monotonic() + seconds
    while children & render_children():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


class StopError(Exception):
    """What a test's `answers` raises."""


def test_a_fit_reports_each_stages_answer_as_it_lands_and_the_last_is_the_fit_returned(tiny_model, tmp_path):
    heard: list[matfit.Fit] = []
    with matfit.Fitter(tiny_model) as fitter:
        fit = fitter.fit(PICTURE, answers=heard.append)  # verified, two rounds of correction, the clean answer
        assert [each.stage for each in heard] == ["neural", "verified", "clean"] and fit.stage == "clean"
        neural, verified, clean = heard
        # the search's answer: no Mitsuba render yet, nor ranges; the same search the fit's params.json records
        assert neural.rendered is None and neural.mitsuba_rmse is None and neural.verification == neural.ranges == {}
        assert neural.evaluations == fit.evaluations and neural.start == fit.start
        assert neural.document["neural_rmse"] == round(neural.neural_rmse, 3) and "mitsuba_rmse" not in neural.document
        assert neural.image.shape == neural.target.shape == fit.image.shape and neural.start_image is not None
        # Mitsuba's after verification: its render and figure, the ranges not measured yet
        kept = verified.verification["kept"]
        assert verified.verification == fit.verification and verified.ranges == {}
        assert verified.mitsuba_rmse == verified.verification["mitsuba_rmse"][kept] and verified.rendered is not None
        # the last is the fit's answer, heard before the call returned, params.json as written but for the timings
        assert clean.material == fit.material and clean.ranges == fit.ranges and clean.answer == fit.answer
        assert without_timings(clean.document) == without_timings(fit.document)
        np.testing.assert_array_equal(clean.rendered, fit.rendered)
        times = [each.document["wall_time_s"] for each in heard]
        assert times == sorted(times) and times[-1] <= fit.document["wall_time_s"]
        # an answers that raises ends the fit there: nothing written, the render processes kept for the next fit
        children = set(fitter._pool._children[k]._child.pid for k in range(fitter._pool.children))

        def stop(each: matfit.Fit) -> None:
            raise StopError(each.stage)  # at the first answer, the start's renders for verification asked for already

        with pytest.raises(StopError, match="neural"):
            fitter.fit(PICTURE, answers=stop, outputs=matfit.Outputs(tmp_path / "p.json"))
        assert os.listdir(tmp_path) == [] and fitter._pool.healthy() and children <= render_children()
        again = fitter.fit(PICTURE)  # no answers: the same fit, the renders left over read by nobody
        assert without_timings(again.document) == without_timings(fit.document) and again.stage == "clean"
    assert ended(children)


def test_an_answers_that_raises_at_the_last_answer_writes_nothing_and_leaves_no_render_process(tiny_model, tmp_path):
    before, started = render_children(), set[int]()

    def stop(each: matfit.Fit) -> None:
        if each.stage == "clean":
            started.update(render_children() - before)
            raise StopError("the last answer")

    model = matfit.load_model(tiny_model)
    with pytest.raises(StopError, match="the last answer"):
        matfit.fit(PICTURE, model=model, answers=stop, outputs=matfit.Outputs(tmp_path / "p.json", report="r.png"))
    assert started and ended(started) and os.listdir(tmp_path) == []


def test_a_fitter_renders_at_the_models_resolution_on_its_render_processes_bit_for_bit(tiny_model):
    from matfit.rendering.engine import Renderer

    material = matfit.Material.preset("jade")
    with matfit.Fitter(tiny_model) as fitter:
        first = fitter.render(material, seed=3, spp=8)
        again = fitter.render(material, seed=3, spp=8)
        other = fitter.render(material, seed=4, spp=8)
        with pytest.raises(matfit.MatfitError, match="spp 0 is out of range"):
            fitter.render(material, spp=0)
        with pytest.raises(matfit.MatfitError, match=r"is no matfit\.Material"):
            fitter.render(material.array(), spp=8)  # type: ignore[arg-type]
    resolution = fitter.model.resolution
    single = Renderer(resolution, 64, threads=1).render(material.array(), seed=3, spp=8)  # one thread: its bits
    assert first.shape == (resolution, resolution, 3) and first.dtype == np.float32
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(first, single)
    assert not np.array_equal(first, other)


NEURAL = matfit.Settings(method="nn")  # a fit in a second with the tiny model, its verification renders included
BOUND = 180.0  # seconds any fit of these tests may take, the render processes' start included: then it hangs


def started(call: Callable[[], object]) -> tuple[threading.Thread, list]:
    """Returns (a started daemon thread that runs `call()`, the list that then holds (True, what it returned) or
    (False, what it raised))."""
    outcome: list = []

    def run() -> None:
        try:
            outcome.append((True, call()))
        except BaseException as error:  # handed to the test's thread
            outcome.append((False, error))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, outcome


def bounded(call: Callable[[], object], seconds: float = BOUND) -> object:
    """Returns what `call()` returns (raises what it raises), run on a thread of its own: fails if it has not ended
    within `seconds` (it hangs: the thread is left blocked)."""
    thread, outcome = started(call)
    thread.join(seconds)
    assert not thread.is_alive(), f"still running after {seconds:.0f} s: it hangs"
    done, value = outcome[0]
    if not done:
        raise value
    return value


def reading_a_render(thread: int) -> bool:
    """Returns whether the thread `thread` waits in `read_message` for a render process's reply to a render."""
    frame = sys._current_frames().get(thread)
    names = []
    while frame is not None:
        names.append((frame.f_code.co_name, type(frame.f_locals.get("self")).__name__))
        frame = frame.f_back
    return ("read_message", "NoneType") in names and ("render", "Process") in names


def when_reading_a_render(thread: int, action: Callable[[], None]) -> threading.Thread:
    """Returns a started thread that runs `action()` once the thread `thread` waits for a render's reply (within
    BOUND seconds; the test then checks that it ran, through what `action` did)."""

    def watch() -> None:
        deadline = time.monotonic() + BOUND
        while time.monotonic() < deadline:
            if reading_a_render(thread):
                action()
                return
            time.sleep(0.001)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    return watcher


@pytest.fixture(scope="module")
def shared_fitter(tiny_model):
    """Returns (a verifying Fitter of the tiny model, its fit of PICTURE with NEURAL): the tests below each leave it
    usable (that is what they check), and start its render processes again where they broke them."""
    with matfit.Fitter(tiny_model) as warm:
        yield warm, warm.fit(PICTURE, settings=NEURAL)


def test_two_threads_fitting_on_one_fitter_queue_and_both_get_the_answer(shared_fitter):
    # They shared its render processes' pipes: one read the other's reply ("the render process ended unexpectedly")
    # and the other waited for ever in read_message.
    fitter, expected = shared_fitter
    calls = [lambda: fitter.fit(PICTURE, settings=NEURAL), lambda: fitter.render(expected.material)] * 2
    running = [started(call) for call in calls]
    deadline = time.monotonic() + len(calls) * BOUND
    for thread, _ in running:
        thread.join(max(deadline - time.monotonic(), 0))
    assert not any(thread.is_alive() for thread, _ in running), "a thread hangs"
    assert [outcome[0][0] for _, outcome in running] == [True] * len(calls), [outcome for _, outcome in running]
    fits, renders = [outcome[0][1] for _, outcome in running[0::2]], [outcome[0][1] for _, outcome in running[1::2]]
    assert all(fit.material == expected.material for fit in fits)
    np.testing.assert_array_equal(renders[0], renders[1])


def test_a_keyboard_interrupt_while_a_fit_reads_a_render_leaves_the_fitter_usable(shared_fitter, monkeypatch):
    # Ctrl-C in a notebook (`_thread.interrupt_main()`) left a reply half read: the next fit never returned. Here
    # the KeyboardInterrupt is raised in the fit's own thread as it starts reading a reply, the reply left unread
    # (deterministic: a watcher sampling the main thread's stack saw no read under CI's load, where the replies are
    # there before they are asked for, and a test need not run in the main thread).
    fitter, expected = shared_fitter
    old = fitter._pool
    real, asked, fitting = process.read_message, [], threading.current_thread()

    def interrupted(file, deadline=None):
        if threading.current_thread() is fitting and not asked:
            asked.append(True)
            raise KeyboardInterrupt
        return real(file, deadline)

    monkeypatch.setattr(process, "read_message", interrupted)
    with pytest.raises(KeyboardInterrupt):
        fitter.fit(PICTURE, settings=NEURAL)
    monkeypatch.undo()
    assert asked
    assert bounded(lambda: fitter.fit(PICTURE, settings=NEURAL)).material == expected.material
    assert old is not None and not old.healthy() and fitter._pool is not old  # ended: its pipes' state was unknown


def test_a_render_process_that_stops_answering_is_one_line_within_its_bound_and_replaced(shared_fitter, monkeypatch):
    # SIGSTOP of a render process mid-fit: the fit waited for ever
    fitter, expected = shared_fitter
    pool = fitter._renderer()
    children = [child._child for child in pool._children]
    monkeypatch.setattr(process, "START_SECONDS", 2.0)  # a reply may take 2 s here: those of the tiny model take ms
    monkeypatch.setattr(process, "SAMPLE_SECONDS", 0.0)
    for child in children:
        os.kill(child.pid, signal.SIGSTOP)
    try:
        started = time.monotonic()
        with pytest.raises(matfit.MatfitError) as raised:
            bounded(lambda: fitter.fit(PICTURE, settings=NEURAL), 60)
        seconds = time.monotonic() - started
    finally:
        for child in children:  # those still stopped end once they run on: their requests have ended
            with contextlib.suppress(ProcessLookupError):
                os.kill(child.pid, signal.SIGCONT)
    assert str(raised.value) == (
        f"the render process gave no reply in 2 s, the most a {fitter.model.resolution} px render of 64 samples may "
        "take (stopped, or stuck): it was killed; the next fit starts new render processes"
    )
    assert 2.0 <= seconds < 30
    assert fitter._pool is None and any(child.wait(10) == -signal.SIGKILL for child in children)
    monkeypatch.undo()
    assert bounded(lambda: fitter.fit(PICTURE, settings=NEURAL)).material == expected.material
    assert all(child.wait(30) is not None for child in children)  # none left running


def test_a_render_process_killed_mid_fit_is_named_so_and_the_next_fit_starts_new_ones(shared_fitter):
    # The error said "exit code None", and the dead processes were kept: the next fit failed too.
    fitter, expected = shared_fitter
    children = [child._child for child in fitter._renderer()._children]
    fits: list[threading.Thread] = []

    def kill() -> None:
        for child in children:
            os.kill(child.pid, signal.SIGKILL)

    def fit() -> matfit.Fit:
        fits.append(when_reading_a_render(threading.get_ident(), kill))
        return fitter.fit(PICTURE, settings=NEURAL)

    with pytest.raises(matfit.MatfitError) as raised:
        bounded(fit)
    assert str(raised.value) == (
        "the render process ended unexpectedly (killed by signal 9 (SIGKILL)): the next fit starts new render "
        "processes; if it ends again, run `matfit render` on a preset to see Mitsuba's own message"
    )
    assert fitter._pool is None
    assert bounded(lambda: fitter.fit(PICTURE, settings=NEURAL)).material == expected.material


def page_code() -> str:
    """Returns the page's Python blocks, in order, as one script."""
    return "\n".join(re.findall(r"```python\n(.*?)```", PAGE.read_text(), re.DOTALL))


@pytest.mark.slow
def test_the_pages_examples_run_as_written(tmp_path):
    edits = tmp_path / "edits"
    edits.mkdir()
    shutil.copy(PICTURE, edits / PICTURE.name)  # one picture: a folder of more is fitted alike
    before = set(os.listdir(tmp_path))
    run = subprocess.run([sys.executable, "-c", page_code()], cwd=tmp_path, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    written = set(os.listdir(tmp_path)) - before
    assert written == {"fits", "params.json", "rougher.exr", "material.xml", "material.py", "room"}, written
    assert sorted(os.listdir(edits)) == ["recoloured.png"]
    assert sorted(os.listdir(tmp_path / "fits")) == ["recoloured.params.json", "recoloured.report.png"]  # no journal
    assert "fits/recoloured.params.json: lbfgsb" in run.stdout
    landed = [line for line in run.stdout.splitlines() if " answer: neural " in line]  # answers=, as each landed
    assert [line.split()[0] for line in landed] == ["neural", "verified", "clean"], run.stdout
    assert landed[0].endswith(", not rendered yet") and ", Mitsuba " in landed[2]
    fitted = [json.loads((tmp_path / name).read_text()) for name in ("fits/recoloured.params.json", "params.json")]
    assert without_timings(fitted[0]) == without_timings(fitted[1])  # fit_all's and fit's params.json alike
