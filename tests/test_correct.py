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
    # the rounds start from the better of the start and the best end: the other end is not rendered
    assert len(verify.candidates(result)) == 3
    assert set(checked.figures) - {"corrected-1"} == {"start", "end-1"} == set(checked.points) - set(checked.decoded)
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
    if checked.chosen == "corrected-2":
        assert checked.rmse == checked.confirmation["corrected-2"] < checked.start_rmse == checked.confirmation["start"]
    else:  # verification's rule among the fit's candidates
        assert not checked.chosen.startswith("corrected") and checked.start_rmse == checked.figures["start"]
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
