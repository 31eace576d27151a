import numpy as np
import pytest

from matfit import images, params
from matfit.errors import FitError
from matfit.fitting import refine
from matfit.rendering import engine, presets, scene


@pytest.fixture(scope="module")
def llvm(renderer):
    if renderer.variant != engine.LLVM_VARIANT:
        pytest.skip("refinement differentiates with llvm_ad_rgb, which needs libLLVM >= 19")
    import mitsuba as mi

    return mi


@pytest.fixture(scope="module")
def reachable(renderer, llvm):
    """A red plastic target and a start whose base colour is 0.25 off in every channel."""
    truth = params.to_unit(presets.preset("red-plastic"))
    target = images.srgb_encode(renderer.render(params.from_unit(truth), seed=11, spp=64))
    start = truth.copy()
    start[:3] = np.clip(start[:3] + np.array([-0.25, 0.25, 0.25]), 0.0, 1.0)
    return target, start


def test_the_drjit_mapping_equals_params_and_scene_on_random_points(llvm):
    for seed in range(5):
        unit = np.random.default_rng(seed).random(params.COUNT)
        unit[params.INDEX["density"]] = 0.0 if seed == 0 else unit[params.INDEX["density"]]  # the extinction's floor
        values = refine.physical(llvm.Float(unit))
        got = np.array([v.array[0] for v in values])
        np.testing.assert_allclose(got, params.from_unit(unit), rtol=1e-6, atol=1e-7)
        sigma_t, albedo = refine.medium_textures(values)
        expected_sigma_t, expected_albedo = scene.medium_textures(params.from_unit(unit))
        np.testing.assert_allclose(np.array(sigma_t).ravel(), expected_sigma_t, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(np.array(albedo).ravel(), expected_albedo, rtol=1e-6)


def test_the_drjit_loss_at_the_images_own_secant_is_images_rmse_with_and_without_a_mask(llvm):
    rng = np.random.default_rng(3)
    linear = rng.uniform(-0.1, 1.3, (8, 8, 3)).astype(np.float32)  # out of range on both sides: clipped
    target = rng.random((8, 8, 3)).astype(np.float32)
    linear[0, 0] = images.srgb_decode(target[0, 0]) + 1e-5  # where the two meet, the tangent
    slope = refine.secant(linear, images.srgb_decode(target))
    for weights in (np.ones((8, 8), np.float32), rng.random((8, 8)).astype(np.float32)):
        loss = refine.step_rmse(
            llvm.TensorXf(linear),
            llvm.TensorXf(images.srgb_decode(target)),
            llvm.TensorXf(slope),
            llvm.TensorXf(refine.normalised_weights(weights)),
        )
        expected = images.rmse(images.srgb_encode(linear), target, weights)
        assert loss.array[0] == pytest.approx(float(expected), rel=1e-4)
        # with Huber's corner too, at the image's own secant the linear residual's loss is the encoded one's
        normalised = llvm.TensorXf(refine.normalised_weights(weights))
        corner = llvm.Float(0.2)
        huber = refine.step_rmse(
            llvm.TensorXf(linear), llvm.TensorXf(images.srgb_decode(target)), llvm.TensorXf(slope), normalised, corner
        )
        encoded = refine.srgb_rmse(llvm.TensorXf(linear), llvm.TensorXf(target), normalised, corner)
        assert huber.array[0] == pytest.approx(encoded.array[0], rel=1e-4) and huber.array[0] < 0.9 * loss.array[0]


def test_the_huber_loss_is_the_squared_one_under_its_corner_and_grows_by_the_absolute_residual_past_it(llvm):
    import drjit as dr

    rng = np.random.default_rng(7)
    linear = rng.random((8, 8, 3)).astype(np.float32)
    target = rng.random((8, 8, 3)).astype(np.float32)
    weights = rng.random((8, 8)).astype(np.float32)
    normalised = llvm.TensorXf(refine.normalised_weights(weights))
    residual = (images.srgb_encode(linear) - target).astype(np.float64)
    squared = refine.srgb_rmse(llvm.TensorXf(linear), llvm.TensorXf(target), normalised)
    wide = refine.srgb_rmse(llvm.TensorXf(linear), llvm.TensorXf(target), normalised, llvm.Float(2.0))
    assert wide.array[0] == pytest.approx(squared.array[0], rel=1e-6)  # every residual under the corner
    corner = 0.2
    huber = np.where(np.abs(residual) <= corner, residual**2, 2 * corner * np.abs(residual) - corner**2)
    expected = 255.0 * np.sqrt((huber * refine.normalised_weights(weights)).sum())
    unit = llvm.TensorXf(linear)
    dr.enable_grad(unit)
    loss = refine.srgb_rmse(unit, llvm.TensorXf(target), normalised, llvm.Float(corner))
    assert loss.array[0] == pytest.approx(expected, rel=1e-5) and expected < 255.0 * np.sqrt(
        (residual**2 * refine.normalised_weights(weights)).sum()
    )
    # past the corner a pixel pulls with the corner, not its residual: the gradient of the loss squared is
    # 2 corner w slope there (the encoding's slope), 2 r w slope under it
    dr.backward(dr.square(loss / 255.0))
    gradient = np.array(dr.grad(unit)).reshape(8, 8, 3)
    slope = images.srgb_slope(linear)
    pull = np.clip(residual, -corner, corner) * 2.0 * refine.normalised_weights(weights) * slope
    np.testing.assert_allclose(gradient, pull, rtol=1e-3, atol=1e-7)


def test_the_huber_corner_is_a_robust_spread_that_a_few_wild_pixels_do_not_move():
    rng = np.random.default_rng(9)
    residuals = rng.normal(0.0, 0.01, (64, 64, 3))
    wild = residuals.copy()
    wild.reshape(-1)[rng.choice(wild.size, wild.size // 50, replace=False)] = 0.8  # 2% fireflies
    weights = np.ones((64, 64, 3), np.float32)
    assert refine.huber_corner(residuals, weights, 3.0) == pytest.approx(0.03, rel=0.05)
    assert refine.huber_corner(wild, weights, 3.0) == pytest.approx(0.03, rel=0.1)  # the square root of the
    assert np.sqrt(np.mean(wild**2)) > 0.1  # mean square moves tenfold
    weights[:32] = 0.0  # only the pixels the fit looks at count
    wild[:32] = 0.8
    assert refine.huber_corner(wild, weights, 3.0) == pytest.approx(0.03, rel=0.1)


def test_a_noisy_images_residual_at_its_means_secant_is_that_of_its_mean_where_the_encoded_one_reads_darker():
    rng = np.random.default_rng(5)
    mean = np.full((64, 64, 3), 0.05)
    noisy = mean * rng.gamma(0.5, 2.0, (64, 64, 3))  # a medium's pixels at few samples: mean 0.05, heavy-tailed
    target = np.full((64, 64, 3), 0.05)
    encoded = 255 * float((images.srgb_encode(noisy) - images.srgb_encode(target)).mean())
    secant = 255 * float((refine.secant(mean, target) * (noisy - target)).mean())
    assert encoded < -15.0  # concave: the noisy image reads darker than its mean
    assert abs(secant) < 0.5  # linear in the image: its expectation is the mean's residual, 0


def test_steps_with_the_linear_residual_start_at_the_encoded_loss_and_descend(renderer, reachable):
    target, start = reachable
    mi, loaded, scene_parameters = refine._differentiable_scene(target.shape[0], renderer.variant)
    weights = refine.normalised_weights(np.ones(target.shape[:2], np.float32))
    problems = {
        linear: refine.Problem(
            mi, loaded, scene_parameters, engine.Keys(), mi.TensorXf(target), mi.TensorXf(weights), linear
        )
        for linear in (False, True)
    }
    _, encoded = refine.path(problems[False], start, 1, spp=4)
    points, losses = refine.path(problems[True], start, 4, spp=4, rate=0.05)
    # the first step's slope is the chord to its own image: the encoded loss, up to float rounding
    assert losses[0] == pytest.approx(encoded[0], rel=1e-3)
    assert losses[-1] < losses[0] and points[-1][0] > start[0]  # towards the red truth


def test_refinement_from_a_perturbed_point_lowers_the_mitsuba_loss(renderer, reachable):
    target, start = reachable
    result = refine.refine(start, target, steps=3, renderer=renderer, spp=4, rate=0.05)
    assert result.accepted and result.steps == 3 and len(result.losses) == 3 and result.losses[-1] < result.losses[0]
    assert result.rmse_after < result.rmse_before and result.rmse == result.rmse_after
    # the base colour moved towards the truth (red up, green and blue down)
    assert result.unit[0] > start[0] and result.unit[1] < start[1] and result.unit[2] < start[2]
    again = images.srgb_encode(
        renderer.render(params.from_unit(result.unit), seed=refine.ACCEPT_SEED, spp=refine.ACCEPT_SPP)
    )
    np.testing.assert_allclose(result.rendered, again, atol=1e-5)  # the same render, up to float rounding
    assert images.rmse(again, target) == pytest.approx(result.rmse_after, rel=1e-6)


def test_a_refinement_that_does_not_improve_returns_the_input_unchanged(renderer, reachable):
    target, truth = renderer.render(params.from_unit(reachable[1]), seed=12, spp=256), reachable[1]
    target = images.srgb_encode(target)  # the start is the truth, and steps of 1 throw the material into the corners
    result = refine.refine(truth, target, steps=3, renderer=renderer, spp=4, rate=1.0)
    assert result.losses[0] < min(result.losses[1:])
    assert not result.accepted and result.rmse == result.rmse_before and len(result.losses) == 3
    np.testing.assert_array_equal(result.unit, truth)
    expected = images.srgb_encode(
        renderer.render(params.from_unit(truth), seed=refine.ACCEPT_SEED, spp=refine.ACCEPT_SPP)
    )
    np.testing.assert_allclose(result.rendered, expected, atol=1e-5)
    nothing = refine.refine(truth, target, steps=0, renderer=renderer)
    assert not nothing.accepted and nothing.losses == [] and nothing.rmse_before == nothing.rmse_after
    np.testing.assert_array_equal(nothing.unit, truth)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"steps": -1}, "refinement steps -1 must be a whole number >= 0: use 0 to skip refinement"),
        ({"steps": 2.5}, "refinement steps 2.5 must be a whole number >= 0"),
        ({"spp": 0}, "refinement spp 0 must be a whole number >= 1"),
        ({"unit": np.full(18, 0.5)}, "the start must be 19 unit-cube values in [0, 1], got shape (18,)"),
        ({"target": np.zeros((16, 8, 3))}, "the target must be a square sRGB image (R, R, 3), got shape (16, 8, 3)"),
        ({"weights": np.ones((8, 8))}, "the mask must be (16, 16) like the target, got (8, 8)"),
    ],
)
def test_bad_settings_are_one_line_errors_naming_the_value_and_the_fix(arguments, message):
    call = {"unit": np.full(params.COUNT, 0.5), "target": np.zeros((16, 16, 3)), "steps": 2} | arguments
    with pytest.raises(FitError) as raised:
        refine.refine(**call)
    assert message in str(raised.value) and "\n" not in str(raised.value)


def test_a_medium_whose_extinction_differs_by_channel_steps_one_channel_a_render_without_heavy_tails(
    tmp_path, llvm, monkeypatch
):
    from dataclasses import replace

    from matfit.fitting import scene_fit
    from matfit.rendering import scene_file, scene_library

    box = scene_file.read(scene_library.write(str(tmp_path), "box", "sky", width=32, height=24), "object")
    renderer = scene_file.Renderer(box, box.size(32))
    jade = presets.preset("jade")
    target = np.clip(images.srgb_encode(renderer.render(jade, seed=3, spp=64)), 0.0, 1.0).astype(np.float32)
    region = scene_fit.region(renderer)[0]
    weights = region.astype(np.float32)
    problem = scene_fit.problem_of(renderer, target, weights, "prbvolpath", linear=True, by_channel=True)
    assert len(problem.channels) == 3 and problem.channels[0][0] is problem.scene
    assert scene_fit.problem_of(renderer, target, weights, "prbvolpath", linear=True).channels == ()  # an opaque fit's
    unit = params.to_unit(jade)
    assert refine.coloured(unit)
    assert not refine.coloured(params.to_unit(presets.preset("glass")))  # clear: one extinction in every channel
    opaque = unit.copy()
    opaque[params.INDEX["spec_trans"]] = 0.0  # no light reaches the medium
    assert not refine.coloured(opaque)

    def images_of(p):
        return np.array([np.array(refine.step_image(p, llvm.Float(unit), unit, seed, 8)) for seed in range(6)])

    monkeypatch.setattr(refine, "CHANNEL_SHARE", 1)  # as many samples a channel as in one render: the estimators alone
    by_channel, in_one = images_of(problem), images_of(replace(problem, channels=()))
    reference = renderer.render(jade, seed=5, spp=1024)[region]
    for found in (by_channel, in_one):  # both estimate the same image
        np.testing.assert_allclose(found.mean(axis=0)[region].mean(axis=0), reference.mean(axis=0), rtol=0.08)
    spread = [found.std(axis=0)[region].mean(axis=0) for found in (by_channel, in_one)]
    assert np.all(spread[0] < spread[1])
    assert by_channel[:, region].max() < 1.5 < in_one[:, region].max()  # no firefly of a transmittance ratio
    # one step moves the medium's colour in every channel: the gradient flows through each channel's render
    monkeypatch.undo()
    one, by_channel = refine.channel_noise(problem, unit, 8, (1, 2))  # a quarter of the samples a channel, and quieter
    assert 0 < by_channel < 0.9 * one
    start = unit.copy()
    colour = [params.INDEX[f"medium_color_{c}"] for c in "rgb"]
    start[colour] = np.clip(start[colour] + 0.1, 0.0, 1.0)
    points, _ = refine.path(problem, start, 1, seed=9)
    assert np.all(points[1][colour] != start[colour])
