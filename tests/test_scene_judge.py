"""The judge of a fit in a scene (`fitting/scene_judge`): a tiny scene, real renders."""

import numpy as np
import pytest

from matfit import images
from matfit.fitting import refine, scene_fit, scene_judge
from matfit.rendering import presets, scene_file, scene_library


def test_the_judge_renders_a_material_once_at_each_seed(red_knot_fit, monkeypatch):
    # the descent's answer is judged by `closest`, `off_bounds` and the acceptance at the same seeds: one render each
    renderer, target, weights = red_knot_fit
    asked = []
    render = renderer.render
    monkeypatch.setattr(renderer, "render", lambda values, **kw: asked.append(kw["seed"]) or render(values, **kw))
    judge = scene_judge.Judge(renderer, target, weights)
    red = presets.preset("red-plastic")
    first = judge.render(red)
    again = judge.render(red.copy())
    assert again is first and asked == [scene_judge.JUDGE_SEED]
    second = judge.render(red, scene_judge.SECOND_SEED)
    assert asked == [scene_judge.JUDGE_SEED, scene_judge.SECOND_SEED] and not np.array_equal(second, first)
    # the noise-free error is made of the two seeds' renders, rendered no more
    squared = judge.squared(red)
    assert squared == 255.0**2 * images.noise_free_mse(np.asarray([first, second]), target, weights)
    assert asked == [scene_judge.JUDGE_SEED, scene_judge.SECOND_SEED]
    error = scene_judge.root(squared)
    assert error == pytest.approx(np.sqrt(max(squared, 0.0))) and error < images.rmse(first, target, weights)


def test_the_robust_judge_weighs_nothing_where_the_target_stands_out_of_its_reference(red_knot_fit, monkeypatch):
    # a target with fireflies: a few of the shape's pixels white, as a heavy-tailed target's noise leaves them
    monkeypatch.setattr(scene_judge, "HEAVY_TAILED", 0.0)  # as if the renders' noise were heavy-tailed (below)
    renderer, target, weights = red_knot_fit
    judge = scene_judge.Judge(renderer, target, weights)
    red = presets.preset("red-plastic")
    region = np.argwhere(weights > 0)
    fireflies = region[:: max(1, len(region) // 12)]
    noisy = target.copy()
    noisy[fireflies[:, 0], fireflies[:, 1]] = 1.0
    spotted = scene_judge.Judge(renderer, noisy, weights, judge.made)  # the same renders
    robust = spotted.robust(red)
    assert robust.weights[fireflies[:, 0], fireflies[:, 1]].max() == 0.0
    seen = (weights > 0) & (robust.weights > 0)
    assert np.median(robust.weights[seen] / weights[seen]) > 0.9  # the rest keeps most of its weight
    assert (robust.weights > 0).sum() > 0.9 * (weights > 0).sum()
    # the squares read the fireflies: the red material seems far from its own picture (214 against 5.2, squared);
    # past them it is as near as without them (4.0)
    clean, fooled, looked_past = (j.squared(red) for j in (judge, spotted, robust))
    assert fooled > 20 * clean and looked_past < 2 * clean
    # a target its reference renders exactly (their mean): nothing stands out, the judge as it was
    exact = scene_judge.Judge(renderer, judge.renders(red).mean(axis=0), weights, judge.made)
    assert exact.robust(red) is exact


def test_the_judge_looks_past_outliers_only_where_the_renders_noise_is_heavy_tailed(red_knot_fit, tmp_path):
    # the red knot under the studio light renders with light-tailed noise: the squares judge it, whatever the target
    renderer, target, weights = red_knot_fit
    red = presets.preset("red-plastic")
    judge = scene_judge.Judge(renderer, target, weights)
    assert judge.tails(red) < scene_judge.HEAVY_TAILED  # 7.7
    assert judge.robust(red) is judge
    # the gold knot under the sun: a glossy metal under a small light renders with fireflies
    path = scene_library.write(str(tmp_path), "knot", "sun", width=32, height=24)
    sun = scene_file.read(path, "object")
    gold = presets.preset("gold")
    lit = scene_file.Renderer(sun, sun.size(64), integrator=scene_file.OPAQUE_INTEGRATOR)
    picture = np.clip(images.srgb_encode(scene_file.Renderer(sun, sun.size(64)).render(gold, seed=11, spp=64)), 0, 1)
    metal = scene_judge.Judge(lit, picture.astype(np.float32), scene_fit.region(lit)[0].astype(np.float32))
    assert metal.tails(gold) > 1.5 * scene_judge.HEAVY_TAILED  # 29.4
    robust = metal.robust(gold)
    assert robust is not metal and 0.5 < robust.weights.sum() / metal.weights.sum() < 1.0
    # and encoded, its noisy renders read darker than their mean: a step's image of the gold knot under the sun by
    # more than `scene_fit.DARKENING`, whose steps then take the linear residual; the red knot under the studio
    # light's by a twelfth of it
    step = refine.PRIMAL * scene_fit.STEP_SPP
    assert metal.darkening(gold, step) > scene_fit.DARKENING  # 0.77
    assert 0.0 < judge.darkening(red, step) < 0.2 * scene_fit.DARKENING  # 0.04


def test_the_darkening_is_the_encoding_of_the_mean_less_the_encodings_scaled_to_the_samples(red_knot_fit):
    # two renders a pixel's mean 0.2 +- 0.05 apart (linear): the curve's bend reads them darker than their mean
    renderer, target, weights = red_knot_fit
    red = presets.preset("red-plastic")
    judge = scene_judge.Judge(renderer, target, weights)
    shape = target.shape
    lower, upper = np.full(shape, 0.15, np.float32), np.full(shape, 0.25, np.float32)
    for seed, linear in ((scene_judge.JUDGE_SEED, lower), (scene_judge.SECOND_SEED, upper)):
        judge.made[(np.asarray(red, np.float64).tobytes(), seed)] = images.srgb_encode(linear)
    encode = lambda x: float(images.srgb_encode(np.float32(x)))  # noqa: E731
    pair = encode(0.2) - (encode(0.15) + encode(0.25)) / 2  # 0.0046: a quarter of the bend times the variance
    assert pair > 0
    assert judge.darkening(red, scene_judge.JUDGE_SPP) == pytest.approx(255 * 2 * pair, rel=1e-4)
    # a render of half the samples has twice the variance: twice as dark
    assert judge.darkening(red, scene_judge.JUDGE_SPP // 2) == pytest.approx(255 * 4 * pair, rel=1e-4)
    # two renders alike: no noise, no darkening
    judge.made[(np.asarray(red, np.float64).tobytes(), scene_judge.SECOND_SEED)] = images.srgb_encode(lower)
    assert judge.darkening(red, 64) == pytest.approx(0.0, abs=1e-4)


def test_the_kurtosis_is_3_for_gaussian_noise_and_grows_with_a_few_wild_pixels():
    noise = np.random.default_rng(0).normal(size=(64, 64, 3))
    weights = np.ones((64, 64))
    assert scene_judge.kurtosis(noise, weights) == pytest.approx(3.0, abs=0.15)
    wild = noise.copy()
    wild[:2, :2] = 30.0  # 4 pixels of 4096
    assert scene_judge.kurtosis(wild, weights) > 50
    weights[:2, :2] = 0.0  # weighed nothing: as if not there
    assert scene_judge.kurtosis(wild, weights) == pytest.approx(3.0, abs=0.15)
    assert scene_judge.kurtosis(np.zeros((4, 4, 3)), np.ones((4, 4))) == 0.0  # no spread at all
