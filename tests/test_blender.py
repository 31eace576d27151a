"""The Blender export and the Cycles round trip (matfit.rendering.blender); the bpy tests need `make blender`."""

import json
import os
import subprocess

import numpy as np
import pytest
from helpers import assert_round_trip
from typer.testing import CliRunner

from matfit import images, params
from matfit.app.cli import app
from matfit.rendering import blender, blender_mapping, export, presets

try:
    BLENDER = blender.find_blender()
except blender.BlenderError:
    BLENDER = None
needs_blender = pytest.mark.skipif(
    BLENDER is None, reason="bpy 4.5 is not installed: run `make blender` (.venv-blender)"
)
INSPECT = os.path.join(os.path.dirname(__file__), "blender_inspect.py")


def test_ior_and_tints_follow_mitsuba():
    values = params.from_mapping(
        {
            "base_color_r": 0.6,
            "base_color_g": 0.3,
            "base_color_b": 0.1,
            "specular": 0.25,
            "spec_tint": 0.5,
            "sheen": 0.8,
            "sheen_tint": 1.0,
        }
    )
    principled, _ = export.blender_inputs(values)
    # F0 of the index of refraction equals Disney's 0.08 x specular
    eta = principled["IOR"]
    assert ((eta - 1) / (eta + 1)) ** 2 == pytest.approx(0.08 * 0.25, rel=1e-9)
    assert export.eta_from_specular(0.5) == pytest.approx(1.5, rel=1e-9)
    luminance = 0.212671 * 0.6 + 0.715160 * 0.3 + 0.072169 * 0.1
    hue = np.array([0.6, 0.3, 0.1]) / luminance
    np.testing.assert_allclose(principled["Specular Tint"][:3], 1 + 0.5 * (hue - 1), rtol=1e-6)
    np.testing.assert_allclose(principled["Sheen Tint"][:3], hue, rtol=1e-6)
    assert principled["Sheen Weight"] == pytest.approx(export.SHEEN_WEIGHT_SCALE * 0.8)
    assert principled["Specular IOR Level"] == 0.5


def test_metal_keeps_a_white_edge_and_no_sheen_through_glass():
    metal, _ = export.blender_inputs(
        params.from_mapping({"metallic": 1.0, "spec_tint": 1.0, "sheen": 1.0, "base_color_r": 0.9})
    )
    assert metal["Specular Tint"] == pytest.approx([1.0, 1.0, 1.0, 1.0])
    assert metal["Sheen Weight"] == 0.0
    glass, _ = export.blender_inputs(params.from_mapping({"spec_trans": 1.0, "sheen": 1.0}))
    assert glass["Sheen Weight"] == 0.0


def test_coat_roughness_is_the_square_root_of_disneys_alpha():
    for gloss, alpha in ((0.0, 0.1), (1.0, 0.001), (0.5, 0.0505)):
        principled, _ = export.blender_inputs(params.from_mapping({"clearcoat": 1.0, "clearcoat_gloss": gloss}))
        assert principled["Coat Roughness"] ** 2 == pytest.approx(alpha, rel=1e-9)
        assert principled["Coat Weight"] == pytest.approx(export.COAT_WEIGHT_SCALE)


def test_script_refuses_a_name_that_would_break_it():
    with pytest.raises(ValueError, match="material name"):
        export.blender_script(presets.preset("gold"), name='a"b')


def fake_comparison(count=2, resolution=16):
    rng = np.random.default_rng(0)
    mitsuba = rng.uniform(0, 1, (count, resolution, resolution, 3)).astype(np.float32)
    return blender.Comparison(
        ["gold", "glass"][:count],
        mitsuba,
        mitsuba * 0.5,
        1.0,
        [1.5, 9.25][:count],
        [2.0, 10.0][:count],
        [1.0, 3.0][:count],
        resolution,
        16,
    )


def test_table_marks_the_opaque_target():
    text = blender.table(fake_comparison())
    assert "| gold | 1.50 | 2.00 | 1.00 | <= 8 (met) |" in text
    assert "| glass | 9.25 | 10.00 | 3.00 |  |" in text


def test_picture_has_one_labelled_row_per_material():
    picture = blender.picture(fake_comparison(), scale=2)
    assert picture.shape == (2 * (32 + 14), 3 * 32, 3)


def test_missing_blender_names_the_fix(tmp_path, monkeypatch):
    monkeypatch.setenv(blender.ENVIRONMENT_VARIABLE, str(tmp_path / "nowhere" / "python"))
    with pytest.raises(blender.BlenderError, match="make blender") as raised:
        blender.find_blender()
    assert "pip install bpy==4.5.15" in str(raised.value) and "\n" not in str(raised.value)


def test_cli_bad_inputs_are_one_line_and_write_nothing(tmp_path):
    runner = CliRunner()
    out = tmp_path / "check"
    result = runner.invoke(
        app, ["blender-check", "--out", str(out), "--preset", "gold", "--blender", str(tmp_path / "no-python")]
    )
    assert result.exit_code == 2 and result.output.count("\n") == 1 and "error: no Blender" in result.output
    assert not out.exists()
    result = runner.invoke(app, ["blender-check", "--out", str(out), "--preset", "gld"])
    assert result.exit_code == 2 and "unknown preset 'gld'" in result.output
    (tmp_path / "file").write_text("x")
    result = runner.invoke(app, ["blender-check", "--out", str(tmp_path / "file"), "--preset", "gold"])
    assert result.exit_code == 2 and "is a file" in result.output
    result = runner.invoke(app, ["blender-check", "--spp", "0"])
    assert result.exit_code == 2 and "--spp" in result.output


@needs_blender
@pytest.mark.parametrize("name", ["jade", "red-plastic"])
def test_exported_script_sets_every_input_on_selected_meshes_only(tmp_path, name):
    values = presets.preset(name)
    principled, volume = export.blender_inputs(values)
    script, report = tmp_path / "mat.py", tmp_path / "report.json"
    script.write_text(export.blender_script(values))
    subprocess.run(
        [BLENDER, INSPECT, str(script), str(report)],
        check=True,
        capture_output=True,
        env={**os.environ, "PYTHONNOUSERSITE": "1"},
    )
    result = json.loads(report.read_text())
    assert result["version"].startswith("4.5")
    bsdf = result["nodes"]["ShaderNodeBsdfPrincipled"]
    assert bsdf["distribution"] == "GGX"
    for key, expected in principled.items():
        assert bsdf["inputs"][key] == pytest.approx(expected, rel=1e-6, abs=1e-7), key
    # only the selected meshes, and per object: the unselected object sharing a mesh keeps "keep"
    assert result["slots"]["bare"] == [["OBJECT", "matfit"]]
    assert result["slots"]["shared_a"] == [["OBJECT", "matfit"]]
    assert result["slots"]["shared_b"] == [["DATA", "keep"]]
    assert result["shared_mesh_materials"] == ["keep"]
    has_volume = name == "jade"
    assert ("ShaderNodeVolumeScatter" in result["nodes"]) == has_volume
    assert result["homogeneous_volume"] == has_volume
    if has_volume:
        absorption = result["nodes"]["ShaderNodeVolumeAbsorption"]["inputs"]
        scatter = result["nodes"]["ShaderNodeVolumeScatter"]["inputs"]
        assert absorption["Density"] == pytest.approx(volume["absorption_density"], rel=1e-6)
        assert absorption["Color"] == pytest.approx(volume["absorption_color"], rel=1e-6, abs=1e-7)
        assert scatter["Density"] == pytest.approx(volume["scatter_density"], rel=1e-6)
        assert scatter["Color"] == pytest.approx(volume["scatter_color"], rel=1e-6, abs=1e-7)
        assert scatter["Anisotropy"] == pytest.approx(0.3, rel=1e-6)
        assert "ShaderNodeAddShader.Shader->ShaderNodeOutputMaterial.Volume" in result["links"]
    assert "ShaderNodeBsdfPrincipled.BSDF->ShaderNodeOutputMaterial.Surface" in result["links"]


@needs_blender
def test_cycles_renders_the_scene_like_mitsuba():
    names = ["gold", "blue-rubber"]
    comparison = blender.compare(names, [presets.preset(name) for name in names], blender.Setup(resolution=32, spp=64))
    # the lights and the environment are in Mitsuba's units: the exposure factor stays near 1
    assert comparison.exposure == pytest.approx(1.0, abs=0.03)
    assert max(comparison.rmse) < 8.0
    # and the comparison can fail: gold's Cycles render against blue rubber's Mitsuba render
    swapped = images.rmse(images.srgb_encode(comparison.cycles[0]), images.srgb_encode(comparison.mitsuba[1]))
    assert swapped > 3 * max(comparison.rmse)


@pytest.mark.parametrize("name", list(presets.PRESETS))
def test_import_of_the_export_gives_back_every_carried_parameter(name):
    values = presets.preset(name)
    principled, volume = export.blender_inputs(values)
    carried_volume = volume if blender_mapping.has_volume(principled, volume) else None
    back, missing, notes = export.from_blender_inputs(principled, carried_volume)
    assert notes == []
    assert_round_trip(values, back, missing)
    # what cannot come back is named, and only that
    metal, transmissive = values[params.INDEX["metallic"]] == 1.0, values[params.INDEX["spec_trans"]] == 1.0
    assert ("spec_tint" in missing) == (metal or transmissive)  # the transmissive presets are white
    assert ("sheen" in missing) == (metal or transmissive)
    assert ("density" in missing) == (not transmissive)


def test_import_clips_and_names_what_matfit_cannot_show():
    principled, volume = export.blender_inputs(presets.preset("velvet"))
    principled.update({"Sheen Weight": 0.5, "Specular IOR Level": 0.8, "Subsurface Weight": 0.3, "IOR": 1.45})
    back, missing, notes = export.from_blender_inputs(principled, None)
    assert "density" in missing and back[params.INDEX["sheen"]] == 1.0
    assert back[params.INDEX["specular"]] == pytest.approx(((1.45 - 1) / 2.45) ** 2 / 0.08)
    assert notes == [
        "sheen 5 clipped to [0, 1]",
        "Specular IOR Level 0.8 shown as 0.5",
        "Subsurface Weight ignored (matfit's shader has none)",
    ]
    # a thick medium: density grows until the darkest channel keeps the lowest colour
    glass = presets.preset("amber-glass")
    principled, volume = export.blender_inputs(glass)
    volume = {**volume, "absorption_density": 5 * volume["absorption_density"]}
    back, _, notes = export.from_blender_inputs(principled, volume)
    assert notes == []
    sigma_t = params.medium_coefficients(back)[0]
    np.testing.assert_allclose(sigma_t, 5 * params.medium_coefficients(glass)[0], rtol=1e-9)
    assert back[params.INDEX["medium_color_b"]] == pytest.approx(0.01) and back[params.INDEX["density"]] > 1
