import numpy as np
import pytest
from helpers import R, random_model, true_point

from matfit import correct, fit, images, params, presets, verify
from matfit.errors import FitError
from matfit.render import Renderer


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
    uncorrected = fit.fit(model, target, fit.Settings(method="lbfgsb", starts=2, iterations=60), extra=truth[None])
    x = uncorrected.unit
    before = float(images.rmse(decoded(model, x) + error, target))
    point, drawn = correct.step(model, target, weights, x, decoded(model, x) + error, decoded(model, x))
    after = float(images.rmse(drawn + error, target))
    assert before > 2.0  # the uncorrected answer carries part of the error (measured 2.89)
    assert after < 0.1 * before  # one round of the default 15 steps removes most of it (measured 0.166)
    assert np.all((point >= 0) & (point <= 1)) and point.shape == (params.COUNT,)
    np.testing.assert_allclose(drawn, decoded(model, point), atol=1e-5)  # the image returned is phi(point)


def test_verification_with_corrections_keeps_only_what_mitsuba_prefers(model):
    renderer = Renderer(R, 8)
    target = images.srgb_encode(renderer.render(presets.preset("red-plastic"), seed=5))
    result = fit.fit(model, target, fit.Settings(method="lbfgsb", starts=2, iterations=10))
    checked = verify.verify(renderer, result, target, corrections=2, model=model)
    assert checked.corrections == 2 and set(checked.decoded) == {"corrected-1", "corrected-2"}
    # the rounds start from the better of the start and the best end: the other end is not rendered; the start is
    # rendered with SEED only when the rounds start from it (its CONFIRM_SEED render, the guard's, chose that)
    assert len(verify.candidates(result)) == 3
    assert set(checked.points) - set(checked.decoded) == {"start", "end-1"}
    from_start = checked.figures["end-1"] >= checked.confirmation["start"]
    assert set(checked.figures) == {"end-1", "corrected-1"} | ({"start"} if from_start else set())
    for name in checked.decoded:  # phi of each round's point, as the decoder draws it
        np.testing.assert_allclose(checked.decoded[name], decoded(model, checked.points[name]), atol=1e-5)

    def figure(name, seed):
        image = renderer.render(params.from_unit(checked.points[name]), seed=seed, spp=verify.SPP)
        return float(images.rmse(images.srgb_encode(image), target))

    # the first round's residual came from a render with its own seed; the last round's point was rendered only
    # against the start, both with CONFIRM_SEED
    assert figure("corrected-1", verify.SEED + 1) == pytest.approx(checked.figures["corrected-1"], abs=1e-3)
    assert "corrected-2" not in checked.figures
    for name in ("start", "corrected-2"):
        assert figure(name, verify.CONFIRM_SEED) == pytest.approx(checked.confirmation[name], abs=1e-3)
    assert checked.start_rmse == checked.confirmation["start"]  # every answer is compared in CONFIRM_SEED's renders
    if checked.chosen == "corrected-2":
        assert checked.rmse == checked.confirmation["corrected-2"] < checked.start_rmse
    else:  # the best end if its lead holds in a second render, else the start
        assert checked.chosen in ("start", "end-1") and checked.rmse == checked.confirmation[checked.chosen]
    assert checked.rmse <= checked.start_rmse
    with pytest.raises(FitError, match="corrections -1 must be >= 0"):
        verify.verify(renderer, result, target, corrections=-1, model=model)
    with pytest.raises(ValueError, match="needs the fit's model"):
        verify.verify(renderer, result, target, corrections=1)


def test_a_round_reuses_the_fits_compiled_step(model):
    from matfit import gradient

    target, weights = decoded(model, true_point(4)) + bias(), np.ones((R, R), np.float32)
    x = true_point(5).astype(np.float64)
    correct.step(model, target, weights, x, decoded(model, x) + bias(), decoded(model, x), iterations=5)
    compiled = gradient.step._cache_size()
    point, _ = correct.step(model, 0.9 * target, weights, 0.9 * x, decoded(model, x), decoded(model, 0.9 * x), 5)
    assert gradient.step._cache_size() == compiled
    assert not np.allclose(point, 0.9 * x)  # it moved: the second round ran


class Scripted:
    """A renderer whose pictures are the target plus a grey offset chosen per material and seed: each branch of
    verification's choice with corrections made to happen. Anything not scripted (a round's point) is far off."""

    def __init__(self, target, offsets):
        self.target, self.offsets, self.asked = target, offsets, []

    def render(self, values, seed=0, spp=None):
        name = next((n for n, (v, _) in self.offsets.items() if np.allclose(v, values)), None)
        self.asked.append((name, seed))
        offset = self.offsets[name][1][seed] if name is not None else 0.3
        return images.srgb_decode(np.clip(self.target + offset, 0, 1))


@pytest.mark.parametrize(
    ("end_seed", "end_confirm", "start_confirm", "chosen", "start_with_seed"),
    [
        (0.05, 0.08, 0.10, "end-1", False),  # the rounds lose; the end's lead holds in a second render
        (0.05, 0.12, 0.10, "start", False),  # the rounds lose; the end's lead was its render's noise
        (0.15, 0.08, 0.10, "start", True),  # the start's guard render beats the end's: the rounds start from it
    ],
)
def test_with_corrections_the_start_is_rendered_once_unless_the_rounds_start_there(
    model, end_seed, end_confirm, start_confirm, chosen, start_with_seed
):
    target = np.full((R, R, 3), 0.4, np.float32)
    result = fit.fit(model, target, fit.Settings(method="lbfgsb", starts=2, iterations=5))
    pool = verify.candidates(result, verify.CORRECTED_CANDIDATES)
    offsets = {
        "start": (params.from_unit(pool["start"]), {verify.SEED: 0.10, verify.CONFIRM_SEED: start_confirm}),
        "end-1": (params.from_unit(pool["end-1"]), {verify.SEED: end_seed, verify.CONFIRM_SEED: end_confirm}),
    }
    scripted = Scripted(target, offsets)
    checked = verify.verify(scripted, result, target, corrections=2, model=model)
    assert checked.chosen == chosen
    assert checked.rmse == checked.confirmation[chosen] == pytest.approx(255 * offsets[chosen][1][verify.CONFIRM_SEED])
    assert checked.start_rmse == checked.confirmation["start"] and checked.rmse <= checked.start_rmse
    start_renders = [seed for name, seed in scripted.asked if name == "start"]
    assert sorted(start_renders) == sorted([verify.CONFIRM_SEED] + ([verify.SEED] if start_with_seed else []))
    assert ("start" in checked.figures) == start_with_seed
    # a round's residual and the last round's guard: SEED + 1, then CONFIRM_SEED, of points nobody scripted
    assert [seed for name, seed in scripted.asked if name is None] == [verify.SEED + 1, verify.CONFIRM_SEED]
