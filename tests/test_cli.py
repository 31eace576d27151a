import importlib.metadata
import importlib.util
import itertools
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

from matfit import images, params, shipped
from matfit.app.cli import app
from matfit.fitting import batch, methods, verify
from matfit.fitting import search as fit
from matfit.model import architectures, weight_files
from matfit.rendering import engine, presets

runner = CliRunner()


def run(*arguments):
    return runner.invoke(app, [str(a) for a in arguments])


ANSWER_LINE = re.compile(r"(neural|verified|clean|refined) answer: (neural|Mitsuba) RMSE (\d+\.\d\d) \(\d+\.\d s\)")


def answer_lines(output: str) -> list[tuple[str, str]]:
    """Returns (stage, its figure as printed: "Mitsuba RMSE 1.92") of each stage's answer `matfit fit` printed as it
    landed, in order; every line that names a stage's answer must have that form (its time aside)."""
    lines = [line for line in output.splitlines() if re.match(r"\w+ answer: ", line)]
    matched = [ANSWER_LINE.fullmatch(line) for line in lines]
    assert all(matched), output
    return [(found[1], f"{found[2]} RMSE {found[3]}") for found in matched if found]


def assert_one_line_error(result, *fragments):
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    for fragment in fragments:
        assert fragment in lines[0]
    assert "Traceback" not in result.output


def test_render_a_preset_to_png_and_exr(tmp_path):
    result = run("render", "--preset", "gold", "-o", tmp_path / "gold.png", "--size", 16, "--spp", 4)
    assert result.exit_code == 0, result.output
    png = images.read(str(tmp_path / "gold.png"))
    assert png.shape == (16, 16, 3)
    result = run("render", "--preset", "gold", "-o", tmp_path / "gold.exr", "--size", 16, "--spp", 4)
    assert result.exit_code == 0, result.output
    exr = images.read(str(tmp_path / "gold.exr"))
    assert images.rmse(images.srgb_encode(exr), images.srgb_encode(png)) < 0.5
    assert exr.mean(axis=(0, 1))[0] > exr.mean(axis=(0, 1))[2]  # gold is warm


def test_render_a_params_file_and_a_random_material(tmp_path):
    (tmp_path / "p.json").write_text(json.dumps({"base_color_r": 0.9, "base_color_g": 0.1, "base_color_b": 0.1}))
    result = run("render", tmp_path / "p.json", "-o", tmp_path / "red.png", "--size", 16, "--spp", 4)
    assert result.exit_code == 0, result.output
    red = images.read(str(tmp_path / "red.png"))
    assert red[8, 8, 0] > red[8, 8, 2]
    result = run("render", "--random", "--seed", 5, "-o", tmp_path / "random.png", "--size", 16, "--spp", 4)
    assert result.exit_code == 0, result.output
    printed = json.loads(result.stdout)
    assert set(printed["params"]) >= {"roughness", "phase_g"}


def test_render_dataset_through_the_cli(tmp_path):
    result = run("render-dataset", tmp_path / "d", "--count", 6, "--resolution", 16, "--spp", 2)
    assert result.exit_code == 0, result.output
    assert "6/6" in result.output
    assert np.load(tmp_path / "d" / "done.npy").sum() == 6


def test_version_is_the_installed_distributions():
    result = run("--version")
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == importlib.metadata.version("matfit")


def test_params_lists_nineteen_parameters():
    result = run("params")
    assert result.exit_code == 0
    assert len(result.stdout.strip().splitlines()) == 19


@pytest.mark.parametrize(
    ("content", "fragments"),
    [
        ("{oops", ("bad.json is not valid JSON",)),
        ('{"rougness": 0.2}', ("did you mean 'roughness'",)),
        ('{"roughness": 2}', ("out of range", "[0.0, 1.0]")),
        ('{"metallic": NaN}', ("'metallic' is nan",)),
        ("[" * 100000, ("bad.json is not valid JSON (nested too deeply to read)", "give a params.json")),
    ],
)
def test_bad_params_files(tmp_path, content, fragments):
    (tmp_path / "bad.json").write_text(content)
    result = run("render", tmp_path / "bad.json", "-o", tmp_path / "out.png", "--size", 16, "--spp", 4)
    assert_one_line_error(result, *fragments)
    assert not (tmp_path / "out.png").exists()


@pytest.mark.parametrize(
    ("arguments", "fragments"),
    [
        (("render", "-o", "{tmp}/x.png"), ("give exactly one material",)),
        (("render", "--preset", "gold", "--random", "-o", "{tmp}/x.png"), ("give exactly one material",)),
        (("render", "--preset", "unobtanium", "-o", "{tmp}/x.png", "--size", "16"), ("unknown preset", "gold")),
        (("render", "--preset", "gold", "-o", "{tmp}/missing/x.png"), ("does not exist",)),
        (("render", "--preset", "gold", "-o", "/proc/x.png"), ("read-only",)),
        (("render", "--preset", "gold", "-o", "{tmp}/x.bmp"), ("unknown image type .bmp",)),
        (
            ("render", "--preset", "gold", "-o", "{tmp}/x.png", "--size", "100000"),
            ("--size 100000 is out of range: use 8 to 4096",),
        ),
        (("render", "--preset", "gold", "-o", "{tmp}/x.png", "--spp", "0"), ("--spp 0 is out of range",)),
        (("render", "{tmp}/none.json", "-o", "{tmp}/x.png"), ("cannot read", "none.json")),
        (("render", "--preset", "gold", "-o", "{tmp}/x.png", "--variant", "cuda"), ("--variant cuda", "llvm_ad_rgb")),
        (("render-dataset", "{tmp}/d", "--count", "0"), ("--count 0 is out of range",)),
        (("render-dataset", "{tmp}/d", "--count", "-5"), ("--count -5 is out of range",)),
        (("render-dataset", "{tmp}/d", "--count", "5", "--resolution", "5000"), ("resolution 5000 is out of range",)),
        (("render-dataset", "{tmp}/d", "--count", "5", "--spp", "0"), ("spp 0 is out of range",)),
        (("render-dataset", "{tmp}/missing/d", "--count", "5"), ("does not exist",)),
        (("render-dataset", "/proc/d", "--count", "5"), ("read-only",)),
        (("render-dataset", "{tmp}/d", "--count", "5", "--sampler", "milk"), ("--sampler milk", "dense-media")),
    ],
)
def test_bad_arguments_give_one_line_errors(tmp_path, arguments, fragments):
    result = run(*(a.replace("{tmp}", str(tmp_path)) for a in arguments))
    assert_one_line_error(result, *fragments)
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "d").exists()


@pytest.mark.parametrize(
    "arguments",
    [
        ("render", "--preset", "gold", "-o", "{tmp}/x.png", "--size", "16", "--spp", "1"),
        ("presets", "-o", "{tmp}/x.png", "--size", "32", "--spp", "1"),
        ("bench-render", "--count", "5"),
        ("render-dataset", "{tmp}/d", "--count", "4", "--resolution", "16", "--spp", "1"),
        ("blender-check", "--out", "{tmp}/b", "--preset", "gold", "--size", "16", "--spp", "1"),
        ("fit", str(shipped.EXAMPLES / "recoloured.png"), "-o", "{tmp}/p.json"),
        ("serve", "--port", "8791"),
    ],
    ids=lambda arguments: arguments[0],
)
def test_cuda_asked_for_without_a_gpu_is_refused_in_one_line_before_any_work(tmp_path, monkeypatch, arguments):
    monkeypatch.setattr(engine, "cuda_devices", lambda: 0)  # as on a machine without an NVIDIA GPU
    result = run(*(a.replace("{tmp}", str(tmp_path)) for a in arguments), "--variant", "cuda_ad_rgb")
    assert_one_line_error(
        result, "variant cuda_ad_rgb is not usable here (no NVIDIA GPU answers libcuda.so.1)", "--variant scalar_rgb"
    )
    assert list(tmp_path.iterdir()) == []


def test_dataset_with_other_settings_is_refused(tmp_path):
    assert run("render-dataset", tmp_path / "d", "--count", 4, "--resolution", 16, "--spp", 2).exit_code == 0
    result = run("render-dataset", tmp_path / "d", "--count", 4, "--resolution", 32, "--spp", 2)
    assert_one_line_error(result, "rendered with resolution 16, not 32")
    result = run(
        "render-dataset", tmp_path / "d", "--count", 6, "--resolution", 16, "--spp", 2, "--sampler", "dense-media"
    )
    assert_one_line_error(result, "drawn with sampler uniform, not dense-media: pass --sampler uniform")


@pytest.mark.slow
def test_a_dense_media_supplement_trains_beside_the_training_set(tmp_path, tiny_dataset):
    supplement = tmp_path / "media"
    arguments = ("--count", 8, "--resolution", 32, "--spp", 1, "--seed", 2, "--sampler", "dense-media")
    assert run("render-dataset", supplement, *arguments).exit_code == 0
    assert json.loads((supplement / "meta.json").read_text())["sampler"] == "dense-media"
    spec_trans = np.load(supplement / "params.npy")[:, params.INDEX["spec_trans"]]
    assert spec_trans.min() >= 0.95
    result = run(
        "train", "--arch", "decoder", "--dataset", tiny_dataset, "--dataset", supplement, "--epochs", 1,
        "--batch-size", 8, "--out", tmp_path / "m",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "m" / "decoder.json").read_text())
    assert metrics["training_samples"] == 46 + 7 and metrics["validation_samples"] == 2 + 1
    assert [each["count"] for each in metrics["dataset"]] == [48, 8]


@pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="Ray is an optional extra: pip install -e '.[cluster]' to run the Ray tests",
)
def test_ray_run_with_other_settings_is_refused(tmp_path):
    assert run("render-dataset", tmp_path / "d", "--count", 4, "--resolution", 16, "--spp", 2).exit_code == 0
    before = {name: (tmp_path / "d" / name).read_bytes() for name in ("meta.json", "images.npy", "done.npy")}
    for option, value, message in (
        ("--resolution", 32, "resolution 16, not 32"),
        ("--spp", 4, "spp 2, not 4"),
        ("--seed", 4, "seed 0, not 4"),
    ):
        settings = {"--resolution": 16, "--spp": 2, "--seed": 0, option: value}
        arguments = [str(item) for pair in settings.items() for item in pair]
        assert_one_line_error(
            run("render-dataset", tmp_path / "d", "--count", 8, *arguments, "--ray", "local"), message
        )
    assert {name: (tmp_path / "d" / name).read_bytes() for name in before} == before


def test_ray_without_the_extra_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` meets when the extra is not installed
    result = run("render-dataset", tmp_path / "d", "--count", 4, "--resolution", 16, "--spp", 2, "--ray", "local")
    assert_one_line_error(result, "--ray needs Ray", ".[cluster]")
    assert not (tmp_path / "d").exists()


@pytest.fixture(scope="module")
def trained(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("model")
    arguments = ("--arch", "decoder,8", "--dataset", tiny_dataset, "--epochs", 1, "--batch-size", 8)
    result = run("train", *arguments, "--no-coarse-absorption", "--out", out)  # plain: a test grows the layer on it
    assert result.exit_code == 0, result.output
    return out


def test_train_writes_weights_metrics_and_checkpoints(trained):
    for name in ("decoder", "encoder-8"):
        assert (trained / f"{name}.msgpack").is_file()
        assert (trained / "checkpoints" / f"{name}.ckpt").is_file()
        metrics = json.loads((trained / f"{name}.json").read_text())
        assert metrics["epochs"] == 1 and metrics["dataset"]["count"] == 48 and len(metrics["history"]) == 1
        assert metrics["wall_time_s"] == pytest.approx(metrics["history"][0]["seconds"], abs=0.05)


def test_evaluate_writes_the_model_card(trained, tiny_dataset):
    result = run("evaluate", "--model", trained, "--references", tiny_dataset, "--card", "--preset-spp", "4")
    assert result.exit_code == 0, result.output
    card = (trained / "MODEL.md").read_text()
    assert "| encoder-8 |" in card and "best-of-1" in card
    assert "| jade | scattering |" in card and "| gold | opaque |" in card and "| glass | transmissive |" in card
    evaluation = json.loads((trained / "evaluation.json").read_text())
    assert evaluation["references"]["count"] == 48
    thirds = evaluation["references"]
    assert (
        thirds["transmissive_count"] + thirds["opaque_count"] == 48
        and thirds["scattering_count"] <= thirds["transmissive_count"]
    )
    assert set(evaluation["presets"]["rmse"]) == set(presets.PRESETS) and evaluation["presets"]["spp"] == 4
    assert (Path(tiny_dataset) / "presets.npz").is_file()
    assert evaluation["best_of_n"]["image_rmse"] == pytest.approx(evaluation["encoders"]["8"]["image_rmse"])


@pytest.mark.parametrize(
    "arch, fragment",
    [
        ("0", "--arch 0 does not exist"),
        ("10", "--arch 10 does not exist"),
        ("two", "--arch 'two' is not an architecture"),
    ],
)
def test_unknown_architectures(tiny_dataset, tmp_path, arch, fragment):
    assert_one_line_error(run("train", "--arch", arch, "--dataset", tiny_dataset, "--out", tmp_path), fragment)


def test_zero_epochs_is_refused_not_replaced_by_the_default(tiny_dataset, tmp_path):
    result = run("train", "--arch", "decoder", "--dataset", tiny_dataset, "--epochs", 0, "--out", tmp_path / "m")
    assert_one_line_error(result, "--epochs 0 is out of range")
    assert not (tmp_path / "m").exists()


def test_missing_and_corrupt_datasets(tmp_path, tiny_dataset):
    assert_one_line_error(
        run("train", "--arch", "1", "--dataset", tmp_path / "none", "--out", tmp_path), "no meta.json", "render-dataset"
    )
    broken = tmp_path / "broken"
    shutil.copytree(tiny_dataset, broken)
    (broken / "images.npy").write_bytes(b"not numpy")
    assert_one_line_error(
        run("train", "--arch", "1", "--dataset", broken, "--out", tmp_path), "images.npy is missing or corrupt"
    )


def test_corrupt_checkpoint_and_weights(tmp_path, tiny_dataset, trained):
    out = tmp_path / "model"
    shutil.copytree(trained, out)
    (out / "checkpoints" / "encoder-8.ckpt").write_bytes(b"\x93garbage")
    result = run("train", "--arch", "8", "--dataset", tiny_dataset, "--epochs", 1, "--batch-size", 8, "--out", out)
    assert_one_line_error(result, "encoder-8.ckpt", "delete it and train again")
    (out / "decoder.msgpack").write_bytes(b"")
    assert_one_line_error(run("evaluate", "--model", out, "--references", tiny_dataset), "decoder.msgpack")
    assert_one_line_error(
        run("evaluate", "--model", tmp_path / "nothing", "--references", tiny_dataset), "does not exist"
    )


def test_finished_networks_are_not_trained_again(trained, tiny_dataset):
    before = weight_files.load(str(trained / "encoder-8.msgpack")).info["metrics"]["wall_time_s"]
    result = run("train", "--arch", "8", "--dataset", tiny_dataset, "--epochs", 1, "--batch-size", 8, "--out", trained)
    assert result.exit_code == 0, result.output
    assert weight_files.load(str(trained / "encoder-8.msgpack")).info["metrics"]["wall_time_s"] == before


@pytest.mark.slow
def test_train_coarse_absorption_grows_the_layer_on_a_plain_decoder(trained, tiny_dataset, tmp_path):
    out = tmp_path / "coarse"
    arguments = ("--dataset", tiny_dataset, "--epochs", 1, "--batch-size", 8)  # the layer is the default
    result = run("train", "--arch", "decoder", *arguments, "--start-from", trained, "--out", out)
    assert result.exit_code == 0, result.output
    coarse, plain = weight_files.load(str(out / "decoder.msgpack")), weight_files.load(str(trained / "decoder.msgpack"))
    assert coarse.module.coarse_absorption and coarse.module.path_start == architectures.COARSE_PATH_START
    assert not plain.module.coarse_absorption
    assert set(coarse.variables["params"]) - set(plain.variables["params"]) == {"path"}
    assert float(coarse.variables["params"]["path"]["bias"][0]) == pytest.approx(1.0, abs=0.05)  # one epoch at 1e-3
    # The plain run's directory holds a decoder of the other architecture: resuming it with the layer is refused.
    assert_one_line_error(run("train", "--arch", "decoder", *arguments, "--out", trained), "architecture")


def black_png(path, side):
    """Writes a valid black side x side PNG cheaply (black rows compress to almost nothing)."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    compressor = zlib.compressobj(9)
    row = b"\x00" * (1 + 3 * side)
    pixels = b"".join([compressor.compress(row) for _ in range(side)] + [compressor.flush()])
    header = struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", pixels) + chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def target(tiny_dataset, tmp_path_factory):
    from matfit.model import dataset

    data = dataset.open_dataset(tiny_dataset)
    path = tmp_path_factory.mktemp("target") / "edited.png"
    images.write(str(path), np.asarray(data.images[-1], np.float32))
    return path


def test_fit_writes_params_and_report(trained, target, tmp_path):
    out, report = tmp_path / "params.json", tmp_path / "report.png"
    xml, blender = tmp_path / "mat.xml", tmp_path / "mat.py"
    result = run(
        "fit",
        target,
        "-o",
        out,
        "--model",
        trained,
        "--iterations",
        10,
        "--report",
        report,
        "--mitsuba-xml",
        xml,
        "--blender",
        blender,
    )
    assert result.exit_code == 0, result.output
    assert 'id="matfit-material"' in xml.read_text() and "ShaderNodeBsdfPrincipled" in blender.read_text()
    document = json.loads(out.read_text())
    assert document["method"] == "lbfgsb"  # the default method; its best-of-n: 2 encoders and the media grid
    assert document["start"] in {"encoder-3", "encoder-8"} | {f"media-{k}" for k in range(1, 49)}
    assert 0 < document["evaluations"] <= 10 * 4 * fit.GRADIENT_COST  # at most 10 steps of 4 starts
    assert document["neural_rmse"] <= document["start_rmse"] and document["mitsuba_rmse"] > 0
    assert len(document["target_sha256"]) == 64
    assert document["mitsuba_variant"] == engine.choose_variant(None)[0]  # the variant that verified it
    values = params.parse_params_json(out.read_text())
    assert values.shape == (19,)
    assert images.read(str(report)).shape[1] == 6 * 192  # the five pictures and the ranges
    # what the picture decides: every parameter's range in physical units holds the parameter's box
    decided = document["ranges"]["parameters"]
    assert list(decided) == list(params.NAMES) and document["ranges"]["threshold_rmse"] > 0
    for p in params.PARAMETERS:
        assert p.low <= decided[p.name]["low"] <= decided[p.name]["high"] <= p.high
        assert decided[p.name]["unit"] == p.unit and decided[p.name]["verdict"] in ("decided", "partly", "free")
    assert document["answer"]["kind"] == "clean" and document["answer"]["kept"] in ("clean", "best")
    assert set(document["answer"]["best"]) == set(params.NAMES)
    if document["answer"]["features_off"] and document["answer"]["kept"] == "clean":  # the answer's own figure
        assert document["mitsuba_rmse"] == document["answer"]["mitsuba_rmse"]["clean"]
    tried = [candidate["features_off"] for candidate in document["answer"]["candidates"].values()]
    assert all(set(fewer) < set(more) for fewer, more in itertools.pairwise(tried))  # nested
    assert document["answer"]["kept"] == "best" or document["answer"]["features_off"] in tried
    # each stage's answer as it landed, before the summary line: the last one's figure is params.json's
    verification, landed = document["verification"], answer_lines(result.output)
    assert [stage for stage, _ in landed] == ["neural", "verified", "clean"]
    searched = landed[0][1]  # the search's own answer, no Mitsuba render yet: at most its start's figure
    assert searched.startswith("neural RMSE ") and float(searched.split()[-1]) <= document["start_rmse"] + 0.005
    assert landed[1:] == [
        ("verified", f"Mitsuba RMSE {verification['mitsuba_rmse'][verification['kept']]:.2f}"),
        ("clean", f"Mitsuba RMSE {document['mitsuba_rmse']:.2f}"),
    ]
    assert result.output.index("clean answer: ") < result.output.index(f"{out}: lbfgsb")
    # params.json feeds `matfit render` directly
    assert run("render", out, "-o", tmp_path / "again.png", "--size", 16, "--spp", 4).exit_code == 0


def test_fit_bad_inputs(trained, target, tmp_path):
    out = tmp_path / "params.json"

    def fit(*arguments):
        return run("fit", *arguments, "-o", out, "--model", trained)

    (tmp_path / "text.png").write_text("not an image")
    assert_one_line_error(fit(tmp_path / "text.png"), "text.png")
    (tmp_path / "empty.png").write_bytes(b"")
    assert_one_line_error(fit(tmp_path / "empty.png"), "empty.png is empty")
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(target.read_bytes()[:200])
    assert_one_line_error(fit(truncated), "truncated.png")
    images.write(str(tmp_path / "whole.jpg"), images.read(str(target)))
    jpeg = (tmp_path / "whole.jpg").read_bytes()
    (tmp_path / "truncated.jpg").write_bytes(jpeg[: (jpeg.index(b"\xff\xda") + len(jpeg)) // 2])  # a whole header
    assert_one_line_error(fit(tmp_path / "truncated.jpg"), "truncated.jpg is damaged or truncated", "export it again")
    black_png(tmp_path / "huge.png", 7100)  # 50.4 Mpixel, over images.MAX_PIXELS
    assert_one_line_error(fit(tmp_path / "huge.png"), "huge.png is 7100x7100", "scale it down")
    nan = np.full((32, 32, 3), 0.5, np.float32)
    nan[3, 4, 1] = np.nan
    import OpenImageIO as oiio

    buffer = oiio.ImageBuf(nan)
    buffer.write(str(tmp_path / "nan.exr"))
    assert_one_line_error(fit(tmp_path / "nan.exr"), "nan.exr contains NaN")
    images.write(str(tmp_path / "mask.png"), np.ones((20, 20, 3), np.float32))
    assert_one_line_error(fit(target, "--mask", tmp_path / "mask.png"), "make the mask the same size")
    assert_one_line_error(fit(target, "--evals", 0), "--evals 0 is out of range")
    assert_one_line_error(fit(target, "--method", "magic"), "--method magic", "'hybrid', 'nn', 'optimize'")
    assert_one_line_error(fit(target, "--evals", "abc"), "--evals abc", "integer")
    assert_one_line_error(fit(target, "--bogus", "1"), "No such option: --bogus")
    assert_one_line_error(run("fit", target, "-o", tmp_path / "no" / "p.json", "--model", trained), "does not exist")
    assert_one_line_error(run("fit", target, "-o", out, "--model", tmp_path / "nothing"), "does not exist")
    incomplete = tmp_path / "incomplete"
    incomplete.mkdir()
    shutil.copy(trained / "decoder.msgpack", incomplete)
    assert_one_line_error(run("fit", target, "-o", out, "--model", incomplete), "no encoders")
    assert not out.exists()  # nothing half-written by any failure


def test_sequence_through_the_cli(trained, tiny_dataset, tmp_path):
    from matfit.model import dataset

    data = dataset.open_dataset(tiny_dataset)
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(3):
        images.write(str(frames / f"frame_{k + 8}.png"), np.asarray(data.images[k], np.float32))
    out = tmp_path / "out"
    # 60 evaluations: with 30 the barely trained model's Nelder-Mead may not leave its start (the previous
    # frame's result), and then an edited frame 9 would rightly leave frame 10 as it was
    result = run("sequence", frames, "-o", out, "--model", trained, "--evals", 60)
    assert result.exit_code == 0, result.output
    assert [line.split("|")[1].strip() for line in result.stdout.splitlines()[2:5]] == [
        "frame_8.png",
        "frame_9.png",
        "frame_10.png",
    ]
    assert (out / "summary.md").is_file() and (out / "preview.png").is_file()
    assert json.loads((out / "frame_10.json").read_text())["sequence"]["index"] == 2
    again = run("sequence", frames, "-o", out, "--model", trained, "--evals", 60)
    assert again.exit_code == 0 and again.stdout == result.stdout  # resumed: every frame read back
    images.write(str(frames / "frame_9.png"), np.asarray(data.images[5], np.float32))  # frame 9 edited again
    edited = run("sequence", frames, "-o", out, "--model", trained, "--evals", 60)
    assert edited.exit_code == 0, edited.output
    assert "frame_9.png: the picture is not the one its result on disk was fitted to: fitted again" in edited.stderr
    assert "frame_10.png: the previous frame's result changed: fitted again" in edited.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_one_line_error(run("sequence", empty, "-o", out, "--model", trained), "holds no frames")
    images.write(str(frames / "frame_99.png"), np.zeros((8, 8, 3), np.float32))
    assert_one_line_error(
        run("sequence", frames, "-o", tmp_path / "o2", "--model", trained), "frame_99.png is 8x8", "same size"
    )


def test_presets_sheet(tmp_path):
    result = run("presets", "-o", tmp_path / "sheet.png", "--size", 32, "--spp", 2)
    assert result.exit_code == 0, result.output
    from matfit.rendering import presets

    assert images.read(str(tmp_path / "sheet.png")).shape == (32 + 14, 32 * len(presets.PRESETS), 3)
    assert_one_line_error(
        run("presets", "-o", tmp_path / "sheet.png", "--size", 16), "--size 16 is out of range: use 32 to 1024"
    )


@pytest.mark.slow
def test_bench_render_prints_both_configurations():
    result = run("bench-render", "--count", 5)
    assert result.exit_code == 0, result.output
    rows = [line.split("|")[1:-1] for line in result.stdout.splitlines()[2:]]
    assert [(row[0].strip(), row[1].strip()) for row in rows] == [("64", "16"), ("128", "32")]
    for row in rows:
        ours, bare, ratio = (float(cell) for cell in row[2:])
        assert ours > 0 and bare > 0 and ratio == pytest.approx(ours / bare, abs=0.02)


def test_bench_model_times_the_trained_networks(trained):
    result = run("bench-model", "--model", trained, "--repeats", 10)
    assert result.exit_code == 0, result.output
    networks, load, forward = (cell.strip() for cell in result.stdout.splitlines()[2].split("|")[1:-1])
    assert networks == "2" and 0.0 < float(load) < 60.0 and 0.0 < float(forward) < 1000.0


def test_fit_with_the_gradient_method_an_init_and_verification(trained, target, tmp_path, tiny_dataset):
    from matfit.model import dataset

    source = tmp_path / "source.json"
    source.write_text(json.dumps(params.params_document(dataset.open_dataset(tiny_dataset).params[-1])))
    out = tmp_path / "params.json"
    result = run(
        "fit",
        target,
        "-o",
        out,
        "--model",
        trained,
        "--method",
        "lbfgsb",
        "--starts",
        2,
        "--iterations",
        10,
        "--init",
        source,
        "--answer",
        "best",  # verification's own answer, not the clean one it may give way to
    )
    assert result.exit_code == 0, result.output
    document = json.loads(out.read_text())
    assert document["method"] == "lbfgsb" and document["init"] == str(source) and "answer" not in document
    verification = document["verification"]
    figures, kept, margins = verification["mitsuba_rmse"], verification["kept"], verification["margins"]
    # the default's two rounds of correction: the last round's point joins the start and the best end, and the
    # lowest estimate is kept, every other decided or the kept one at the cap of batches
    assert verification["corrections"] == 2 and {"start", "corrected-2"} <= set(figures) <= {
        "start",
        "end-1",
        "corrected-2",
    }
    assert document["mitsuba_rmse"] == figures[kept] == min(figures.values()) and set(margins) == set(figures) - {kept}
    assert verification["batches"][kept] == verify.MAX_BATCHES or min(margins.values()) >= verify.LEAD
    assert "Mitsuba RMSE" in result.output and f"kept {document['verification']['kept']}" in result.output
    assert_one_line_error(
        run("fit", target, "-o", out, "--model", trained, "--starts", 0), "--starts 0 is out of range"
    )
    out.unlink()
    assert_one_line_error(
        run("fit", target, "-o", out, "--model", trained, "--no-verify", "--corrections", 1),
        "1 correction rounds need verification's renders: drop --no-verify or add --corrections 0",
    )
    assert not out.exists()
    assert_one_line_error(
        run("fit", target, "-o", out, "--model", trained, "--refine", -1), "--refine -1 is out of range"
    )


def test_fit_of_several_pictures_writes_one_params_json_each_and_goes_on_past_a_bad_one(trained, target, tmp_path):
    copy = tmp_path / "copy.png"
    copy.write_bytes(target.read_bytes())
    broken = tmp_path / "broken.png"
    broken.write_text("not an image")
    out = tmp_path / "fits" / "new"
    result = run("fit", target, broken, copy, "-o", out, "--model", trained, "--iterations", 10, "--report", "r.png")
    assert result.exit_code == 2, result.output
    assert sorted(path.name for path in out.iterdir()) == [
        ".matfit-fit-journal.json",  # a picture failed: the same command run again fits only that one
        "copy.params.json",
        "copy.r.png",
        "edited.params.json",
        "edited.r.png",
    ]
    errors = [line for line in result.output.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and str(broken) in errors[0] and "Traceback" not in result.output
    assert f"fitted 2 of 3 pictures into {out}" in result.output
    assert answer_lines(result.output) == []  # each picture's summary line only
    first, second = (json.loads((out / f"{name}.params.json").read_text()) for name in ("edited", "copy"))
    assert first["target"] == str(target) and second["target"] == str(copy) and "verification" in first
    # the same picture fitted first (cold) and last (warm) in one process: the same answer, to the bit
    assert params.parse_params_json(json.dumps(first)).tolist() == params.parse_params_json(json.dumps(second)).tolist()


def test_fit_of_several_pictures_run_again_goes_on_where_it_stopped(trained, target, tmp_path):
    # The journal of the pictures fitted: a second run of the same command keeps those and fits the rest; the folder
    # is left without it once every picture is fitted; other settings, or a picture changed since, fit again.
    first, second = tmp_path / "first.png", tmp_path / "second.png"
    first.write_bytes(target.read_bytes())
    second.write_text("not an image yet")  # fails: as if the run had stopped before it
    out = tmp_path / "fits"
    command = ["fit", first, second, "-o", out, "--model", trained, "--iterations", 10, "--no-verify"]
    assert run(*command).exit_code == 2
    written = (out / "first.params.json").read_bytes()
    assert (out / batch.JOURNAL).is_file()
    second.write_bytes(target.read_bytes())
    result = run(*command)
    assert result.exit_code == 0, result.output
    assert f"{out / 'first.params.json'}: kept, fitted by an earlier run" in result.output
    assert "kept" not in next(line for line in result.output.splitlines() if "second" in line)
    assert (out / "first.params.json").read_bytes() == written and not (out / batch.JOURNAL).exists()
    assert sorted(path.name for path in out.iterdir()) == ["first.params.json", "second.params.json"]
    # finished: the same command fits both again
    assert "kept" not in run(*command).output
    # stopped again; then other settings, or the picture changed since, fit again
    second.write_text("not an image")
    run(*command)
    second.write_bytes(target.read_bytes())
    assert "kept" not in run(*command[:-3], "--iterations", 11, "--no-verify").output
    second.write_text("not an image")
    run(*command)
    first.write_bytes(target.read_bytes()[:-1] + b"\0")  # another picture under the same name
    second.write_bytes(target.read_bytes())
    assert "first.params.json: kept" not in run(*command).output


def test_fit_of_several_pictures_refuses_a_plan_that_cannot_run_before_any_work(trained, target, tmp_path):
    copy = tmp_path / "edited.jpg"
    images.write(str(copy), images.read(str(target)))
    (tmp_path / "afile").write_text("")

    def fit(*arguments):
        return run("fit", *arguments, "--model", trained)

    assert_one_line_error(fit(target, copy, "-o", tmp_path / "p.json"), "p.json names one file", "give -o a folder")
    assert_one_line_error(fit(target, copy, "-o", tmp_path / "afile"), "afile is a file", "give -o a folder")
    assert_one_line_error(fit(target, copy, "-o", tmp_path / "out"), "have one name", "edited.params.json")
    assert_one_line_error(fit(target, target, "-o", tmp_path / "out"), "is given twice")
    assert_one_line_error(fit(target, tmp_path / "none.png", "-o", tmp_path / "out" / "deep"), "none.png is not a file")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["afile", "edited.jpg"]  # no folder made


def test_bench_speed_times_each_stage_and_counts_the_renders_of_a_warm_fit(trained, target):
    from matfit.app.bench import speed

    table = speed.fit_speed(str(trained), 1, cold=False, pictures=[str(target)])
    header, _, row = table.splitlines()
    assert "verification + correction" in header and "renders" in header
    cells = [cell.strip() for cell in row.split("|")[1:-1]]
    assert cells[0] == "edited.png" and "first answer" in header
    first, fit, search, verification, rest, clean = (float(cell.split()[0]) for cell in cells[1:7])
    assert 0 < search < fit and 0 < verification < fit and 0 < rest < fit and clean >= 0
    assert search - 0.01 <= first < fit  # the neural answer lands once the search ends, before Mitsuba checks it
    # five figures each rounded to 0.01 in the table: their sum may read up to 5 x 0.005 off
    assert fit == pytest.approx(search + verification + rest + clean, abs=0.026)
    renders, samples, cores = int(cells[7]), float(cells[8]), float(cells[9])
    # at least the batches of the start, the best end and the last round, and the rounds' residuals
    assert renders >= 3 * verify.BATCHES + methods.CORRECTIONS
    from matfit.model import models

    side = models.load_model(str(trained)).resolution
    assert samples == pytest.approx(renders * verify.SPP * side**2 / 1e6, abs=0.01) and cores > 0


def test_fit_records_the_variant_it_was_asked_for(trained, target, tmp_path):
    out = tmp_path / "params.json"
    arguments = ("fit", target, "-o", out, "--model", trained, "--iterations", 5, "--corrections", 0)
    result = run(*arguments, "--variant", "scalar_rgb")
    assert result.exit_code == 0, result.output
    document = json.loads(out.read_text())
    assert document["mitsuba_variant"] == "scalar_rgb" and document["mitsuba_rmse"] > 0
    assert [stage for stage, _ in answer_lines(result.output)] == ["neural", "verified", "clean"]
    result = run(*arguments, "--no-verify")
    assert result.exit_code == 0, result.output
    document = json.loads(out.read_text())
    assert document["mitsuba_variant"] is None  # no Mitsuba render was made
    landed = answer_lines(result.output)  # nothing rendered: the neural figures, the clean answer's params.json's
    assert [stage for stage, _ in landed] == ["neural", "clean"] and all(figure[0] == "n" for _, figure in landed)
    assert landed[-1][1] == f"neural RMSE {document['neural_rmse']:.2f}"


def test_fit_with_physical_refinement(trained, target, tmp_path):
    out = tmp_path / "params.json"
    result = run("fit", target, "-o", out, "--model", trained, "--iterations", 5, "--refine", 2)
    assert result.exit_code == 0, result.output
    document = json.loads(out.read_text())
    refinement = document["refinement"]
    assert refinement["steps"] == 2 and refinement["seconds"] > 0
    before, after = refinement["mitsuba_rmse_before"], refinement["mitsuba_rmse_after"]
    assert refinement["kept"] == (after < before)  # kept only when the independent render improves
    # refinement starts from the point verification kept, whose estimate is recorded
    verification = document["verification"]
    assert verification["mitsuba_rmse"][verification["kept"]] > 0
    # One figure per answer, the one that chose it, in params.json and in the summary line alike: a refinement not kept
    # left verification's answer with its acceptance render's figure (2.575 in params.json, 1.93 in the line).
    chosen = document["answer"]["mitsuba_rmse"].get(
        document["answer"]["kept"], verification["mitsuba_rmse"][verification["kept"]]
    )
    assert document["mitsuba_rmse"] == (after if refinement["kept"] else chosen)
    assert f"Mitsuba RMSE {document['mitsuba_rmse']:.2f} (verification kept {verification['kept']}" in result.output
    assert f"refined 2 steps, {'kept' if refinement['kept'] else 'not kept'} (its acceptance renders: " in result.output
    landed = answer_lines(result.output)
    assert [stage for stage, _ in landed] == ["neural", "verified", "clean", "refined"]
    assert landed[-1][1] == f"Mitsuba RMSE {document['mitsuba_rmse']:.2f}"
    assert document["mitsuba_variant"] == "llvm_ad_rgb"  # the variant of the fit's renderer, which differentiates
    assert_one_line_error(
        run("fit", target, "-o", tmp_path / "p3.json", "--model", trained, "--refine", 1, "--variant", "scalar_rgb"),
        "refinement differentiates with cuda_ad_rgb or llvm_ad_rgb, not scalar_rgb",
    )
    assert not (tmp_path / "p3.json").exists()
    (tmp_path / "bad.json").write_text('{"roughness": 3}')
    assert_one_line_error(
        run("fit", target, "-o", tmp_path / "p2.json", "--model", trained, "--init", tmp_path / "bad.json"),
        "out of range",
    )
    assert not (tmp_path / "p2.json").exists()


@pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="Ray is an optional extra: pip install -e '.[cluster]' to run the Ray tests",
)
@pytest.mark.parametrize(
    ("address", "fragment"),
    [("127.0.0.1:1", "no Ray answers at 127.0.0.1:1"), ("nowhere", "is not a Ray address: use local, auto, HOST:PORT")],
)
def test_unreachable_ray_is_one_line(tmp_path, address, fragment):
    result = run("render-dataset", tmp_path / "d", "--count", 4, "--resolution", 16, "--spp", 2, "--ray", address)
    assert_one_line_error(result, fragment, "local")
    assert not (tmp_path / "d").exists()


def test_train_starts_from_a_model_directory(trained, tiny_dataset, tmp_path):
    out = tmp_path / "more"
    common = ("train", "--arch", "8", "--dataset", tiny_dataset, "--epochs", 1, "--batch-size", 8)
    result = run(*common, "--learning-rate", 2e-4, "--start-from", trained, "--out", out)
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "encoder-8.json").read_text())
    assert metrics["config"]["start_from"] == str(trained) and metrics["start_sha256"] is not None
    assert_one_line_error(
        run(*common, "--start-from", tmp_path / "none", "--out", tmp_path / "m"),
        "--start-from",
        "has no encoder-8.msgpack",
    )
    assert not (tmp_path / "m").exists()
    assert_one_line_error(
        run(*common, "--loss", "l1", "--out", tmp_path / "m"), "loss 'l1' is unknown: use srgb or linear"
    )
    assert not (tmp_path / "m").exists()


def test_several_pictures_never_overwrite_a_picture_or_a_users_file(tmp_path):
    # Refused before any work (the model is not even loaded): one line, exit 2, every file as it was.
    fast = ("--method", "nn", "--no-verify")
    folder = tmp_path / "d"
    folder.mkdir()
    shutil.copy(shipped.EXAMPLES / "recoloured.png", folder / "a.png")
    shutil.copy(shipped.EXAMPLES / "desaturated.png", folder / "a.report.png")
    before = {path.name: path.read_bytes() for path in folder.iterdir()}
    result = run("fit", folder / "a.png", folder / "a.report.png", "-o", folder, "--report", "report.png", *fast)
    assert_one_line_error(result, f"report {folder / 'a.report.png'} is the target", "choose another output folder")
    assert {path.name: path.read_bytes() for path in folder.iterdir()} == before
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.params.json").write_text("notes")
    result = run("fit", folder / "a.png", folder / "a.report.png", "-o", out, *fast)
    assert_one_line_error(result, f"{out / 'a.params.json'} is in the output folder already and matfit did not write")
    assert os.listdir(out) == ["a.params.json"] and (out / "a.params.json").read_text() == "notes"
    (out / "a.params.json").unlink()
    (out / batch.JOURNAL).mkdir()  # the journal's place taken by a folder: said at once, not after every fit
    result = run("fit", folder / "a.png", folder / "a.report.png", "-o", out, *fast)
    assert_one_line_error(result, f"{out / batch.JOURNAL} is a folder, where matfit keeps the journal")
    assert os.listdir(out) == [batch.JOURNAL]


def test_a_command_without_its_argument_says_what_to_give():
    assert_one_line_error(run("fit"), "matfit fit needs the edited picture: give its path", "matfit fit --help")
    assert_one_line_error(run("sequence"), "matfit sequence needs the folder of frames")


def test_a_sequence_written_into_its_frames_folder_is_refused_on_the_first_run(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    shutil.copy(shipped.EXAMPLES / "recoloured.png", frames / "f1.png")
    result = run("sequence", frames, "-o", frames, "--model", tmp_path / "no-model")  # refused before the model
    assert_one_line_error(result, f"--out {frames} is the folder of the frames", "choose another out folder")
    assert os.listdir(frames) == ["f1.png"]


def test_outputs_that_would_lose_a_file_are_refused_before_any_work(tmp_path):
    picture = tmp_path / "edited.png"
    images.write(str(picture), np.full((16, 16, 3), 0.5, np.float32))
    original = picture.read_bytes()
    (tmp_path / "link.png").symlink_to(picture)
    out = tmp_path / "p.json"

    def fit(*arguments):
        return run("fit", picture, "-o", out, *arguments)

    assert_one_line_error(
        fit("--report", tmp_path / "r.png", "--render", tmp_path / "r.png"),
        "--report",
        "r.png and render",
        "are the same file",
        "give each output its own path",
    )
    assert_one_line_error(fit("--report", picture), "--report", "is the target", "choose another path for the report")
    assert_one_line_error(fit("--render", tmp_path / "link.png"), "--render", "link.png is the target")
    assert_one_line_error(fit("--mask", picture, "--render", picture), "--render", "is the target")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["edited.png", "link.png"]
    out.write_text('{"metallic": 1.0}')  # a previous answer, given as the start of the next fit
    assert_one_line_error(fit("--init", out), "--output", "p.json is the init", "choose another path for the output")
    assert out.read_text() == '{"metallic": 1.0}'
    assert picture.read_bytes() == original
    (tmp_path / "material.png").write_text('{"metallic": 1.0}')  # a params file with a picture's name
    assert_one_line_error(
        run("render", tmp_path / "material.png", "-o", tmp_path / "material.png", "--size", 16, "--spp", 1),
        "--output",
        "is the params file",
    )
    assert (tmp_path / "material.png").read_text() == '{"metallic": 1.0}'


def test_an_output_name_too_long_is_refused_before_any_work(tmp_path):
    picture = tmp_path / "edited.png"
    images.write(str(picture), np.full((16, 16, 3), 0.5, np.float32))
    result = run("fit", picture, "-o", tmp_path / ("p" * 300 + ".json"), "--model", tmp_path / "no-model")
    assert_one_line_error(result, "its name is 305 bytes", "choose a shorter name")


@pytest.mark.parametrize("arguments", [["params"], ["--help"], ["render", "--help"]])
def test_a_reader_that_went_away_ends_the_command_quietly(arguments):
    """`matfit params | head -1`: the reader has gone before the first line; exit 141 as SIGPIPE, nothing on stderr."""
    read, write = os.pipe()
    os.close(read)
    try:
        result = subprocess.run(
            [sys.executable, "-m", "matfit", *arguments], stdout=write, stderr=subprocess.PIPE, text=True, timeout=120
        )
    finally:
        os.close(write)
    assert (result.returncode, result.stderr) == (141, "")


def test_train_and_sequence_refuse_a_read_only_output_as_fit_does(tiny_dataset, tmp_path):
    result = run("train", "--arch", "8", "--dataset", tiny_dataset, "--epochs", 1, "--out", "/proc/model")
    assert_one_line_error(result, "--out /proc/model cannot be written: /proc is read-only", "choose another folder")
    frames = tmp_path / "frames"
    frames.mkdir()
    images.write(str(frames / "f.png"), np.full((16, 16, 3), 0.5, np.float32))
    result = run("sequence", frames, "-o", "/proc/sequence", "--model", tmp_path / "no-model")  # checked first
    assert_one_line_error(result, "--out /proc/sequence cannot be written: /proc is read-only")


def linked_model(folder: Path) -> Path:
    """Returns a model folder whose files are links to the shipped model's (a model of one's own, made in no time)."""
    folder.mkdir()
    for name in os.listdir(shipped.MODEL):
        (folder / name).symlink_to(shipped.MODEL / name)
    return folder


def test_no_output_of_a_fit_may_be_a_file_of_its_model_or_of_the_shipped_one(tmp_path):
    # `matfit fit in.png -o <model>/decoder.json` replaced the model's own file: every later fit with it failed.
    model = linked_model(tmp_path / "model")
    target = shipped.EXAMPLES / "recoloured.png"
    fit = ("fit", target, "--model", model, "--method", "nn", "--no-verify")
    for option, name in (("-o", "decoder.json"), ("-o", "evaluation.json"), ("--report", "report.png")):
        arguments = (*fit, "-o", tmp_path / "p.json") if option != "-o" else fit
        result = run(*arguments, option, model / name)
        assert_one_line_error(result, f"{model / name} is a file of the model {model}: writing it would change")
        assert (model / name).is_symlink() or not (model / name).exists()
    (tmp_path / "link.json").symlink_to(shipped.MODEL / "decoder.json")  # the shipped model's, by another name
    result = run("fit", target, "-o", tmp_path / "link.json", "--method", "nn", "--no-verify")
    assert_one_line_error(result, f"is a file of the model {shipped.MODEL}", "choose another path for the output")
    result = run("render", "--preset", "gold", "-o", shipped.MODEL / "gold.png", "--size", 16, "--spp", 1)
    assert_one_line_error(result, f"is a file of the model {shipped.MODEL}")
    assert not (shipped.MODEL / "gold.png").exists() and not (tmp_path / "p.json").exists()


def test_a_model_whose_card_is_damaged_is_refused_before_the_fit(tmp_path):
    model = linked_model(tmp_path / "model")
    (model / "evaluation.json").unlink()
    (model / "evaluation.json").write_text('{"decoder_rmse": {"mean": 0, "median": 1, "p95": 2}}')
    target = shipped.EXAMPLES / "recoloured.png"
    result = run("fit", target, "-o", tmp_path / "p.json", "--model", model, "--method", "nn", "--no-verify")
    assert_one_line_error(result, "evaluation.json: decoder_rmse.mean is 0, not a positive RMSE", "--card")
    assert not (tmp_path / "p.json").exists()


def test_json_inputs_that_are_not_regular_files_are_refused_at_once(tmp_path):
    # `mkfifo f.json; matfit render f.json` hung; `--init /dev/zero` read until the kernel killed it.
    os.mkfifo(tmp_path / "f.json")
    result = run("render", tmp_path / "f.json", "-o", tmp_path / "x.png", "--size", 16, "--spp", 1)
    assert_one_line_error(result, f"cannot read {tmp_path / 'f.json'}: it is a FIFO (named pipe), not a regular file")
    target = shipped.EXAMPLES / "recoloured.png"
    result = run("fit", target, "-o", tmp_path / "p.json", "--init", "/dev/zero", "--method", "nn", "--no-verify")
    assert_one_line_error(result, "cannot read /dev/zero: it is a character device, not a regular file")
    assert list(tmp_path.iterdir()) == [tmp_path / "f.json"]
