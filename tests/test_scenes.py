"""A scene of the user's own through the public API and the command line (`api/scenes`, `matfit fit/render --scene`)."""

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import matfit
from matfit import images, params
from matfit.app.cli import app
from matfit.fitting import scene_fit, scene_judge
from matfit.rendering import scene_library

pytestmark = pytest.mark.usefixtures("tiny_scene_fits")  # tests/conftest.py

runner = CliRunner()


def run(*arguments):
    return runner.invoke(app, [str(a) for a in arguments])


def assert_one_line_error(result, *fragments):
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """Returns the torus knot's scene file (studio lighting, a 4:3 camera)."""
    return Path(scene_library.write(str(tmp_path_factory.mktemp("scene")), "knot", "studio", width=32, height=24))


@pytest.fixture(scope="module")
def edited(scene, tmp_path_factory) -> Path:
    """Returns a picture to fit: the knot rendered in red plastic by `matfit render --scene`, its red turned orange."""
    folder = tmp_path_factory.mktemp("edit")
    material = folder / "red.json"
    material.write_text(matfit.Material.preset("red-plastic").to_json())
    picture = folder / "render.png"
    result = run("render", material, "--scene", scene, "--object", "object", "-o", picture, "--size", 64, "--spp", 32)
    assert result.exit_code == 0, result.output
    srgb = images.srgb_encode(images.load(str(picture)).pixels)
    srgb[..., 1] = np.where(srgb[..., 0] > 2 * srgb[..., 2] + 0.05, srgb[..., 1] + 0.15, srgb[..., 1])
    images.write(str(folder / "edited.png"), images.srgb_decode(np.clip(srgb, 0, 1)))
    return folder / "edited.png"


def test_matfit_render_renders_the_scene_at_the_cameras_aspect(scene, tmp_path):
    out = tmp_path / "gold.png"
    result = run(
        "render", "--preset", "gold", "--scene", scene, "--object", "object", "-o", out, "--size", 40, "--spp", 4
    )
    assert result.exit_code == 0, result.output
    assert "40x30" in result.output
    assert images.header(str(out))[:2] == (40, 30)


def test_matfit_fit_in_a_scene_writes_every_output_and_comes_closer(scene, edited, tmp_path):
    start = tmp_path / "start.json"
    start.write_text(matfit.Material.preset("red-plastic").to_json())
    out = {name: tmp_path / name for name in ("p.json", "report.png", "big.png", "m.xml", "b.py")}
    result = run(
        "fit", edited, "--scene", scene, "--object", "object", "--init", start, "-o", out["p.json"],
        "--report", out["report.png"], "--render", out["big.png"], "--size", 32, "--spp", 4,
        "--mitsuba-xml", out["m.xml"], "--blender", out["b.py"], "--refine", 4,
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert all(path.is_file() for path in out.values())
    # progress by step (stage, RMSE, time left), then the summary line
    steps = [line for line in result.output.splitlines() if line.startswith("fitting 'object' in ")]
    assert steps and all(", RMSE " in line for line in steps) and " s left" in steps[0], steps
    assert result.output.splitlines()[-1].startswith(f"{out['p.json']}: scene 'object', Mitsuba RMSE ")
    document = json.loads(out["p.json"].read_text())
    assert document["method"] == "scene" and set(document["params"]) == set(params.NAMES)
    assert document["scene"]["object"] == "object" and document["scene"]["camera"] == [32, 24]
    assert document["scene"]["path"] == str(scene.resolve())
    assert document["start"]["material"] == str(start)
    assert document["mitsuba_rmse"] <= document["start"]["rmse"]
    assert document["steps"] == {"short": 1, "descent": 4, "spp": 16}
    assert set(document["ranges"]) == set(params.NAMES)
    # an opaque fit's judge after its descent: the kurtosis of its renders' noise, whether it looked past outliers
    assert set(document["judge"]) == {"kurtosis", "robust", "weight"} and document["judge"]["kurtosis"] > 0
    assert document["judge"]["robust"] == (document["judge"]["kurtosis"] > scene_judge.HEAVY_TAILED)
    assert (document["judge"]["weight"] < 1.0) == document["judge"]["robust"]
    # its steps' residual: how much darker than its mean a step's image encodes where the descent began, and linear
    # in the image past `scene_fit.DARKENING` (a red plastic under a studio light: encoded)
    assert set(document["residual"]) == {"darkening", "linear"} and document["residual"]["darkening"] > 0
    assert document["residual"]["darkening"] < scene_fit.DARKENING and document["residual"]["linear"] is False
    assert document["again"] == {}  # an opaque fit's chosen start descends once (`scene_fit.again`: a transmissive's)
    assert images.header(str(out["big.png"]))[:2] == (32, 24)
    assert "matfit-material" in out["m.xml"].read_text()
    assert matfit.Material.read(out["p.json"]) == matfit.Material.from_dict(document["params"])


@pytest.mark.parametrize(
    ("arguments", "fragments"),
    [
        (("--scene", "{scene}"), ("--scene needs --object",)),
        (("--object", "object"), ("--object needs --scene",)),
        (("--scene", "{scene}", "--object", "floor2"), ("'floor2' is not a shape of", "key-light, object, floor")),
        (("--scene", "{scene}", "--object", "key-light"), ("is an emitter",)),
        (("--scene", "{missing}", "--object", "object"), ("is not a file",)),
    ],
)
def test_a_scene_fit_that_cannot_be_done_is_one_line_and_writes_nothing(scene, edited, tmp_path, arguments, fragments):
    names = {"scene": scene, "missing": tmp_path / "none.xml"}
    out = tmp_path / "p.json"
    result = run("fit", edited, *(str(a).format(**names) for a in arguments), "-o", out)
    assert_one_line_error(result, *fragments)
    assert not out.exists()


def test_a_picture_of_another_aspect_or_a_missing_mesh_is_refused_before_the_fit(scene, edited, tmp_path):
    square = tmp_path / "square.png"
    images.write(str(square), np.full((32, 32, 3), 0.5, np.float32))
    out = tmp_path / "p.json"
    assert_one_line_error(run("fit", square, "--scene", scene, "--object", "object", "-o", out), "aspect 1.000")
    moved = tmp_path / "moved"
    moved.mkdir()
    (moved / "scene.xml").write_text(scene.read_text())
    assert_one_line_error(
        run("fit", edited, "--scene", moved / "scene.xml", "--object", "object", "-o", out), "'knot.ply', which is not"
    )
    assert_one_line_error(
        run("fit", edited, "--scene", scene, "--object", "object", "-o", out, "--mitsuba-xml", scene),
        "would overwrite",
    )
    assert not out.exists() and not (moved / "p.json").exists()


def test_the_api_renders_and_fits_in_a_scene(scene, edited):
    chosen = matfit.Scene(scene, "object")
    gold = matfit.render(matfit.Material.preset("gold"), size=40, spp=4, scene=chosen)
    assert gold.shape == (30, 40, 3) and gold.dtype == np.float32
    pixels = images.srgb_encode(images.load(str(edited)).pixels)
    heard = []
    fitted = matfit.fit(
        pixels, scene=chosen, init=matfit.Material.preset("red-plastic"), refine=4, progress=lambda *a: heard.append(a)
    )
    assert isinstance(fitted.material, matfit.Material) and np.isnan(fitted.neural_rmse)
    assert fitted.mitsuba_rmse <= fitted.start_rmse and fitted.document["target"] == "array"
    assert fitted.rendered.shape == fitted.target.shape == (24, 32, 3)  # FIT_SIZE, tiny
    assert heard[-1][0] == "judge"
    with pytest.raises(matfit.MatfitError, match="is no path"):
        matfit.render(matfit.Material(), scene=matfit.Scene(5, "object"))
    with pytest.raises(matfit.MatfitError, match=r"is no matfit\.Scene"):
        matfit.fit(pixels, scene=os.fspath(scene))


def test_no_output_replaces_a_file_the_scene_names(tmp_path):
    sky = Path(scene_library.write(str(tmp_path), "box", "sky", width=32, height=24))
    image = tmp_path / "sky.exr"
    before = image.read_bytes()
    rendered = run("render", "--preset", "gold", "--scene", sky, "--object", "object", "-o", image, "--size", 16)
    assert_one_line_error(rendered, "is the scene's file", "sky.exr")
    picture = tmp_path / "picture.png"
    images.write(str(picture), np.full((24, 32, 3), 0.5, np.float32))
    fitted = run("fit", picture, "--scene", sky, "--object", "object", "-o", tmp_path / "p.json", "--report", image)
    assert_one_line_error(fitted, "--report", "is the scene's file")
    assert image.read_bytes() == before and not (tmp_path / "p.json").exists()


def test_a_shape_whose_material_matfit_cannot_read_starts_from_the_test_scenes_guess(scene, edited, tmp_path):
    text, count = re.subn(r'<bsdf type="principled">.*?</bsdf>', '<bsdf type="roughplastic"/>', scene.read_text())
    assert count == 1  # the knot's own material; the floor's is diffuse
    other = tmp_path / "scene.xml"
    other.write_text(text)
    for name in os.listdir(scene.parent):
        if name.endswith(".ply"):
            (tmp_path / name).symlink_to(scene.parent / name)
    fitted = matfit.fit(str(edited), scene=matfit.Scene(other, "object"), refine=1)
    start = fitted.document["start"]
    assert start["material"].startswith("the test scene's best-of-n of the shape's pixels (")
    colour = [start["params"][f"base_color_{c}"] for c in "rgb"]
    assert colour[0] > 2 * colour[2]  # the edit is orange-red: so is the guess
    assert fitted.document["scene"]["own_material"] is not None  # why the shape's own was not read


def test_several_pictures_fit_in_a_scene_into_a_folder_and_a_failed_one_alone_fits_again(scene, edited, tmp_path):
    pictures = tmp_path / "edits"
    pictures.mkdir()
    shutil.copy(edited, pictures / "orange.png")
    shutil.copy(edited, pictures / "other.png")
    images.write(str(pictures / "square.png"), np.full((32, 32, 3), 0.5, np.float32))  # not this camera's aspect
    start = tmp_path / "start.json"
    start.write_text(matfit.Material.preset("red-plastic").to_json())
    names = [pictures / name for name in ("orange.png", "other.png", "square.png")]
    out = tmp_path / "fits"
    command = ("fit", *names, "--scene", scene, "--object", "object", "--init", start, "--refine", 2, "-o", out)
    result = run(*command, "--report", "report.png")
    assert result.exit_code == 2, result.output
    assert "error: " in result.output and "aspect 1.000" in result.output
    assert "fitted 2 of 3 pictures into" in result.output
    written = sorted(os.listdir(out))
    assert written == [
        ".matfit-fit-journal.json",
        *(f"{s}.{k}" for s in ("orange", "other") for k in ("params.json", "report.png")),
    ]
    documents = {stem: json.loads((out / f"{stem}.params.json").read_text()) for stem in ("orange", "other")}
    for stem, document in documents.items():
        assert document["method"] == "scene" and document["target"] == str(pictures / f"{stem}.png")
        assert document["scene"]["object"] == "object" and document["start"]["material"] == str(start)
        assert document["mitsuba_rmse"] <= document["start"]["rmse"]
    # the square picture made right: the same command fits it alone, the two fitted are kept as they are
    before = {name: (out / name).read_bytes() for name in written if not name.startswith(".")}
    shutil.copy(edited, pictures / "square.png")
    again = run(*command, "--report", "report.png")
    assert again.exit_code == 0, again.output
    assert again.output.count("kept, fitted by an earlier run") == 2 and "fitted 3 of 3" in again.output
    assert {name: (out / name).read_bytes() for name in before} == before
    assert json.loads((out / "square.params.json").read_text())["method"] == "scene"
    assert not (out / ".matfit-fit-journal.json").exists()  # all fitted: the journal is gone


def test_a_sequence_of_frames_fits_in_a_scene_each_from_the_last_and_goes_on_where_it_stopped(scene, edited, tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("frame_1.png", "frame_2.png"):
        shutil.copy(edited, frames / name)
    start = tmp_path / "start.json"
    start.write_text(matfit.Material.preset("red-plastic").to_json())
    out = tmp_path / "out"
    shutil.copytree(scene.parent, tmp_path / "scene")
    scene = tmp_path / "scene" / scene.name  # a copy, changed below
    command = ("sequence", frames, "--scene", scene, "--object", "object", "--init", start, "--refine", 2, "-o", out)
    result = run(*command, "--render", "--size", 32, "--spp", 4)
    assert result.exit_code == 0, result.output
    assert sorted(os.listdir(out)) == sorted(
        ["frame_1.json", "frame_2.json", "frame_1-render.png", "frame_2-render.png", "summary.md", "preview.png"]
    )
    first, second = (json.loads((out / f"frame_{k}.json").read_text()) for k in (1, 2))
    for index, document in enumerate((first, second)):
        assert document["method"] == "scene" and document["scene"]["object"] == "object"
        assert document["mitsuba_rmse"] <= document["start"]["rmse"]
        assert document["sequence"]["index"] == index and document["sequence"]["settings"]["steps"] == 2
        assert document["sequence"]["frame"] == str(frames / f"frame_{index + 1}.png")
    assert first["start"]["material"] == str(start) and first["sequence"]["start"] == "--init"
    # the second frame starts from the first's answer
    assert second["start"]["material"] == "previous frame" and second["sequence"]["start"] == "previous frame"
    assert second["sequence"]["previous"] == first["sequence"]["unit"]
    assert second["start"]["params"] == pytest.approx(first["params"], abs=1e-3)
    assert images.header(str(out / "frame_2-render.png"))[:2] == (32, 24)
    summary = (out / "summary.md").read_text()
    assert "| frame | start | start Mitsuba RMSE | Mitsuba RMSE | steps | time (s) |" in summary
    assert "| frame_2.png | previous frame |" in summary and summary in result.output
    width, height = images.header(str(out / "preview.png"))[:2]
    assert (width, height) == (2 * 128, 2 * (96 + 12))  # two frames: each picture above its answer's render
    # stopped after the first frame: the same command keeps it and fits the second from its answer
    kept = (out / "frame_1.json").read_bytes()
    (out / "frame_2.json").unlink()
    again = run(*command, "--render", "--size", 32, "--spp", 4)
    assert again.exit_code == 0, again.output
    assert (out / "frame_1.json").read_bytes() == kept
    assert json.loads((out / "frame_2.json").read_text())["sequence"]["previous"] == first["sequence"]["unit"]
    # the scene file changed: every frame is fitted again, each saying why
    scene.write_text(scene.read_text() + "<!-- the light moved -->\n")
    changed = run(*command)
    assert changed.exit_code == 0, changed.output
    said = [line for line in changed.output.splitlines() if line.endswith(": fitted again")]
    assert len(said) == 2 and said[0].startswith("frame_1.png: the scene file, or a file it names,")
    assert (out / "frame_1.json").read_bytes() != kept
    # the test scene's sequence takes no steps of a scene fit
    assert_one_line_error(run("sequence", frames, "--refine", 2, "-o", tmp_path / "neural"), "--refine 2 is for the")
    assert not (tmp_path / "neural").exists()


def test_a_scene_sequence_refuses_a_frame_of_another_aspect_before_any_fit(scene, edited, tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    shutil.copy(edited, frames / "a.png")
    images.write(str(frames / "b.png"), np.full((32, 32, 3), 0.5, np.float32))
    out = tmp_path / "out"
    result = run("sequence", frames, "--scene", scene, "--object", "object", "-o", out)
    assert_one_line_error(result, "b.png is 32x32", "give a picture of the camera's aspect")
    assert not out.exists()


def test_the_api_fits_a_list_of_frames_in_a_scene_each_from_the_last(scene, edited):
    chosen = matfit.Scene(scene, "object")
    start = matfit.Material.preset("red-plastic")
    fits = matfit.fit_sequence([edited, edited], scene=chosen, init=start, refine=2)
    assert [fit.start for fit in fits] == ["--init", "previous frame"]
    assert fits[0].document["start"]["material"] == "Material"
    assert fits[1].document["start"]["params"] == pytest.approx(fits[0].document["params"], abs=1e-3)
    assert all(fit.mitsuba_rmse is not None and fit.mitsuba_rmse <= fit.document["start"]["rmse"] for fit in fits)
    with pytest.raises(matfit.MatfitError, match="settings= are the test scene's search"):
        matfit.fit_sequence([edited], scene=chosen, settings=matfit.Settings())


def test_a_scene_sequence_stopped_keeps_the_frames_written_and_one_stopped_at_once_leaves_no_folder(
    scene, edited, tmp_path, monkeypatch
):
    from matfit.api import scenes

    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("frame_1.png", "frame_2.png"):
        shutil.copy(edited, frames / name)
    real, calls = scenes.fit_in_scene, []

    def stopped_after(kept: int):
        def fit_in_scene(*arguments, **options):
            calls.append(arguments[0])
            if len(calls) > kept:
                raise KeyboardInterrupt  # Ctrl-C in the middle of a frame's fit
            return real(*arguments, **options)

        return fit_in_scene

    chosen = matfit.Scene(scene, "object")
    monkeypatch.setattr(scenes, "fit_in_scene", stopped_after(1))
    with pytest.raises(KeyboardInterrupt):
        matfit.fit_sequence(frames, scene=chosen, refine=2, out=tmp_path / "out")
    assert sorted(os.listdir(tmp_path / "out")) == ["frame_1.json"]  # not the frame in hand, summary.md, preview.png
    calls.clear()
    monkeypatch.setattr(scenes, "fit_in_scene", stopped_after(0))
    with pytest.raises(KeyboardInterrupt):
        matfit.fit_sequence(frames, scene=chosen, refine=2, out=tmp_path / "new")
    assert not (tmp_path / "new").exists()
    monkeypatch.setattr(scenes, "fit_in_scene", real)
    fits = matfit.fit_sequence(frames, scene=chosen, refine=2, out=tmp_path / "out")  # goes on: frame 1 kept
    assert "kept, fitted by an earlier run" in fits[0].summary and "kept" not in fits[1].summary
    assert sorted(os.listdir(tmp_path / "out")) == ["frame_1.json", "frame_2.json", "preview.png", "summary.md"]


def test_a_scene_sequence_fits_every_frame_through_one_mask_and_again_when_it_changes(scene, edited, tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("frame_1.png", "frame_2.png"):
        shutil.copy(edited, frames / name)
    width, height = images.header(str(edited))[:2]
    mask = tmp_path / "mask.png"
    images.write(str(mask), np.ones((height, width, 3), np.float32))
    small = tmp_path / "small.png"
    images.write(str(small), np.ones((height // 2, width // 2, 3), np.float32))
    out = tmp_path / "out"
    command = ("sequence", frames, "--scene", scene, "--object", "object", "--refine", 2, "-o", out)
    refused = run(*command, "--mask", small)
    assert_one_line_error(refused, f"the mask is {width // 2}x{height // 2}", "give a mask of the frames' size")
    assert not out.exists()
    missing = run(*command, "--mask", tmp_path / "none.png")
    assert_one_line_error(missing, f"mask {tmp_path / 'none.png'} is not a file", "give the mask's path")
    assert not out.exists()
    assert_one_line_error(run("sequence", frames, "--mask", mask, "-o", out), "--mask")  # the test scene's: none
    result = run(*command, "--mask", mask)
    assert result.exit_code == 0, result.output
    documents = [json.loads((out / f"frame_{k}.json").read_text()) for k in (1, 2)]
    assert all(d["mask"] == str(mask) and d["sequence"]["mask_sha256"] for d in documents)
    images.write(str(mask), np.concatenate([np.ones((height, width // 2, 3)), np.zeros((height, width // 2, 3))], 1))
    again = run(*command, "--mask", mask)
    assert again.exit_code == 0, again.output
    assert "frame_1.png: the mask is not the one its result on disk was fitted through: fitted again" in again.output
    assert json.loads((out / "frame_1.json").read_text())["region_fraction"] < documents[0]["region_fraction"]
