import numpy as np
import pytest
from helpers import Noisy, R, random_model, true_point

from matfit import images, params
from matfit.errors import FitError
from matfit.fitting import correct, search, verify
from matfit.rendering import presets
from matfit.rendering.engine import Renderer


@pytest.fixture(scope="module")
def model():
    return random_model()


def decoded(model, unit):
    return np.asarray(model.decode(np.asarray(unit)[None])[0])


def bias():
    """A smooth error that does not depend on the material: what a decoder that draws everything too dark misses."""
    ramp = np.linspace(0.02, 0.12, R, dtype=np.float32)
    return np.broadcast_to(ramp[:, None, None], (R, R, 3)).copy()


def test_the_corrected_target_is_the_target_less_the_decoders_error():
    rng = np.random.default_rng(0)
    target, rendered, drawn = (rng.uniform(0, 1, (4, 4, 3)).astype(np.float32) for _ in range(3))
    corrected = correct.corrected_target(target, rendered, drawn)
    assert corrected.dtype == np.float32
    np.testing.assert_allclose(corrected, target.astype(np.float64) - rendered + drawn, atol=1e-6)
    with pytest.raises(ValueError, match=r"Shape mismatch: got \(4, 4, 3\), \(4, 4, 3\) and \(2, 4, 3\)"):
        correct.corrected_target(target, rendered, drawn[:2])


def test_one_round_removes_an_error_the_decoder_makes_everywhere(model):
    # "Mitsuba" here is the decoder plus a fixed error: a round must find where phi + error meets the target,
    # which the fit of the target alone cannot (it matches phi to the target, error and all).
    truth, error = true_point(3), bias()
    target = decoded(model, truth) + error
    weights = np.ones((R, R), np.float32)
    uncorrected = search.neural_search(
        model, target, settings=search.Settings(method="lbfgsb", starts=2, iterations=60), extra=truth[None]
    )
    x = uncorrected.unit
    before = float(images.rmse(decoded(model, x) + error, target))
    point, drawn = correct.correction_round(model, target, weights, x, decoded(model, x) + error, decoded(model, x))
    after = float(images.rmse(drawn + error, target))
    assert before > 2.0  # the uncorrected answer carries part of the error (measured 2.89)
    assert after < 0.1 * before  # one round of the default 15 steps removes most of it (measured 0.166)
    assert np.all((point >= 0) & (point <= 1)) and point.shape == (params.COUNT,)
    np.testing.assert_allclose(drawn, decoded(model, point), atol=1e-5)  # the image returned is phi(point)


class Recording(Renderer):
    """Mitsuba, and the list of its renders as (material, seed)."""

    asked: list

    def render(self, values, seed=0, spp=None):
        self.asked.append((np.asarray(values), seed))
        return super().render(values, seed, spp)


def test_verification_with_corrections_keeps_the_lowest_estimate_of_the_start_the_best_end_and_the_last_round(model):
    renderer = Recording(R, 8)
    renderer.asked = []
    target = images.srgb_encode(renderer.render(presets.preset("red-plastic"), seed=5))
    result = search.neural_search(model, target, settings=search.Settings(method="lbfgsb", starts=2, iterations=10))
    renderer.asked = []
    checked = verify.correct_then_verify(renderer, result, target, model=model, corrections=2)
    assert checked.corrections == 2 and set(checked.decoded) == {"corrected-1", "corrected-2"}
    assert len(verify.candidates(result)) == 3  # the other end is not among them
    assert set(checked.figures) == set(checked.batches) == {"start", "end-1", "corrected-2"}
    assert checked.chosen == min(checked.figures, key=checked.figures.get) and checked.rmse <= checked.start_rmse
    for name in checked.decoded:  # phi of each round's point, as the decoder draws it
        np.testing.assert_allclose(checked.decoded[name], decoded(model, checked.points[name]), atol=1e-5)

    def renders_of(name):
        values = params.from_unit(checked.points[name])
        return [seed for material, seed in renderer.asked if np.allclose(material, values)]

    # every candidate's batches with the common seeds; the residuals with seeds no batch uses: the first round's of
    # where the rounds start (the best end, if its render with SEED beats the start's first batch, else the start),
    # the second round's of the first round's point
    batches = {name: [verify.BATCH_SEED + j for j in range(count)] for name, count in checked.batches.items()}
    end_first = images.rmse(
        images.srgb_encode(renderer.render(params.from_unit(checked.points["end-1"]), verify.SEED, verify.SPP)), target
    )
    start_first = images.rmse(
        images.srgb_encode(renderer.render(params.from_unit(checked.points["start"]), verify.BATCH_SEED, verify.SPP)),
        target,
    )
    origin = "end-1" if end_first < start_first else "start"
    assert sorted(renders_of("end-1")[: len(batches["end-1"]) + 1]) == sorted([*batches["end-1"], verify.SEED])
    start_renders = sorted([*batches["start"], *([verify.SEED] if origin == "start" else [])])
    assert sorted(renders_of("start")[: len(start_renders)]) == start_renders
    assert renders_of("corrected-1") == [verify.SEED + 1]
    assert renders_of("corrected-2")[: len(batches["corrected-2"])] == batches["corrected-2"]
    rounds_from = checked.points["corrected-1"]  # one round of correction from the origin gives the first point
    again, _ = correct.correction_round(
        model,
        target,
        np.ones((R, R), np.float32),
        checked.points[origin],
        images.srgb_encode(renderer.render(params.from_unit(checked.points[origin]), verify.SEED, verify.SPP)),
        decoded(model, checked.points[origin]),
    )
    np.testing.assert_allclose(again, rounds_from, atol=1e-4)
    with pytest.raises(FitError, match="corrections -1 must be >= 0"):
        verify.correct_then_verify(renderer, result, target, model=model, corrections=-1)
    with pytest.raises(ValueError, match="at least one round of correction"):
        verify.correct_then_verify(renderer, result, target, model=model, corrections=0)


def test_a_round_reuses_the_fits_compiled_step(model):
    from matfit.fitting import gradient

    target, weights = decoded(model, true_point(4)) + bias(), np.ones((R, R), np.float32)
    x = true_point(5).astype(np.float64)
    correct.correction_round(model, target, weights, x, decoded(model, x) + bias(), decoded(model, x), iterations=5)
    compiled = gradient.step._cache_size()
    point, _ = correct.correction_round(
        model, 0.9 * target, weights, 0.9 * x, decoded(model, x), decoded(model, 0.9 * x), iterations=5
    )
    assert gradient.step._cache_size() == compiled
    assert not np.allclose(point, 0.9 * x)  # it moved: the second round ran


def scripted_fit(model, start_offset: float, end_offset: float, spread: float = 0.02):
    """Returns (a grey target, a short fit of it, its start and best end, a `Noisy` renderer drawing them
    `start_offset` and `end_offset` off the target)."""
    target = np.full((R, R, 3), 0.4, np.float32)
    result = search.neural_search(model, target, settings=search.Settings(method="lbfgsb", starts=2, iterations=5))
    pool = verify.candidates(result, count=verify.CORRECTED_CANDIDATES)
    offsets = {"start": start_offset, "end-1": end_offset}
    return (
        target,
        result,
        pool,
        Noisy(target, {name: (params.from_unit(pool[name]), offsets[name], spread) for name in pool}),
    )


@pytest.mark.parametrize(("start_offset", "end_offset", "origin"), [(0.10, 0.05, "end-1"), (0.05, 0.10, "start")])
def test_the_rounds_start_from_the_better_estimate_and_a_worse_last_round_is_not_kept(
    model, start_offset, end_offset, origin
):
    target, result, _, scripted = scripted_fit(model, start_offset, end_offset)
    offsets = {"start": start_offset, "end-1": end_offset}
    checked = verify.correct_then_verify(scripted, result, target, model=model, corrections=2)
    # the rounds' points are 0.3 off: the better of the start and the best end is kept, as it was where they started
    assert checked.chosen == origin and checked.figures["corrected-2"] == pytest.approx(255 * 0.3, rel=1e-3)
    assert checked.figures[origin] == pytest.approx(255 * offsets[origin], rel=0.05)
    assert (origin, verify.SEED) in scripted.asked and (None, verify.SEED + 1) in scripted.asked
    assert [seed for name, seed in scripted.asked if name is None and seed < verify.BATCH_SEED] == [verify.SEED + 1]


def test_residual_renders_take_their_own_samples_and_the_start_then_its_own_seed_render(model):
    target, result, _, scripted = scripted_fit(model, 0.05, 0.10)
    samples = []
    render = scripted.render
    scripted.render = lambda values, seed=0, spp=None: samples.append((seed, spp)) or render(values, seed, spp)
    checked = verify.correct_then_verify(scripted, result, target, model=model, corrections=2, spp=16, residual_spp=64)
    assert checked.chosen == "start"
    # both rounds' starting renders with SEED at 64 (compared like with like), the second round's residual at 64,
    # every batch at 16
    residuals = [(seed, spp) for seed, spp in samples if seed < verify.BATCH_SEED]
    assert sorted(residuals) == [(verify.SEED, 64), (verify.SEED, 64), (verify.SEED + 1, 64)]
    assert {spp for seed, spp in samples if seed >= verify.BATCH_SEED} == {16}
    assert ("start", verify.SEED) in scripted.asked and ("end-1", verify.SEED) in scripted.asked


def test_the_best_ends_batches_are_asked_for_beside_each_render_the_rounds_wait_for(model):
    # The judge renders the best end's batches whatever the rounds do: each is asked for right after a render the
    # rounds wait for (a second render child makes it meanwhile), and none is rendered twice or in vain.
    target, result, pool, scripted = scripted_fit(model, 0.10, 0.05)
    calls = []
    render = scripted.render
    named = {name: params.from_unit(pool[name]) for name in pool}

    def name_of(values):
        return next((name for name, known in named.items() if np.allclose(known, values)), None)

    scripted.prefetch = lambda values, seed=0, spp=None: calls.append(("ask", name_of(values), seed))
    scripted.render = lambda values, seed=0, spp=None: (
        calls.append(("render", name_of(values), seed)) or render(values, seed, spp)
    )
    checked = verify.correct_then_verify(scripted, result, target, model=model, corrections=2)
    assert checked.chosen == "end-1" and checked.batches["end-1"] == verify.BATCHES
    waits = [(verify.SEED, "end-1"), (verify.SEED + 1, None)]  # the rounds start at the best end; round 2's residual
    for j, (seed, name) in enumerate(waits):
        at = calls.index(("ask", name, seed))
        assert calls[at + 1] == ("ask", "end-1", verify.BATCH_SEED + j)
        assert calls.index(("render", name, seed)) > at + 1
    judged = calls.index(("render", None, verify.BATCH_SEED))  # the judge's first render of the last round's point
    assert calls.index(("ask", "end-1", verify.BATCH_SEED + 1)) < judged
    renders = [call[1:] for call in calls if call[0] == "render"]
    assert sorted(seed for name, seed in renders if name == "end-1") == sorted(
        [verify.SEED, *(verify.BATCH_SEED + j for j in range(verify.BATCHES))]
    )
