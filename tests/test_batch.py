"""Several pictures of one command (`matfit/fitting/batch.py`): a plan refuses, before any work, an output that would
lose a file (another picture, another picture's output, a file the user keeps in the folder), and the journal keeps
a picture only when its params.json is matfit's of that very picture."""

from __future__ import annotations

import json
import os
import shutil

import pytest

from matfit import files, shipped
from matfit.errors import OutputError
from matfit.fitting import batch
from matfit.fitting.methods import Settings
from matfit.fitting.request import Outputs, Request

PICTURE = shipped.EXAMPLES / "recoloured.png"
OTHER = shipped.EXAMPLES / "desaturated.png"


def request(**outputs: str) -> Request:
    """Returns the request every picture of a plan is made from: `--method nn --no-verify`, the outputs named."""
    return Request("", settings=Settings("nn"), verified=False, outputs=Outputs("params.json", **outputs))


def listing(folder) -> dict[str, bytes]:
    return {name: (folder / name).read_bytes() for name in sorted(os.listdir(folder))}


def matfit_params(target: str, **fields: object) -> str:
    """Returns a params.json as matfit writes one for the picture `target` (the fields that decide whether it is)."""
    document = {
        "params": {"roughness": 0.2},
        "units": {"roughness": ""},
        "method": "nn",
        "box": "clip",
        "polish_steps": 0,
        "model": "matfit/data/model",
        "target": target,
        "target_sha256": files.sha256(target) if os.path.isfile(target) else "0" * 64,
        "mask": None,
        "init": None,
    }
    return json.dumps({**document, **fields})


def test_an_output_of_one_picture_that_is_another_picture_is_refused_before_any_work(tmp_path):
    # `matfit fit d/a.png d/a.report.png -o d --report report.png`: a's report is the second picture
    shutil.copy(PICTURE, tmp_path / "a.png")
    shutil.copy(OTHER, tmp_path / "a.report.png")
    before = listing(tmp_path)
    pictures = [str(tmp_path / "a.png"), str(tmp_path / "a.report.png")]
    with pytest.raises(OutputError, match=r"report .*a\.report\.png is the target .*a\.report\.png: writing it would"):
        batch.plan(pictures, str(tmp_path), request(report="report.png"))
    assert listing(tmp_path) == before
    # two pictures' outputs that are one file: a's b.c.png report and a.b's c.png render
    shutil.copy(OTHER, tmp_path / "a.b.png")
    pictures = [str(tmp_path / "a.png"), str(tmp_path / "a.b.png")]
    with pytest.raises(OutputError, match=r"report .*a\.b\.c\.png and render .*a\.b\.c\.png are the same file"):
        batch.plan(pictures, str(tmp_path / "out"), request(report="b.c.png", render="c.png"))
    assert not (tmp_path / "out").exists()


def test_a_file_the_user_keeps_under_a_name_of_the_plan_is_refused_and_matfits_own_is_replaced(tmp_path):
    for name in ("p0.png", "p1.png"):
        shutil.copy(PICTURE, tmp_path / name)
    pictures, out = [str(tmp_path / "p0.png"), str(tmp_path / "p1.png")], tmp_path / "out"
    out.mkdir()

    def refused(name: str, content: str, *fragments: str, **outputs: str) -> None:
        (out / name).write_text(content)
        with pytest.raises(OutputError) as error:
            batch.plan(pictures, str(out), request(**outputs))
        assert (out / name).read_text() == content
        for fragment in (str(out / name), "matfit did not write it", *fragments):
            assert fragment in str(error.value)
        (out / name).unlink()

    refused("p0.params.json", "notes", "no params.json that matfit wrote for a picture named p0")
    refused("p0.params.json", '{"params": {"roughness": 0.2}}', "no params.json that matfit wrote")
    refused("p0.params.json", matfit_params(pictures[1]), "for a picture named p0")  # p1's, by another name
    refused("p1.report.png", "a picture", f"{out / 'p1.params.json'} is not there", report="report.png")
    (out / "p1.report.png").write_text("a picture")
    refused("p1.params.json", "notes", "for a picture named p1", report="report.png")  # named first
    (out / "p1.report.png").unlink()
    # matfit's own: its params.json of the picture, and the outputs written beside it, are replaced
    (out / "p1.params.json").write_text(matfit_params(pictures[1]))
    (out / "p1.report.png").write_text("the report matfit wrote")
    (out / "p0.params.json").write_text(matfit_params(str(tmp_path / "elsewhere" / "p0.png")))
    assert len(batch.plan(pictures, str(out), request(report="report.png"))) == 2


@pytest.mark.parametrize("kind", ["folder", "fifo"])
def test_a_journal_that_is_no_file_is_refused_before_any_work(tmp_path, kind):
    shutil.copy(PICTURE, tmp_path / "p0.png")
    shutil.copy(OTHER, tmp_path / "p1.png")
    out = tmp_path / "out"
    out.mkdir()
    journal = out / batch.JOURNAL
    journal.mkdir() if kind == "folder" else os.mkfifo(journal)
    called = []
    with pytest.raises(OutputError, match=rf"{batch.JOURNAL} is a (folder|FIFO).*journal of the pictures fitted"):
        batch.plan(
            [str(tmp_path / "p0.png"), str(tmp_path / "p1.png")],
            str(out),
            request(),
            then=lambda: called.append("model loaded"),
        )
    assert os.listdir(out) == [batch.JOURNAL] and not called


def scene_params(target: str, **fields: object) -> str:
    """Returns a params.json as matfit writes one for `target` fitted in a scene: no model, box or polish steps."""
    document = json.loads(matfit_params(target, **fields))
    return json.dumps({name: value for name, value in document.items() if name not in ("model", "box", "polish_steps")})


def test_the_journal_keeps_a_picture_only_when_its_params_json_is_matfits_of_that_picture(tmp_path):
    shutil.copy(PICTURE, tmp_path / "p0.png")
    out = tmp_path / "out"
    out.mkdir()
    (fitted,) = batch.plan([str(tmp_path / "p0.png")], str(out), request(report="report.png"))
    model = str(shipped.MODEL)
    journal = batch.Journal(str(out), "key", model)
    journal.record(fitted, files.sha256(str(tmp_path / "p0.png")))
    journal = batch.Journal(str(out), "key", model)  # read back, as a rerun does
    (out / "p0.report.png").write_text("the report")
    target, params_json = str(tmp_path / "p0.png"), out / "p0.params.json"
    model_shown = matfit_params(target, model="matfit/data/model")
    params_json.write_text(model_shown)
    assert journal.fitted(fitted)
    for planted in (
        "notes",  # any file by that name
        matfit_params(target, target_sha256="0" * 64),  # of another picture by that name
        matfit_params(target, method="hybrid"),  # of other settings
        matfit_params(target, mask="mask.png"),
        matfit_params(str(OTHER)),
        matfit_params(target, model="another-model"),
    ):
        params_json.write_text(planted)
        assert not journal.fitted(fitted), planted
    params_json.write_text(model_shown)
    (out / "p0.report.png").unlink()
    assert not journal.fitted(fitted)  # an output missing


def test_in_a_scene_the_journal_keeps_a_picture_fitted_in_that_scenes_shape_and_its_key_holds_the_meshes(tmp_path):
    shutil.copy(PICTURE, tmp_path / "p0.png")
    out = tmp_path / "out"
    out.mkdir()
    (fitted,) = batch.plan([str(tmp_path / "p0.png")], str(out), request())
    scene = {"path": "/s/scene.xml", "object": "knot", "sha256": "a" * 64, "files": {"/s/knot.ply": "b" * 64}}
    model = str(shipped.MODEL)
    key = batch.journal_key([fitted], model, scene)
    assert key != batch.journal_key([fitted], model)  # a scene fit is not the test scene's
    mesh_changed = {**scene, "files": {"/s/knot.ply": "c" * 64}}
    assert key != batch.journal_key([fitted], model, mesh_changed)
    journal = batch.Journal(str(out), key, model, scene)
    journal.record(fitted, files.sha256(str(tmp_path / "p0.png")))
    journal = batch.Journal(str(out), key, model, scene)
    target, params_json = str(tmp_path / "p0.png"), out / "p0.params.json"
    shape = {**{name: scene[name] for name in ("path", "object", "sha256")}, "camera": [32, 24]}
    scene_fit = {"method": "scene", "scene": shape}
    params_json.write_text(scene_params(target, **scene_fit))
    assert journal.fitted(fitted)
    for planted in (
        matfit_params(target),  # the test scene's fit of that picture
        scene_params(target, **{**scene_fit, "scene": {**shape, "object": "floor"}}),  # another shape's
        scene_params(target, **{**scene_fit, "scene": {**shape, "sha256": "d" * 64}}),  # another scene file's
        scene_params(target, **{**scene_fit, "mask": "mask.png"}),
    ):
        params_json.write_text(planted)
        assert not journal.fitted(fitted), planted
