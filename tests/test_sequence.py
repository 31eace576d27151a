import json
import os

import numpy as np
import pytest
from helpers import decode, random_model, true_point

from matfit import files, images, params
from matfit.errors import ImageError, OutputError
from matfit.fitting import fitfile, search, sequence
from matfit.fitting.request import Outputs, Request
from matfit.fitting.sequence import SequenceError


@pytest.fixture(scope="module")
def model():
    return random_model()


def test_natural_order(tmp_path):
    for name in ("frame_10.png", "frame_2.png", "frame_1.png", "notes.txt", "Frame_3.PNG"):
        (tmp_path / name).write_bytes(b"")
    assert [p.split("/")[-1] for p in sequence.list_frames(str(tmp_path))] == [
        "frame_1.png",
        "frame_2.png",
        "Frame_3.PNG",
        "frame_10.png",
    ]


def test_empty_or_missing_folder(tmp_path):
    with pytest.raises(SequenceError, match="holds no frames"):
        sequence.list_frames(str(tmp_path))
    with pytest.raises(SequenceError, match="is not a folder"):
        sequence.list_frames(str(tmp_path / "none"))


@pytest.fixture
def frames(tmp_path, model):
    directory = tmp_path / "frames"
    directory.mkdir()
    base = decode(model, true_point(11))
    for k in range(4):
        images.write(str(directory / f"f{k}.png"), images.srgb_decode(np.clip(base * (1 - 0.05 * k), 0, 1)))
    return sequence.list_frames(str(directory))


def test_reinit_pool_holds_the_previous_optimum_and_resume_matches(tmp_path, model, frames, monkeypatch):
    settings = search.Settings(method="hybrid", evaluations=40)
    whole = sequence.fit_sequence(model, frames, out=str(tmp_path / "whole"), settings=settings)
    assert len(whole) == 4
    seen = []
    original = fitfile.fit_neural

    def spy(request, model_):  # every frame is fitted through one Request on the fit path
        result = original(request, model_)
        seen.append((request.candidates, result.candidate_rmse))
        assert request.target in frames and request.pixels.shape == (model.resolution, model.resolution, 3)
        assert not request.verified and request.outputs is None and request.settings == settings
        return result

    with monkeypatch.context() as patch:
        patch.setattr(fitfile, "fit_neural", spy)
        partial = sequence.fit_sequence(model, frames[:2], out=str(tmp_path / "parts"), settings=settings)
        resumed = sequence.fit_sequence(model, frames, out=str(tmp_path / "parts"), settings=settings)
    assert seen[0][0] is None and "extra-1" not in seen[0][1]
    np.testing.assert_array_equal(seen[1][0][0], partial[0].unit)  # the previous optimum is a candidate
    assert "extra-1" in seen[1][1]
    assert len(seen) == 4  # the resumed run fitted only frames 3 and 4
    np.testing.assert_array_equal(seen[2][0][0], partial[1].unit.astype(np.float32))
    for a, b in zip(whole, resumed, strict=True):
        np.testing.assert_allclose(a.unit, b.unit, atol=1e-6)
        assert a.rmse == pytest.approx(b.rmse, abs=1e-4)
    document = json.loads((tmp_path / "parts" / "f3.json").read_text())
    assert document["sequence"]["index"] == 3 and document["sequence"]["settings"]["reinit"] is True


def test_a_frame_request_fits_as_the_direct_search_and_a_bad_one_is_refused(tmp_path, model, frames):
    """A frame's Request (the frame as read, the previous optimum a candidate) gives what neural_search gives."""
    settings = search.Settings(method="hybrid", evaluations=40)
    target = sequence.load_frame(frames[1], model.resolution)
    previous = search.neural_search(model, sequence.load_frame(frames[0], model.resolution), settings=settings).unit
    candidates = previous.astype(np.float32)[None]
    direct = search.neural_search(model, target, settings=settings, extra=candidates)
    frame = dict(settings=settings, verified=False, answer="best", candidates=candidates)
    read = fitfile.fit_neural(Request(frames[1], pixels=target, **frame), model)
    from_file = fitfile.fit_neural(Request(frames[1], **frame), model)  # the same picture, read from its file
    for result in (read, from_file):
        np.testing.assert_array_equal(result.unit, direct.unit)
        assert (result.rmse, result.chosen, result.evaluations) == (direct.rmse, direct.chosen, direct.evaluations)
    assert "extra-1" in read.candidate_rmse  # the previous optimum was among the candidates
    # The source material's physical values come first, the unit-cube candidates after them, unconverted.
    init = params.from_unit(np.full(params.COUNT, 0.25))
    both = Request(frames[1], init_values=init, **frame).extra_candidates()
    np.testing.assert_array_equal(both[1], candidates[0])
    np.testing.assert_allclose(both[0], 0.25, atol=1e-12)
    # A mask weighs the picture as read just as it weighs the one read from its file.
    mask = str(tmp_path / "mask.png")
    images.write(mask, np.tile(np.linspace(0, 1, 32, dtype=np.float32)[None, :, None], (32, 1, 3)))
    masked = [
        fitfile.fit_neural(Request(frames[1], mask=mask, pixels=pixels, **frame), model) for pixels in (target, None)
    ]
    np.testing.assert_array_equal(masked[0].unit, masked[1].unit)
    assert masked[0].rmse != read.rmse
    with pytest.raises(ValueError, match="not verification, the clean answer: call fit_file"):
        fitfile.fit_neural(Request(frames[1], pixels=target), model)
    with pytest.raises(ValueError, match="not refinement, outputs"):
        fitfile.fit_neural(
            Request(frames[1], refine_steps=2, outputs=Outputs(str(tmp_path / "p.json")), **frame), model
        )
    with pytest.raises(ImageError, match=r"target .*gone\.png is not a file"):  # no pixels: its file is read
        fitfile.fit_neural(Request(str(tmp_path / "gone.png"), **frame), model)
    # pixels given are the picture: the name is only a label, as for an array fitted through the API
    named = fitfile.fit_neural(Request(str(tmp_path / "gone.png"), pixels=target, **frame), model)
    np.testing.assert_array_equal(named.unit, direct.unit)


def test_no_reinit_never_offers_the_previous_frame(tmp_path, model, frames):
    results = sequence.fit_sequence(
        model, frames, out=str(tmp_path), settings=search.Settings(method="hybrid", evaluations=30), reinit=False
    )
    assert all(frame.start != sequence.PREVIOUS for frame in results)


def test_mixed_sizes_and_other_settings_are_refused(tmp_path, model, frames):
    images.write(str(tmp_path / "frames" / "f9.png"), np.zeros((20, 20, 3), np.float32))
    with pytest.raises(SequenceError, match=r"f9\.png is 20x20, the first frame is 32x32"):
        sequence.fit_sequence(
            model,
            sequence.list_frames(str(tmp_path / "frames")),
            out=str(tmp_path / "out"),
            settings=search.Settings(method="hybrid", evaluations=30),
        )
    assert not (tmp_path / "out").exists()  # refused before fitting anything
    sequence.fit_sequence(
        model, frames[:1], out=str(tmp_path / "out"), settings=search.Settings(method="hybrid", evaluations=30)
    )
    with pytest.raises(SequenceError, match="other settings"):
        sequence.fit_sequence(
            model, frames, out=str(tmp_path / "out"), settings=search.Settings(method="hybrid", evaluations=31)
        )


def test_summary_table_sums():
    frames = [sequence.Frame(f"f{k}.png", np.zeros(19), 1.5 * k, "encoder-1", 2.0, 100, 0.1) for k in range(3)]
    table = sequence.summary_table(frames)
    assert "| f2.png | encoder-1 | 2.00 | 3.00 | 100 | 0.100 |" in table
    assert "| sum | | | 4.50 | 300 | 0.30 |" in table


def test_a_changed_frame_and_the_frames_after_it_are_fitted_again(tmp_path, model, frames):
    settings = search.Settings(method="hybrid", evaluations=40)
    first = sequence.fit_sequence(model, frames, out=str(tmp_path / "out"), settings=settings)
    again = sequence.fit_sequence(model, frames, out=str(tmp_path / "out"), settings=settings)
    assert [frame.note for frame in again] == [None] * 4 and all(frame.image is None for frame in again)  # all reused
    changed = images.srgb_decode(np.clip(decode(model, true_point(12)), 0, 1))
    images.write(frames[2], changed)  # the artist edits frame 2 again
    resumed = sequence.fit_sequence(model, frames, out=str(tmp_path / "out"), settings=settings)
    assert [frame.image is not None for frame in resumed] == [False, False, True, True]
    assert "the picture is not the one" in resumed[2].note and "previous frame's result changed" in resumed[3].note
    whole = sequence.fit_sequence(model, frames, out=str(tmp_path / "whole"), settings=settings)
    for a, b in zip(whole, resumed, strict=True):
        np.testing.assert_allclose(a.unit, b.unit, atol=1e-6)
    assert np.abs(resumed[2].unit - first[2].unit).max() > 1e-3  # the new result is the new picture's
    document = json.loads((tmp_path / "out" / "f2.json").read_text())
    assert document["sequence"]["frame_sha256"] == files.sha256(frames[2])
    assert document["sequence"]["settings"]["model"] == model.identity()  # what the weights are, not where they lie


def test_another_folder_with_the_same_names_is_fitted_again(tmp_path, model, frames):
    settings = search.Settings(method="hybrid", evaluations=30)
    sequence.fit_sequence(model, frames[:2], out=str(tmp_path / "out"), settings=settings)
    other = tmp_path / "other"
    other.mkdir()
    for k, name in enumerate(("f0.png", "f1.png")):
        images.write(str(other / name), images.srgb_decode(np.clip(decode(model, true_point(20 + k)), 0, 1)))
    results = sequence.fit_sequence(
        model, sequence.list_frames(str(other)), out=str(tmp_path / "out"), settings=settings
    )
    assert all(frame.image is not None and frame.note for frame in results)


def test_another_model_is_refused_and_a_failed_first_frame_leaves_no_folder(tmp_path, model, frames, monkeypatch):
    settings = search.Settings(method="hybrid", evaluations=30)
    sequence.fit_sequence(model, frames[:1], out=str(tmp_path / "out"), settings=settings)
    with pytest.raises(SequenceError, match="another model"):
        sequence.fit_sequence(random_model(seed=1), frames[:1], out=str(tmp_path / "out"), settings=settings)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(search, "neural_search", interrupted)
    with pytest.raises(KeyboardInterrupt):
        sequence.fit_sequence(model, frames, out=str(tmp_path / "new"), settings=settings)
    assert not (tmp_path / "new").exists()


def test_a_finished_frame_nested_too_deeply_is_one_line_naming_it(tmp_path):
    (tmp_path / "f1.json").write_text("[" * 100000)
    with pytest.raises(SequenceError, match=r"f1\.json is not valid JSON \(nested too deeply.*delete it to fit that"):
        sequence.read_finished(str(tmp_path / "f1.json"), {})


def test_two_frames_with_one_result_name_are_refused_before_any_fit(tmp_path, model, frames, monkeypatch):
    folder = tmp_path / "frames"
    images.write(str(folder / "f1.jpg"), images.srgb_decode(np.clip(decode(model, true_point(5)), 0, 1)))
    monkeypatch.setattr(search, "neural_search", None)  # a fit would fail: the refusal comes first
    settings = search.Settings(method="hybrid", evaluations=30)
    with pytest.raises(SequenceError, match=r"frames .*f1\.(jpg|png) and .*f1\.(png|jpg) would both write .* f1\.json"):
        sequence.run(model, str(folder), out=str(tmp_path / "out"), settings=settings)
    with pytest.raises(SequenceError, match="would both write"):
        sequence.fit_sequence(model, sequence.list_frames(str(folder)), out=str(tmp_path / "out"), settings=settings)
    assert not (tmp_path / "out").exists()


def test_outputs_that_are_frames_or_a_read_only_folder_are_refused(tmp_path, model, frames, monkeypatch):
    folder = tmp_path / "frames"
    monkeypatch.setattr(search, "neural_search", None)
    settings = search.Settings(method="hybrid", evaluations=30)
    images.write(str(folder / "preview.png"), images.srgb_decode(np.clip(decode(model, true_point(5)), 0, 1)))
    with pytest.raises(OutputError, match=r"preview .*preview\.png is the frame .*choose another out folder"):
        sequence.run(model, str(folder), out=str(folder), settings=settings)  # the results beside the frames
    with pytest.raises(OutputError, match=r"out /proc/seq cannot be written: /proc is read-only"):
        sequence.run(model, str(folder), out="/proc/seq", settings=settings)
    (folder / "preview.png").unlink()  # the first run into the frames' folder: its preview.png would be a frame
    with pytest.raises(OutputError, match=r"out .*frames is the folder of the frames: its preview\.png .* would be"):
        sequence.run(model, str(folder), out=str(folder), settings=settings)
    assert sorted(os.listdir(folder)) == [f"f{k}.png" for k in range(4)]  # nothing written


def test_a_render_is_made_again_whenever_its_frame_was_fitted_again(tmp_path, model, frames):
    """Frame 2 edited, the run interrupted once its result and frame 3's were rewritten: a resumed run renders both."""
    settings, out = search.Settings(method="hybrid", evaluations=40), tmp_path / "out"
    sequence.run(model, str(tmp_path / "frames"), out=str(out), settings=settings, render=(16, 2))
    renders = [out / f"f{k}-render.png" for k in range(4)]
    before = [(path.stat().st_ino, path.read_bytes()) for path in renders]
    document = json.loads((out / "f2.json").read_text())
    assert document["sequence"]["render"] == {"size": 16, "spp": 2, "sha256": files.sha256(str(renders[2]))}
    images.write(frames[2], images.srgb_decode(np.clip(decode(model, true_point(12)), 0, 1)))
    sequence.fit_sequence(
        model, frames, out=str(out), settings=settings
    )  # what a run stopped before its renders leaves
    resumed = sequence.run(model, str(tmp_path / "frames"), out=str(out), settings=settings, render=(16, 2))
    assert all(frame.image is None for frame in resumed)  # every result read back: nothing fitted in this run
    after = [(path.stat().st_ino, path.read_bytes()) for path in renders]
    assert after[:2] == before[:2]  # frames 0 and 1 kept their results, and their renders
    assert after[2][1] != before[2][1] and after[3][1] != before[3][1]  # renders of the new results
    for k in (2, 3):
        recorded = json.loads((out / f"f{k}.json").read_text())["sequence"]["render"]["sha256"]
        assert recorded == files.sha256(str(renders[k]))
    sequence.run(
        model, str(tmp_path / "frames"), out=str(out), settings=settings, render=(20, 2)
    )  # other render settings
    assert all(images.read(str(path)).shape == (20, 20, 3) for path in renders)
