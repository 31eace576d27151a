"""The judge of a fit in a scene (`fitting/scene_judge`): a tiny scene, real renders."""

import numpy as np
import pytest

from matfit import images
from matfit.fitting import scene_judge
from matfit.rendering import presets


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
