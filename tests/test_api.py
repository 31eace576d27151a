"""The public API (`import matfit`, docs/api.md): the command line's answers and errors, arrays, the page's examples."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import matfit
from matfit import images, params, shipped
from matfit.app.cli import app
from matfit.model import architectures, weight_files
from matfit.render import export, scene
from tests.helpers import random_model

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "api.md"
PICTURE = shipped.EXAMPLES / "recoloured.png"
TIMINGS = ("fit_seconds", "wall_time_s", "seconds")


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
    assert names == str(sorted(["Fit", "Fitter", "Material", "MatfitError", "Settings", "fit", "fit_sequence",
                                "load_model", "render"]))  # fmt: skip


def test_fit_and_render_are_functions_and_still_their_subpackages():
    import matfit.fit.search
    import matfit.render.engine

    assert callable(matfit.fit) and callable(matfit.render)
    assert matfit.fit is sys.modules["matfit.fit"] and matfit.render is sys.modules["matfit.render"]
    assert matfit.fit.search.neural_search and matfit.render.engine.Renderer
    assert "picture" in str(__import__("inspect").signature(matfit.fit))


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


def test_render_checks_its_arguments_before_rendering():
    with pytest.raises(matfit.MatfitError, match="size 4 is out of range: use 8 to 4096"):
        matfit.render(matfit.Material(), size=4)
    with pytest.raises(matfit.MatfitError, match=r"render takes a matfit.Material, got str:"):
        matfit.render("gold")  # type: ignore[arg-type]


def test_render_is_the_renderers_picture(renderer):
    gold = matfit.Material.preset("gold")
    image = matfit.render(gold, size=16, spp=4, seed=3, variant=renderer.variant)
    assert image.shape == (16, 16, 3) and image.dtype == np.float32
    # rendered on every core: the same picture up to the last bits the threads' order changes (docs/fitting.md)
    again = matfit.render(gold, size=16, spp=4, seed=3, variant=renderer.variant)
    np.testing.assert_allclose(image, again, rtol=0, atol=1e-5)
    assert not np.allclose(image, matfit.render(gold, size=16, spp=4, seed=4, variant=renderer.variant), atol=1e-3)


def test_bad_pictures_raise_matfit_errors_with_the_command_lines_messages(fitter, tmp_path):
    missing = tmp_path / "missing.png"
    with pytest.raises(matfit.MatfitError) as error:
        fitter.fit(missing)
    assert str(error.value) == cli_error("fit", missing, "-o", tmp_path / "p.json", "--no-verify")
    bad = {
        "has shape (4, 4, 5): give (H, W, 3) RGB": np.zeros((4, 4, 5), np.float32),
        "has shape (4,)": np.zeros(4, np.float32),
        "holds int64 values: give float sRGB in 0-1, uint8 0-255": np.zeros((4, 4, 3), np.int64),
        "contains NaN or infinite values": np.full((4, 4, 3), np.nan, np.float32),
        "values run from 0 to 255, outside sRGB's 0-1: divide 0-255 values by 255": np.linspace(0, 255, 48).reshape(
            4, 4, 3
        ),
        "cannot be read": [[1, 2], [3]],
    }
    for message, picture in bad.items():
        with pytest.raises(matfit.MatfitError, match=re.escape(message)):
            fitter.fit(picture)  # type: ignore[arg-type]
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


@pytest.mark.slow
def test_fit_of_a_file_gives_the_command_lines_params_json_bit_for_bit(tiny_model, tmp_path, monkeypatch):
    # The defaults of both: verification on a render Pool, two rounds of correction, the clean answer.
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["fit", str(PICTURE), "-o", "p.json", "--model", str(tiny_model)])
    assert result.exit_code == 0, result.output
    fit = matfit.fit(PICTURE, model=Path(tiny_model))
    written = json.loads((tmp_path / "p.json").read_text())
    assert written["verification"]["corrections"] == 2 and "answer" in written
    assert without_timings(json.loads(fit.to_json())) == without_timings(written)
    assert fit.material == matfit.Material.from_array(params.from_unit(params.to_unit(fit.material.array())))
    assert [path.name for path in tmp_path.iterdir()] == ["p.json"]


def page_code() -> str:
    """Returns the page's Python blocks, in order, as one script."""
    return "\n".join(re.findall(r"```python\n(.*?)```", PAGE.read_text(), re.DOTALL))


@pytest.mark.slow
def test_the_pages_examples_run_as_written(tmp_path):
    edits = tmp_path / "edits"
    edits.mkdir()
    shutil.copy(PICTURE, edits / PICTURE.name)  # one picture: the folder's loop is the same for more
    before = set(os.listdir(tmp_path))
    run = subprocess.run([sys.executable, "-c", page_code()], cwd=tmp_path, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    written = set(os.listdir(tmp_path)) - before
    assert written == {"params.json", "rougher.exr", "material.xml", "material.py"}, written
    assert sorted(os.listdir(edits)) == ["recoloured.params.json", "recoloured.png"]
