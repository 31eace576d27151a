"""The extension's scene export (blender/extension/scene_export.py) and its two scene operators, in one bpy session.

A scene built in Blender (a UV sphere on a ground plane, a sun, an area light, a point light, a spot, a world
colour and a world image) is exported once per light kind, each light alone; Cycles renders it there and
Mitsuba renders the export here (`scene_file.Renderer`, matfit's own integrator), and the median ratio of their
pixels per light kind must be within 3% of 1. Then the whole loop runs headless: "Picture of this object", a
hue edit of that picture (NumPy, the ball's red pixels turned to green), "Fit edited picture in this scene"
(`--refine 12`), the material on the ball. Needs `make blender` (skipped with the reason otherwise).
"""

import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ElementTree

import numpy as np
import pytest

from matfit import images, params, shipped
from matfit.rendering import blender, export, scene_file

try:
    BLENDER = blender.find_blender()
except blender.BlenderError:
    BLENDER = None
pytestmark = pytest.mark.skipif(BLENDER is None, reason="bpy 4.5 is not installed: run `make blender` (.venv-blender)")
ROOT = shipped.PACKAGE.parent
RUN = os.path.join(os.path.dirname(__file__), "blender_scene_export_run.py")
KINDS = ("sun", "area", "point", "spot", "world", "world_image")
SPP = 128  # both renderers, 64 x 48 pixels: two Mitsuba seeds then differ by under 0.2% in the median ratio
LOOP_SIZE, LOOP_SPP = 64, 32
# The edit of the picture: the ball's red pixels turned to green (a hue turn of 120 degrees), everything else kept.
EDIT = """import sys
import numpy as np
from matfit import images
picture = images.read(sys.argv[1])
red = picture[..., 0] > 1.5 * np.maximum(picture[..., 1], picture[..., 2])
edited = picture.copy()
edited[red] = picture[red][:, [2, 0, 1]]
images.write(sys.argv[2], edited)
"""


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """Returns (report, folder, Blender's output) of one bpy session that exported, rendered and fitted."""
    folder = tmp_path_factory.mktemp("scene-export")
    built = subprocess.run(
        [sys.executable, str(ROOT / "blender" / "build.py"), str(folder / "dist")],
        capture_output=True,
        text=True,
        check=True,
    )
    command = folder / "matfit"
    command.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m matfit "$@"\n')
    command.chmod(0o755)
    (folder / "edit.py").write_text(EDIT)
    (folder / "edited-first.png").write_bytes((shipped.EXAMPLES / "recoloured.png").read_bytes())
    job = {
        "zip": built.stdout.strip(),
        "out": str(folder / "out"),
        "spp": SPP,
        "cases": list(KINDS),
        "refusals": {"edited": str(folder / "edited-first.png")},
        "notes": True,
        "loop": {
            "command": str(command),
            "size": LOOP_SIZE,
            "spp": LOOP_SPP,
            "options": "--refine 12",  # 4 steps move the colour a tenth of the way; 12 take 1.5 s more
            "edit": [sys.executable, str(folder / "edit.py")],
        },
    }
    (folder / "job.json").write_text(json.dumps(job))
    environment = {**os.environ, "PYTHONNOUSERSITE": "1", "BLENDER_USER_RESOURCES": str(folder / "user")}
    run = subprocess.run(
        [BLENDER, RUN, str(folder / "job.json"), str(folder / "report.json")],
        capture_output=True,
        text=True,
        env=environment,
        timeout=900,
    )
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    return json.loads((folder / "report.json").read_text()), folder, run.stdout + run.stderr


def pooled_brightness(image):
    """Returns the mean of the three channels over 2 x 2 blocks: less noise per pixel, the ratio's median steadier."""
    height, width = image.shape[0] // 2 * 2, image.shape[1] // 2 * 2
    return image[:height, :width].reshape(height // 2, 2, width // 2, 2, 3).mean(axis=(1, 3, 4))


def median_ratio(image, reference):
    """Returns the median over the lit pixels (above 5% of each image's 99th percentile) of image / reference."""
    a, b = pooled_brightness(image), pooled_brightness(reference)
    lit = (a > 0.05 * np.percentile(a, 99)) & (b > 0.05 * np.percentile(b, 99))
    assert lit.sum() > 50
    return float(np.median(a[lit] / b[lit]))


def test_the_export_is_a_scene_file_matfit_reads(session):
    case = session[0]["cases"]["area"]
    read = scene_file.read(case["path"], case["object"])
    # the film is the render resolution (128 x 96) at its percentage (50); every mesh is a file beside the XML
    assert (read.width, read.height) == (64, 48) and read.shapes == ("Ball", "Ground", "Area")
    assert case["ids"] == {"Ball": "Ball", "Ground": "Ground"} and case["notes"] == []
    # the ball's own material is its Principled BSDF through blender_mapping: the fit's start
    assert read.own is not None and read.own_note == "the shape's principled BSDF"
    np.testing.assert_allclose(read.own[:3], [0.7, 0.12, 0.08], atol=1e-6)
    assert read.own[params.INDEX["roughness"]] == pytest.approx(0.35, abs=1e-6)
    root = ElementTree.parse(case["path"]).getroot()
    ground = next(shape for shape in root.iter("shape") if shape.get("id") == "Ground")
    assert ground.find("bsdf").get("type") == "diffuse"  # Specular IOR Level 0: diffuse, as measured
    emitters = {
        kind: [emitter.get("type") for emitter in ElementTree.parse(case["path"]).getroot().iter("emitter")]
        for kind, case in session[0]["cases"].items()
    }
    assert emitters == {
        "sun": ["directional"],
        "area": ["area"],
        "point": ["point"],
        "spot": ["spot"],
        "world": ["constant"],
        "world_image": ["envmap"],
    }


@pytest.mark.parametrize("kind", KINDS)
def test_mitsuba_render_of_the_export_matches_cycles_per_light_kind(session, kind):
    report, folder, _ = session
    case = report["cases"][kind]
    read = scene_file.read(case["path"], case["object"])
    renderer = scene_file.Renderer(read, read.size(64))
    mitsuba = renderer.render(read.own, seed=1, spp=SPP)
    cycles = np.load(folder / "out" / kind / "cycles.npy")
    assert mitsuba.shape == cycles.shape == (48, 64, 3)
    noise = median_ratio(mitsuba, renderer.render(read.own, seed=2, spp=SPP))
    ratio = median_ratio(mitsuba, cycles)
    print(f"{kind}: median ratio Mitsuba / Cycles {ratio:.4f} (Mitsuba / Mitsuba {noise:.4f})")
    assert abs(noise - 1) < 0.01
    assert 0.97 <= ratio <= 1.03


def test_what_the_export_cannot_carry_is_one_line_each(session):
    notes = session[0]["notes"]
    assert notes["fitted"] == "Odd_thing" and notes["ids"]["Ball"] == "Ball"
    assert notes["notes"] == [
        "fitted object 'Odd thing': Base Color (Image Texture) read at their unlinked values",
        "fitted object 'Odd thing': distribution MULTI_GGX shown as GGX",
        "fitted object 'Odd thing': 2 materials; its active one 'Textured' is fitted, on the whole object",
        "light 'Point': radius 0.1 shown as a point (hard shadows)",
    ]


def test_scene_operators_refuse_in_one_line_and_leave_nothing(session):
    refusals = session[0]["refusals"]
    assert refusals["fit_first"] == [
        ["CANCELLED"],
        "Error: matfit: no scene exported: make the object's picture first (Picture of this object), then edit it",
    ]
    assert refusals["orthographic"] == [
        ["CANCELLED"],
        "Error: matfit: camera 'Camera' is ortho, not perspective: matfit renders a perspective camera; set its "
        "Type to Perspective",
    ]
    assert "refused" not in refusals["left"]


def test_picture_then_fit_in_this_scene_puts_a_material_closer_to_the_edit_on_the_object(session):
    report, folder, output = session
    loop = report["loop"]
    out = folder / "out" / "loop"
    picture = out / "picture-Ball-standard.png"
    assert loop["picture"] == [["FINISHED"], None] and loop["scene_picture"] == str(picture)
    assert f"matfit: picture of 'Ball' in this scene saved to {picture} (Standard view transform" in output
    scene = out / "picture-Ball-standard.scene" / "scene.xml"
    source = params.read_file(str(out / "picture-Ball-standard.source.json"))
    assert images.read(str(picture)).shape == (48, 64, 3)  # the preferences' size on the camera's aspect
    # the fit: its params.json beside the edited picture, its material on the ball alone
    assert loop["fit"] == [["FINISHED"], None]
    document = json.loads((out / "edited.params.json").read_text())
    assert document["scene"]["object"] == "Ball" and document["scene"]["path"] == str(scene)
    figures = f"Mitsuba RMSE {document['mitsuba_rmse']:.2f} (start {document['start']['rmse']:.2f})"
    assert f"Info: matfit: material 'matfit Ball' on 'Ball', fitted in its scene, {figures}" in output.splitlines()
    assert loop["slots"] == {"Ball": [["OBJECT", "matfit Ball"]], "Ground": [["DATA", "Floor"]]}
    fitted = params.read_file(str(out / "edited.params.json"))
    principled, _ = export.blender_inputs(fitted)
    inputs = loop["fitted"]["nodes"]["ShaderNodeBsdfPrincipled"]["inputs"]
    for key, expected in principled.items():
        assert inputs[key] == pytest.approx(expected, rel=1e-6, abs=1e-6), key
    # its Mitsuba render in the exported scene is closer to the edit than the start's (one seed for both)
    read = scene_file.read(str(scene), "Ball")
    renderer = scene_file.Renderer(read, read.size(LOOP_SIZE))
    edited = images.srgb_encode(images.read(str(out / "edited.png")))
    start = float(images.rmse(images.srgb_encode(renderer.render(source, seed=7, spp=128)), edited))
    after = float(images.rmse(images.srgb_encode(renderer.render(fitted, seed=7, spp=128)), edited))
    print(f"RMSE to the edit: start {start:.2f}, fitted {after:.2f}")
    assert after < 0.8 * start
