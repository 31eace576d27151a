"""The Blender extension (blender/extension/): its zip installed into a fresh bpy session, every operator run there.

One Blender session (tests/blender_extension_run.py) does every step, since starting bpy, matfit's renders and
the fit cost seconds each; the tests read its report. Needs `make blender` (skipped with the reason otherwise).
"""

import json
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_round_trip

from matfit import images, params, shipped
from matfit.rendering import blender, blender_mapping, export, presets

try:
    BLENDER = blender.find_blender()
except blender.BlenderError:
    BLENDER = None
pytestmark = pytest.mark.skipif(BLENDER is None, reason="bpy 4.5 is not installed: run `make blender` (.venv-blender)")
ROOT = shipped.PACKAGE.parent
RUN = os.path.join(os.path.dirname(__file__), "blender_extension_run.py")
SIZE, SPP = 32, 16  # the picture's and the fit's renders: small, the checks compare like with like
FIT_OPTIONS = ["--method", "nn"]
PICTURE_PRESET = "jade"  # transmission and a scattering medium: every part of the mapping
EDITED = str(shipped.EXAMPLES / "recoloured.png")
REFUSALS = ("texture", "glass", "emission")
SESSION_SECONDS = 900  # the whole bpy session, every step: under two minutes on a 2-core machine; more is a hang
MUTE_SECONDS = 3.0  # the extension's FIT_SECONDS for the worker that never answers: what its fit may take, there
STALE = {"neural_rmse": 99.0, "mitsuba_rmse": 99.0}  # the figures of a params.json that no fit of this run wrote
WRITTEN = {
    "params": {"base_color_r": 0.2, "spec_trans": 0.9, "density": 2.0, "medium_color_g": 0.5},
    "neural_rmse": 1.5,
}
PREVIEW = "matfit (not final)"  # the material of a running fit's earlier answer
# A "matfit worker" of protocol 2 whose fits send the neural answer WRITTEN, then fail once the file GO exists
FAILS_LATE = """#!{python}
import json, os, sys, time
print(json.dumps({{"ready": "matfit worker", "protocol": 2}}), flush=True)
for line in sys.stdin:
    request = json.loads(line)
    print(json.dumps({{"id": request["id"], "stage": "neural", "document": {written}}}), flush=True)
    while not os.path.exists({go!r}):
        time.sleep(0.05)
    print(json.dumps({{"id": request["id"], "exit": 2, "output": "error: the fit failed after its neural answer"}}))
"""
# "matfit" commands that exit 0 having written, as the output, something that is not matfit's params.json
WRITERS = {
    "not JSON": "printf 'not json' > \"$out\"",
    "NaN": 'printf \'{"params": {"roughness": NaN}}\' > "$out"',
    "out of range": 'printf \'{"params": {"roughness": 7}}\' > "$out"',
    "unknown name": 'printf \'{"params": {"roughnes": 0.2}}\' > "$out"',
    "no params": "printf '[1, 2]' > \"$out\"",
    "too large": 'head -c 2000000 /dev/zero > "$out"',
    "a FIFO": 'mkfifo "$out"',
    "a link": 'ln -s "$STALE" "$out"',
}


def matfit(*arguments, folder):
    """Runs the matfit command line as the extension does; returns its output."""
    result = subprocess.run(
        [sys.executable, "-m", "matfit", *arguments], capture_output=True, text=True, check=True, cwd=folder
    )
    return result.stdout


def open_bytes(path):
    with open(path, "rb") as file:
        return file.read()


def assert_material_is(state, path):
    """Asserts that the material's nodes are blender_mapping.to_blender of the params.json at `path`, input by input."""
    principled, volume = export.blender_inputs(params.read_file(str(path)))
    nodes = state["nodes"]
    for key, expected in principled.items():
        assert nodes["ShaderNodeBsdfPrincipled"]["inputs"][key] == pytest.approx(expected, rel=1e-6, abs=1e-6), key
    assert nodes["ShaderNodeBsdfPrincipled"]["distribution"] == "GGX"
    if not blender_mapping.has_volume(principled, volume):
        assert sorted(nodes) == ["ShaderNodeBsdfPrincipled", "ShaderNodeOutputMaterial"]
        return
    absorption, scatter = nodes["ShaderNodeVolumeAbsorption"]["inputs"], nodes["ShaderNodeVolumeScatter"]["inputs"]
    actual = [*absorption["Color"], absorption["Density"], *scatter["Color"], scatter["Density"], scatter["Anisotropy"]]
    expected = [
        *volume["absorption_color"],
        volume["absorption_density"],
        *volume["scatter_color"],
        volume["scatter_density"],
        volume["anisotropy"],
    ]
    assert actual == pytest.approx(expected, rel=1e-6, abs=1e-6)
    assert "ShaderNodeAddShader.Shader->ShaderNodeOutputMaterial.Volume" in state["links"]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """Returns (report, folder, Blender's output) of one bpy session that ran every step."""
    folder = tmp_path_factory.mktemp("extension")
    built = subprocess.run(
        [sys.executable, str(ROOT / "blender" / "build.py"), str(folder / "dist")],
        capture_output=True,
        text=True,
        check=True,
    )
    command = folder / "matfit"
    command.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m matfit "$@"\n')
    command.chmod(0o755)
    (folder / "my dir").mkdir()
    spaced = folder / "my dir" / "matfit"  # the same command, in a folder whose name has a space
    spaced.write_text(command.read_text())
    spaced.chmod(0o755)
    silent = folder / "silent"  # a "matfit" that exits 0 and writes nothing
    silent.write_text("#!/bin/sh\nexit 0\n")
    silent.chmod(0o755)
    # planted beside a picture in a shared folder: a script that would leave a mark, and a stale params.json
    (folder / "planted.blender.py").write_text(f"open({str(folder / 'executed')!r}, 'w').write('planted')\n")
    stale = params.params_document(presets.preset("gold"), **STALE)
    (folder / "planted.params.json").write_text(json.dumps(stale))
    crashes = folder / "crashes"  # a "matfit worker" that says it is ready, then ends during every fit
    crashes.write_text(
        f"#!/bin/sh\necho started >> '{folder / 'crashes.count'}'\n"
        'echo \'{"ready": "matfit worker", "protocol": 1}\'\nread request\n'
        "echo 'Traceback (most recent call last):' >&2\necho 'RuntimeError: the worker crashed' >&2\nexit 3\n"
    )
    crashes.chmod(0o755)
    mute = folder / "mute"  # a "matfit worker" that says it is ready, then answers every fit with lines that are none
    mute.write_text(
        '#!/bin/sh\necho \'{"ready": "matfit worker", "protocol": 1}\'\n'
        'while read request; do echo \'{"id": "no such fit", "exit": 0}\'; echo "not an answer"; done\n'
    )
    mute.chmod(0o755)
    fails = folder / "fails late"
    fails.write_text(FAILS_LATE.format(python=sys.executable, written=json.dumps(WRITTEN), go=str(folder / "go")))
    fails.chmod(0o755)
    writers = {}
    # and one that writes a params.json of matfit's form (names left out take their defaults), for a picture
    # beside which NAME.params.json cannot be saved (a folder is in the way)
    (folder / "blocked.png").write_bytes(open_bytes(EDITED))
    (folder / "blocked.params.json").mkdir()
    for kind, write in {**WRITERS, "params.json": f"printf '{json.dumps(WRITTEN)}' > \"$out\""}.items():
        writers[kind] = str(folder / f"writes {kind}")  # the -o path of the fit is the one written
        find_output = 'while [ $# -gt 0 ]; do [ "$1" = -o ] && out="$2"; shift; done'
        stale_file = folder / "planted.params.json"
        Path(writers[kind]).write_text(f"#!/bin/sh\nSTALE='{stale_file}'\n{find_output}\n{write}\n")
        Path(writers[kind]).chmod(0o755)
    imports = {}
    for name in presets.PRESETS:
        imports[name] = str(folder / f"{name}.py")
        (folder / f"{name}.py").write_text(export.blender_script(presets.preset(name), name=name))
    (folder / "picture.py").write_text(export.blender_script(presets.preset(PICTURE_PRESET)))
    (folder / "edited.png").write_bytes(open_bytes(EDITED))
    (folder / "not-a-picture.png").write_text("not a picture")
    (folder / "follow.png").write_bytes(open_bytes(EDITED))
    (folder / "stages.png").write_bytes(open_bytes(EDITED))
    job = {
        "zip": built.stdout.strip(),
        "command": str(command),
        "size": SIZE,
        "spp": SPP,
        "fit_options": " ".join(FIT_OPTIONS),
        "imports": imports,
        "picture": {"script": str(folder / "picture.py"), "out": str(folder / "pictures" / "picture.png")},
        "refusals": list(REFUSALS),
        "unwritable": [str(folder / "pictures" / "refused.gif"), "/proc/picture.png", "/proc/matfit/picture.png"],
        "fit": str(folder / "edited.png"),
        "worker": True,
        "failures": [
            [str(folder / "no-such-matfit"), str(folder / "edited.png")],
            [str(command), str(folder / "not-a-picture.png")],
            [str(spaced), str(folder / "not-a-picture.png")],
        ],
        "planted": {
            "edited": str(folder / "planted.png"),
            "silent": str(silent),
            "redirect": " ".join([*FIT_OPTIONS, "-o", str(folder / "x.json"), "--blender", str(folder / "x.py")]),
            "writers": writers,
            "blocked": str(folder / "blocked.png"),
            "crashes": str(crashes),
            "mute": str(mute),
            "mute_seconds": MUTE_SECONDS,
        },
        "follow": {"edited": str(folder / "follow.png"), "saved": str(shipped.EXAMPLES / "desaturated.png")},
        "stages": {"edited": str(folder / "stages.png"), "fails": str(fails), "go": str(folder / "go")},
        "cancel": str(folder / "edited.png"),
    }
    (folder / "job.json").write_text(json.dumps(job))
    environment = {**os.environ, "PYTHONNOUSERSITE": "1", "BLENDER_USER_RESOURCES": str(folder / "user")}
    run = subprocess.run(
        [BLENDER, RUN, str(folder / "job.json"), str(folder / "report.json")],
        capture_output=True,
        text=True,
        env=environment,
        timeout=SESSION_SECONDS,
    )
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    return json.loads((folder / "report.json").read_text()), folder, run.stdout + run.stderr


def test_the_zip_carries_the_mapping_table_and_installs(session):
    report, folder, _ = session
    assert report["installed"] == ["FINISHED"] and report["version"].startswith("4.")
    (zip_path,) = (folder / "dist").iterdir()
    with zipfile.ZipFile(zip_path) as archive:
        assert archive.read("blender_mapping.py") == (ROOT / "matfit" / "rendering" / "blender_mapping.py").read_bytes()
        assert json.loads(archive.read("parameters.json")) == params.table()
        assert "blender_manifest.toml" in archive.namelist()


@pytest.mark.parametrize("name", list(presets.PRESETS))
def test_import_of_every_exported_preset_gives_back_its_parameters(session, name):
    imported = session[0]["imports"][name]
    assert imported["notes"] == []
    back = params.from_mapping(imported["values"])
    assert_round_trip(presets.preset(name), back, imported["missing"])


def test_picture_of_an_exported_preset_is_matfit_render_of_the_preset_within_noise(session):
    report, folder, output = session
    assert report["picture"] == [["FINISHED"], None] and report["picture_material"] == "matfit"
    assert f"picture saved to {folder / 'pictures' / 'picture.png'}" in output
    picture = images.read(str(folder / "pictures" / "picture.png"))
    # the parameters it rendered, beside it: the preset's within 1e-3 (matfit's defaults where the export carries none)
    source = params.read_file(str(folder / "pictures" / "picture.source.json"))
    imported = report["imports"][PICTURE_PRESET]
    assert_round_trip(presets.preset(PICTURE_PRESET), source, imported["missing"])
    renders = {}
    for preset, seed in ((PICTURE_PRESET, 0), (PICTURE_PRESET, 1), ("milk", 0)):
        out = str(folder / f"{preset}-{seed}.png")
        matfit("render", "--preset", preset, "--seed", str(seed), "--size", str(SIZE), "--spp", str(SPP), "-o", out,
               folder=folder)  # fmt: skip
        renders[preset, seed] = images.read(out)
    noise = float(images.rmse(renders[PICTURE_PRESET, 1], renders[PICTURE_PRESET, 0]))
    assert float(images.rmse(picture, renders[PICTURE_PRESET, 0])) <= noise
    # and the check can fail: another preset is further away than the noise
    assert float(images.rmse(picture, renders["milk", 0])) > 2 * noise


@pytest.mark.parametrize("kind", REFUSALS)
def test_a_material_matfit_cannot_represent_gets_one_line(session, kind):
    report, folder, output = session
    outcome, line = report["refusals"][kind]
    assert "Traceback" not in output
    if kind == "texture":  # read at the socket's own value, and said so in the report line
        assert outcome == ["FINISHED"]
        lines = [text for text in output.splitlines() if "Image Texture" in text]
        assert lines == [
            f"Warning: matfit: picture saved to {folder / 'pictures' / 'picture.png.texture.png'}; not mapped: "
            "Base Color (Image Texture) "
            "read at their unlinked values, distribution MULTI_GGX shown as GGX"
        ]
    else:
        label = {"glass": "Glass BSDF", "emission": "Emission"}[kind]
        assert outcome == ["CANCELLED"] and "\n" not in line
        assert line == (
            f"Error: matfit: material '{kind}': its Surface is {label}, which matfit cannot represent; "
            "use a Principled BSDF there (for glass: Transmission Weight 1)"
        )


def test_a_missing_or_failing_matfit_shows_its_error_line(session):
    report, folder, _ = session
    missing, failing, _ = report["failures"]
    assert missing == [
        ["CANCELLED"],
        f"Error: matfit: cannot run '{folder / 'no-such-matfit'}' (No such file or directory): "
        "set its path in Edit > Preferences > Add-ons > matfit",
    ]
    assert failing[0] == ["CANCELLED"] and "\n" not in failing[1]
    assert failing[1].startswith(f"Error: matfit ({folder / 'matfit'}) failed: error: ")
    assert "not-a-picture.png" in failing[1]


def test_fit_puts_the_values_matfit_fit_writes_on_the_selected_objects_only(session):
    report, folder, output = session
    assert report["fit"] == [["FINISHED"], None]
    assert report["slots"] == {
        "source": [["OBJECT", "matfit"]],
        "bare": [["OBJECT", "matfit"]],
        "shared_a": [["OBJECT", "matfit"]],
        "shared_b": [["DATA", "keep"]],
    }
    assert report["shared_mesh_materials"] == ["keep"]
    # the same fit from the command line, with the settings the extension passed
    reference = str(folder / "reference.json")
    matfit("fit", EDITED, "-o", reference, "--size", str(SIZE), "--spp", str(SPP), *FIT_OPTIONS, folder=folder)
    document = json.loads(open_bytes(reference))
    assert_material_is(report["fitted"], reference)
    line = (
        f"Info: matfit: material 'matfit' on 3 selected mesh(es), neural RMSE {document['neural_rmse']:.2f}, "
        f"Mitsuba RMSE {document['mitsuba_rmse']:.2f}"
    )
    assert line in output.splitlines()
    np.testing.assert_allclose(
        params.read_file(str(folder / "edited.params.json")), params.read_file(reference), atol=1e-6
    )


def test_fit_from_the_panel_is_one_undo_step(session):
    report = session[0]
    undone, before = report["fit_undone"]
    assert before["matfit"] is None and report["fitted"] is not None
    assert undone == before  # no material "matfit", every slot as it was
    assert report["fit_redone"] == report["fitted"]


def test_fit_shows_the_neural_answer_at_once_then_puts_the_final_one_in_its_place(session):
    report, folder, _ = session
    stages = report["stages"]
    assert next(iter(stages["shown"])) == "neural"
    neural = stages["shown"]["neural"]
    # at once, while the fit runs: the neural answer's material on the selected meshes, said not yet checked
    assert re.fullmatch(
        r"matfit fit running for \d+ s: in matfit's worker; the neural answer shown, not yet checked in Mitsuba",
        neural["status"],
    )
    shown = {"source": [["OBJECT", PREVIEW]], "bare": [["OBJECT", PREVIEW]], "shared_a": [["OBJECT", PREVIEW]]}
    assert neural["state"]["slots"] == {**shown, "shared_b": [["DATA", "keep"]]}
    assert neural["state"]["matfit"]["nodes"] == stages["before"]["matfit"]["nodes"]  # the earlier material untouched
    answer = folder / "neural.json"
    answer.write_text(json.dumps(neural["document"]))
    assert_material_is(neural["preview"], answer)
    # then the final answer, the params.json the job wrote, in its place; the neural answer's material gone
    final = json.loads(open_bytes(folder / "stages.params.json"))
    assert final["params"] != neural["document"]["params"]  # verification changed it: the two checks differ
    assert_material_is(stages["after"]["matfit"], folder / "stages.params.json")
    assert stages["after"]["slots"] == stages["before"]["slots"]  # "matfit" on the selected meshes, as before
    assert stages["after"]["materials"] == stages["before"]["materials"] == ["keep", "matfit"]
    assert stages["line"] == (
        f"matfit: material 'matfit' on 3 selected mesh(es), neural RMSE {final['neural_rmse']:.2f}, "
        f"Mitsuba RMSE {final['mitsuba_rmse']:.2f}"
    )


@pytest.mark.parametrize("end", ["cancelled", "failed"])
def test_a_fit_that_ends_without_its_answer_after_the_neural_one_puts_back_the_materials_the_meshes_had(session, end):
    report, folder, _ = session
    ended = report["stages"][end]
    shown = ended["shown"]["neural"]["state"]
    assert shown["slots"] == {
        "source": [["OBJECT", PREVIEW]],
        "bare": [["OBJECT", PREVIEW]],  # a slot added to its mesh
        "shared_a": [["OBJECT", PREVIEW]],
        "shared_b": [["DATA", "keep"]],
    }
    assert ended["before"]["slots"] == {
        "source": [],
        "bare": [],
        "shared_a": [["DATA", "keep"]],
        "shared_b": [["DATA", "keep"]],
    }
    assert ended["after"] == ended["before"]  # the slots, the links and every material, PREVIEW gone
    if end == "failed":
        answer = folder / "fails-late.json"
        answer.write_text(json.dumps(WRITTEN))
        assert_material_is(ended["shown"]["neural"]["preview"], answer)
        assert (
            ended["line"] == f"matfit ({folder / 'fails late'}) failed: error: the fit failed after its neural answer"
        )


def test_follow_refits_when_the_picture_is_saved(session):
    report, folder, _ = session
    assert report["follow_idle"] == [None, "matfit follows follow.png: waiting for the picture to change (Esc stops)"]
    document = json.loads(open_bytes(folder / "follow.params.json"))
    assert report["follow"] == (
        f"matfit: material 'matfit' on 3 selected mesh(es), neural RMSE {document['neural_rmse']:.2f}, "
        f"Mitsuba RMSE {document['mitsuba_rmse']:.2f}"
    )
    # the saved picture (desaturated copper) was fitted, not the one Follow started with (recoloured plastic)
    followed = params.read_file(str(folder / "follow.params.json"))
    metallic = params.INDEX["metallic"]
    assert followed[metallic] > 0.5 > params.read_file(str(folder / "edited.params.json"))[metallic]
    assert_material_is(report["follow_fitted"], folder / "follow.params.json")
    # its neural answer shown first, the whole fit one undo step
    assert report["follow_shown"][0] == "neural"
    undone, before = report["follow_undone"]
    assert undone == before and before["matfit"] is None
    assert report["follow_redone"] == report["follow_fitted"]


def test_esc_stops_a_running_fit_at_once(session):
    cancel = session[0]["cancel"]
    assert re.fullmatch(r"matfit fit running for \d+ s(: .*)?", cancel["status"])
    assert cancel["code"] != 0 and cancel["seconds"] < 5


def test_a_matfit_command_whose_path_has_a_space_runs(session):
    report, folder, _ = session
    outcome, line = report["failures"][2]
    # it ran: the error is matfit's own, about the picture, not "No such file or directory" for ".../my"
    assert outcome == ["CANCELLED"] and line.startswith(
        f"Error: matfit ({folder / 'my dir' / 'matfit'}) failed: error: "
    )
    assert "not-a-picture.png" in line


@pytest.mark.parametrize("where", ["gif", "proc", "proc-folder"])
def test_a_picture_the_extension_cannot_write_is_one_line_and_leaves_nothing(session, where):
    report, folder, output = session
    path = {
        "gif": str(folder / "pictures" / "refused.gif"),
        "proc": "/proc/picture.png",
        "proc-folder": "/proc/matfit/picture.png",
    }[where]
    outcome, line = report["unwritable"][path]
    assert outcome == ["CANCELLED"] and "\n" not in line and "Traceback" not in output
    if where == "gif":  # matfit's own refusal; the parameters were not left beside it
        assert line.startswith(f"Error: matfit ({folder / 'matfit'}) failed: error: cannot write {path}: ")
        assert not (folder / "pictures" / "refused.source.json").exists()
    else:
        assert line.startswith(f"Error: matfit: cannot write the picture {path} (")
        assert line.endswith("): choose a folder you can write to in the panel's Picture")


def test_a_script_beside_the_picture_is_never_run(session):
    _, folder, _ = session
    # neither by a matfit that wrote nothing, nor by a fit that redirected its outputs, nor by a fit that succeeded
    assert not (folder / "executed").exists()
    assert (folder / "planted.blender.py").read_text().startswith("open(")


def test_a_matfit_that_writes_nothing_is_one_line_and_leaves_the_material_as_it_was(session):
    report, folder, _ = session
    planted = report["planted"]
    assert planted["silent"] == [
        ["CANCELLED"],
        f"Error: matfit ({folder / 'silent'}) ended without writing the fit's params.json: the material is "
        "unchanged; set the matfit command to matfit's own executable in Edit > Preferences > Add-ons > matfit",
    ]
    assert planted["before"] is not None and planted["after_silent"] == planted["before"]


@pytest.mark.parametrize("kind", list(WRITERS))
def test_a_matfit_that_writes_no_params_json_of_its_own_is_one_line_and_changes_nothing(session, kind):
    report, folder, output = session
    planted = report["planted"]
    outcome, line = planted["writers"][kind]
    expected = {
        "not JSON": "the fit's params.json is not valid JSON (",
        "NaN": "the fit's params.json is not valid JSON (NaN is not a number JSON allows)",
        "out of range": "the fit's params.json gives roughness = 7, outside [0, 1]",
        "unknown name": "the fit's params.json names 'roughnes', which is not one of matfit's parameters",
        "no params": 'the fit\'s params.json holds no "params" object',
        "too large": f"matfit ({folder / 'writes too large'}) wrote a params.json of more than 1024 KB",
        "a FIFO": f"matfit ({folder / 'writes a FIFO'}) wrote something other than a file as the fit's params.json",
        "a link": f"matfit ({folder / 'writes a link'}) wrote a link as the fit's params.json",
    }[kind]
    assert outcome == ["CANCELLED"] and "\n" not in line and "Traceback" not in output
    assert expected in line and line.startswith("Error: matfit")
    assert line.endswith("set the matfit command to matfit's own executable in Edit > Preferences > Add-ons > matfit")
    assert planted["after_writers"] == planted["before"]


def test_a_params_json_that_cannot_be_kept_beside_the_picture_is_said_and_the_material_is_still_applied(session):
    report, folder, output = session
    assert report["planted"]["blocked"] == [["FINISHED"], None]
    line = "Info: matfit: material 'matfit' on 3 selected mesh(es), neural RMSE 1.50, "
    assert line + "blocked.params.json not saved (Is a directory)" in output.splitlines()
    written = folder / "written.json"
    written.write_text(json.dumps(WRITTEN))
    assert_material_is(report["planted"]["after_blocked"], written)  # matfit's defaults where it names none
    assert (folder / "blocked.params.json").is_dir() and not list((folder / "blocked.params.json").iterdir())
    assert not [path.name for path in folder.iterdir() if path.name.startswith(".matfit-")]


def test_fit_options_that_redirect_the_outputs_are_refused_and_apply_nothing(session):
    report, folder, _ = session
    planted = report["planted"]
    assert planted["redirect"] == [
        ["CANCELLED"],
        "Error: matfit: the Fit options name an output (-o): remove it from the extension's preferences; "
        "the fit's params.json is saved beside the picture as planted.params.json",
    ]
    assert planted["after_redirect"] == planted["before"]
    assert not (folder / "x.json").exists() and not (folder / "x.py").exists()


def test_fit_applies_exactly_to_blender_of_the_params_json_its_own_job_wrote(session):
    report, folder, output = session
    planted = report["planted"]
    assert planted["fit"] == [["FINISHED"], None]
    # the job's params.json, saved beside the picture over the stale one
    document = json.loads(open_bytes(folder / "planted.params.json"))
    assert document["neural_rmse"] != STALE["neural_rmse"]
    assert_material_is(planted["fitted"], folder / "planted.params.json")
    # a fit of jade's picture keeps a medium: the volume nodes are compared too
    principled, volume = export.blender_inputs(params.read_file(str(folder / "planted.params.json")))
    assert blender_mapping.has_volume(principled, volume)
    line = (
        f"Info: matfit: material 'matfit' on 3 selected mesh(es), neural RMSE {document['neural_rmse']:.2f}, "
        f"Mitsuba RMSE {document['mitsuba_rmse']:.2f}"
    )
    assert line in output.splitlines()


def test_a_second_fit_runs_in_the_same_worker_and_a_killed_worker_is_started_again(session):
    report, folder, _ = session
    again, killed = report["worker"]["again"], report["worker"]["killed"]
    # the second Fit was sent to the worker the first started (the model and Mitsuba loaded), with the same answer
    assert again["outcome"] == [["FINISHED"], None] and again["same_worker"]
    assert again["fitted"] == report["fitted"]
    # a worker killed between two fits: the next Fit starts another and succeeds, with the same answer
    assert killed["outcome"] == [["FINISHED"], None] and killed["new_worker"]
    assert killed["fitted"] == report["fitted"]
    assert_material_is(killed["fitted"], folder / "edited.params.json")


def test_a_worker_that_ends_during_every_fit_is_started_again_once_then_one_line(session):
    report, folder, output = session
    planted = report["planted"]
    assert planted["crashes"] == [
        ["CANCELLED"],
        f"Error: matfit ({folder / 'crashes'}) failed: error: its worker ended during the fit, twice (exit code 3): "
        "RuntimeError: the worker crashed",
    ]
    assert planted["crashes_unchanged"] and "Traceback" not in output
    assert (folder / "crashes.count").read_text().split() == ["started", "started"]


def test_a_worker_that_never_answers_is_given_up_after_what_the_fit_can_take_in_one_line(session):
    # `bpy.ops.matfit.fit()` (a script, headless) waited 3600 s for it
    report, folder, output = session
    planted = report["planted"]
    assert planted["mute"] == [
        ["CANCELLED"],
        f"Error: matfit ({folder / 'mute'}) failed: error: its worker gave no answer in {MUTE_SECONDS:.0f} s, the most "
        "this fit may take: it was ended, and the next fit starts a new one",
    ]
    assert MUTE_SECONDS <= planted["mute_seconds"] < MUTE_SECONDS + 30
    assert planted["mute_unchanged"] and "Traceback" not in output


def test_a_command_without_a_worker_runs_each_fit_as_its_own_process_said_once(session):
    _, folder, output = session
    # the "matfit" commands that write a file (and know no `matfit worker`) fitted as before, and said so once each
    for command in (folder / "silent", folder / "writes params.json"):
        note = f"Info: matfit: '{command}' has no `matfit worker` (an older matfit?): each fit starts matfit"
        assert output.splitlines().count(note) == 1
