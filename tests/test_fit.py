import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import R, decode, random_model, true_point

from matfit import images, params, programs
from matfit.fitting import correct, gradient, ranges, search
from matfit.fitting.search import FitError, Settings
from matfit.model import architectures, models


@pytest.fixture(scope="module")
def model():
    return random_model()


def test_best_of_n_picks_the_closest_candidate(model):
    truth = true_point(1)
    extra = np.stack([true_point(2), truth, true_point(3)])
    result = search.neural_search(model, decode(model, truth), settings=Settings(method="nn"), extra=extra)
    assert result.chosen == "extra-2"
    np.testing.assert_allclose(result.start_image, decode(model, truth), atol=1e-5)
    assert result.rmse == pytest.approx(0.0, abs=1e-3)
    assert result.evaluations == 0
    assert set(result.candidate_rmse) == {"encoder-3", "encoder-8", "extra-1", "extra-2", "extra-3"}
    assert min(result.candidate_rmse, key=result.candidate_rmse.get) == "extra-2"


def test_hybrid_improves_on_its_start_and_stays_in_the_box(model):
    target = decode(model, true_point(4))
    for box in ("clip", "barrier"):
        result = search.neural_search(model, target, settings=Settings(method="hybrid", evaluations=400, box=box))
        assert result.evaluations == 400
        assert result.rmse < 0.8 * result.start_rmse
        assert result.unit.min() >= 0.0 and result.unit.max() <= 1.0
        np.testing.assert_allclose(result.values, params.from_unit(result.unit))


def test_box_terms():
    decoder = architectures.Decoder(resolution=8, hidden=8, base_channels=4, stage_channels=(4,))
    variables = architectures.initialise(decoder, jax.random.key(0), (19,))
    target, weights = np.zeros((8, 8, 3), np.float32), np.ones((8, 8), np.float32)
    inside = np.full(19, 0.5, np.float32)
    outside = inside.copy()
    outside[0] = 1.5
    clipped = inside.copy()
    clipped[0] = 1.0
    f = {
        box.value: (lambda x, box=box: float(search.objective(x, (decoder, variables, target, weights, box))))
        for box in search.Box
    }
    assert f["clip"](outside) == pytest.approx(f["clip"](clipped) + search.PENALTY * 0.5, rel=1e-5)
    assert f["barrier"](outside) >= search.BARRIER
    assert f["barrier"](inside) == pytest.approx(f["clip"](inside))


def test_box_penalty_has_a_zero_gradient_inside_the_box():
    gradient = jax.grad(search.distance_outside)(jnp.full(19, 0.5, jnp.float32))
    assert np.all(np.isfinite(gradient)) and np.all(gradient == 0.0)
    outside = jnp.full(19, 0.5, jnp.float32).at[0].set(1.5)
    np.testing.assert_allclose(jax.grad(search.distance_outside)(outside)[0], 1.0)


def test_a_mask_ignores_what_it_blacks_out(model):
    target = decode(model, true_point(5))
    spoiled = target.copy()
    spoiled[: R // 2] = 1.0 - spoiled[: R // 2]
    weights = np.ones((R, R), np.float32)
    weights[: R // 2] = 0.0
    masked = search.neural_search(model, spoiled, settings=Settings(method="hybrid", evaluations=300), weights=weights)
    plain = search.neural_search(model, spoiled, settings=Settings(method="hybrid", evaluations=300))
    assert masked.rmse < plain.rmse


def test_one_compilation_serves_every_target(model):
    settings = Settings(method="hybrid", evaluations=60)
    search.neural_search(model, decode(model, true_point(6)), settings=settings)
    before = search._best_of_n._cache_size()
    for seed in (7, 8, 9):
        search.neural_search(model, decode(model, true_point(seed)), settings=settings)
    assert search._best_of_n._cache_size() == before


def test_optimize_starts_from_a_seeded_random_point(model):
    target = decode(model, true_point(10))
    settings = Settings(method="optimize", evaluations=100)
    a = search.neural_search(model, target, settings=settings, seed=1)
    before = search._best_of_n._cache_size()
    b = search.neural_search(model, target, settings=settings, seed=1)
    c = search.neural_search(model, target, settings=settings, seed=2)
    assert search._best_of_n._cache_size() == before  # the seed is data: no new compilation
    np.testing.assert_array_equal(a.unit, b.unit)
    assert not np.array_equal(a.unit, c.unit)


@pytest.mark.parametrize(
    "settings, message, field",
    [
        ({"method": "hybrid", "evaluations": 0}, "evaluations 0 is out of range", "evaluations"),
        ({"method": "hybrid", "evaluations": 20}, "evaluations 20 is out of range", "evaluations"),
        ({"method": "magic"}, "method 'magic' is unknown", "method"),
        ({"box": "soft"}, "box 'soft' is unknown", "box"),
    ],
)
def test_bad_settings(model, settings, message, field):
    with pytest.raises(FitError, match=message) as raised:
        search.neural_search(model, np.zeros((R, R, 3), np.float32), settings=Settings(**settings))
    assert raised.value.field == field


def test_wrong_target_shape_and_bad_mask(model):
    with pytest.raises(FitError, match=r"needs \(32, 32, 3\)"):
        search.neural_search(model, np.zeros((8, 8, 3), np.float32))
    with pytest.raises(FitError, match="mask must be"):
        search.neural_search(model, np.zeros((R, R, 3), np.float32), weights=np.zeros((R, R)))
    with pytest.raises(FitError, match="make the mask the same size"):
        search.prepare_mask(np.ones((10, 12, 3), np.float32), (12, 12), R, "m.png")


def test_prepare_target_warns_about_aspect():
    square, notices = search.prepare_target(np.full((40, 40, 3), 0.2, np.float32), R, "t.png")
    assert square.shape == (R, R, 3) and notices == []
    np.testing.assert_allclose(square, 0.4845292, rtol=1e-4)  # sRGB of linear 0.2
    _, notices = search.prepare_target(np.full((40, 50, 3), 0.2, np.float32), R, "t.png")
    assert len(notices) == 1 and "50x40" in notices[0] and "1.250" in notices[0] and "1.000" in notices[0]


@pytest.mark.parametrize("method", ["lbfgsb", "hybrid-lbfgsb"])
def test_gradient_methods_reach_a_reachable_target_and_count_their_budget(model, method):
    truth = true_point(11)
    target = decode(model, truth)
    settings = Settings(method=method, evaluations=60, starts=2, iterations=60, narrow_after=20)
    best_of_n = search.neural_search(model, target, settings=Settings(method="nn"))
    result = search.neural_search(model, target, settings=settings)
    assert result.rmse <= best_of_n.rmse and result.rmse == pytest.approx(result.end_rmse[0])
    assert np.all(np.diff(result.end_rmse) >= 0)  # end points best first
    assert len(result.ends) == (3 if method == "hybrid-lbfgsb" else 2)
    simplex_part = 60 if method == "hybrid-lbfgsb" else 0
    spent = round(
        (result.evaluations - simplex_part) / search.GRADIENT_COST
    )  # value-and-gradient evaluations, all starts
    assert result.evaluations - simplex_part == pytest.approx(search.GRADIENT_COST * spent, abs=0.5)  # rounded to whole
    assert len(result.ends) <= spent <= 20 * len(result.ends) + 40  # every start 20 steps at most, the best 40 more
    compiled = [search._best_of_n, search._polish_and_sort, gradient.step]
    before = [function._cache_size() for function in compiled]
    search.neural_search(model, decode(model, true_point(12)), settings=settings)
    assert [function._cache_size() for function in compiled] == before


def test_optimize_reports_its_random_start(model):
    target = decode(model, true_point(13))
    result = search.neural_search(model, target, settings=Settings(method="optimize", evaluations=40), seed=3)
    expected = np.random.default_rng(3).uniform(0.0, 1.0, params.COUNT).astype(np.float32)
    assert result.chosen == "random"
    np.testing.assert_array_equal(result.start, expected)
    assert result.start_rmse == pytest.approx(float(np.asarray(images.rmse(decode(model, expected), target))), rel=1e-5)


def test_gradient_methods_add_the_media_grid_to_best_of_n(model):
    grid = search.media_candidates()
    assert grid.shape == (48, params.COUNT) and grid.min() >= 0.0 and grid.max() <= 1.0
    assert len({tuple(point) for point in grid}) == 48
    physical = np.stack([params.from_unit(point) for point in grid])
    for name in ("base_color_r", "base_color_g", "base_color_b", "spec_trans"):
        np.testing.assert_allclose(physical[:, params.INDEX[name]], 1.0)
    assert sorted(set(np.round(physical[:, params.INDEX["density"]], 6))) == [0.5, 1.0, 2.0, 4.0]
    target = decode(model, grid[17])
    result = search.neural_search(
        model, target, settings=Settings(method="lbfgsb", starts=1, iterations=1, narrow_after=1)
    )
    assert result.chosen == "media-18" and result.start_rmse == pytest.approx(0.0, abs=1e-3)
    assert len(result.candidate_rmse) == len(model.encoders) + 48
    paper = search.neural_search(model, target, settings=Settings(method="nn"))
    assert set(paper.candidate_rmse) == {"encoder-3", "encoder-8"}


def test_the_fit_hands_back_the_images_of_its_start_and_end_points(model):
    target = decode(model, true_point(5))
    result = search.neural_search(
        model, target, settings=Settings(method="lbfgsb", starts=2, iterations=3, narrow_after=2)
    )
    assert result.end_images.shape == (len(result.ends), R, R, 3)
    for end, image in zip(result.ends, result.end_images, strict=True):
        np.testing.assert_allclose(result.decoded(end), decode(model, end), atol=1e-5)
        np.testing.assert_array_equal(result.decoded(end), image)
    np.testing.assert_allclose(result.decoded(result.start), decode(model, result.start), atol=1e-5)
    np.testing.assert_allclose(result.image, result.end_images[0])
    assert result.decoded(np.full(params.COUNT, 0.123)) is None  # not a point the fit decoded


def test_on_start_hears_best_of_n_winner_and_never_a_random_start(model):
    target = decode(model, true_point(14))
    heard = []

    def on_start(start):
        heard.append(np.array(start))

    result = search.neural_search(
        model, target, settings=Settings(method="lbfgsb", starts=2, iterations=3, narrow_after=2), on_start=on_start
    )
    assert len(heard) == 1
    # the very bytes verification renders the start from (`verify.candidates`): a prefetched render is found
    assert np.asarray(heard[0], np.float64).tobytes() == np.asarray(result.start, np.float64).tobytes()
    search.neural_search(model, target, settings=Settings(method="optimize", evaluations=40), on_start=on_start)
    assert len(heard) == 1  # optimize starts from a random point, not from best-of-n's winner


def test_a_model_that_decodes_nan_is_refused_and_no_params_json_is_written(model, tmp_path):
    import dataclasses

    from matfit.fitting import fitfile
    from matfit.fitting.request import Outputs, Request

    poisoned = jax.tree_util.tree_map(lambda leaf: np.full(np.shape(leaf), np.nan, np.float32), model.decoder.variables)
    broken = dataclasses.replace(model, decoder=dataclasses.replace(model.decoder, variables=poisoned))
    images.write(str(tmp_path / "edit.png"), np.full((R, R, 3), 0.3, np.float32))
    outputs = Outputs(str(tmp_path / "params.json"))
    request = Request(str(tmp_path / "edit.png"), settings=Settings(method="nn"), verified=False, outputs=outputs)
    with pytest.raises(FitError, match=r"decodes images that are not finite \(neural RMSE nan\).*train it again"):
        fitfile.run(request, broken)
    assert not (tmp_path / "params.json").exists()  # was written with "neural_rmse": NaN, which is not JSON


def test_a_request_is_refused_before_any_work_with_the_one_line_error(tmp_path):
    from matfit.errors import ImageError, OutputError
    from matfit.fitting import fitfile
    from matfit.fitting.methods import CORRECTIONS
    from matfit.fitting.request import Outputs, Request

    missing_model = str(tmp_path / "no-model")  # loading it would fail: each refusal must come before
    picture = str(tmp_path / "edit.png")
    images.write(picture, np.full((R, R, 3), 0.3, np.float32))
    written = Outputs(str(tmp_path / "params.json"))
    refusals = [
        (
            Request(picture, outputs=Outputs(str(tmp_path / "params.txt"))),
            OutputError,
            r"params\.txt must end in \.json",
        ),
        (Request(str(tmp_path / "gone.png"), outputs=written), ImageError, r"target .*gone\.png is not a file"),
        (Request(picture, mask=str(tmp_path / "no-mask.png"), outputs=written), ImageError, "mask .* is not a file"),
        (Request(picture, verified=False, corrections=2, outputs=written), FitError, "2 correction rounds need"),
        (Request(picture, corrections=-1, outputs=written), FitError, "corrections -1 must be >= 0"),
        (Request(picture, refine_steps=-1, outputs=written), FitError, "refine steps -1 must be >= 0"),
    ]
    for request, error, message in refusals:
        with pytest.raises(error, match=message):
            fitfile.run(request, missing_model)
    assert not (tmp_path / "params.json").exists()
    with pytest.raises(ValueError, match="writes the request's outputs"):
        fitfile.run(Request(picture), missing_model)
    assert Request(picture).rounds == CORRECTIONS and Request(picture, verified=False).rounds == 0
    assert Request(picture, corrections=1).rounds == 1


def test_the_ranges_written_are_those_of_the_answer_written_and_no_render_has_no_noise(tmp_path):
    # On glass, `fit --method nn --no-verify` wrote density 0.055 with a "decided" range [0, 0.029]: the ranges were the
    # fit's best's, the values the clean answer's (its other parameters re-fitted); and answer.render_noise was 0.0
    # where nothing was rendered.
    from matfit import shipped
    from matfit.fitting import fitfile
    from matfit.fitting.request import Request
    from matfit.rendering import engine, presets

    picture = str(tmp_path / "glass.png")
    engine.render_file(presets.preset("glass"), picture, 256, 64)
    outcome, _ = fitfile.fit_file(Request(picture, settings=Settings(method="nn"), verified=False), str(shipped.MODEL))
    document = outcome.document
    assert document["answer"]["kept"] == "clean" and document["answer"]["features_off"]
    for name, value in document["params"].items():
        reported = document["ranges"]["parameters"][name]
        assert reported["low"] <= value <= reported["high"], (name, value, reported)
    assert document["answer"]["render_noise"] is None and document["answer"]["mitsuba_rmse"] == {}


def test_a_new_process_with_the_stored_programs_traces_and_compiles_nothing_in_the_stages_after_the_search(
    model, tmp_path, caplog
):
    # A JAX operation outside a stored program (an index, jnp.arange, eval_shape) is traced and compiled in every new
    # process: 0.4-0.6 s of a cold `matfit fit` before these stages ran NumPy instead (docs/fitting.md#measured).
    previous = programs._directory, programs._key
    programs.enable(str(tmp_path / "programs"))
    try:
        target = decode(model, true_point(5))
        unit = true_point(6)
        weights = np.ones((R, R), np.float32)

        drawn = decode(model, unit)

        def stages():
            correct.correction_round(model, target, weights, unit, drawn, drawn, iterations=3)
            ranges.measure(ranges.Decoding(model.decoder.module), model.decoder.variables, unit, None, 2.0)

        stages()  # compiles the programs and stores them
        jax.clear_caches()  # what a new process holds: nothing traced, nothing compiled
        for function in (
            gradient.step,
            models.apply,
            ranges.decoded,
            ranges._linearise,
            ranges._linear_ends,
            ranges._check,
        ):
            function.loaded.clear()
        with jax.log_compiles(), caplog.at_level(logging.DEBUG, logger="jax"):
            stages()
        logged = [record.getMessage() for record in caplog.records]
        assert not [message for message in logged if "Compiling" in message or "tracing" in message]
    finally:
        programs._directory, programs._key = previous
