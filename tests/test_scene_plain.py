"""Plainer materials than a scene fit's descent reached (`fitting/scene_plain`): tiny scenes and few steps, real
renders."""

import numpy as np
import pytest

from matfit import params
from matfit.fitting import scene_fit, scene_judge, scene_plain
from matfit.rendering import presets

pytestmark = pytest.mark.usefixtures("tiny_scene_fits")  # tests/conftest.py


def test_a_roughness_near_0_goes_to_0_unless_the_picture_asks_for_it(red_knot_fit):
    renderer, target, weights = red_knot_fit
    judge = scene_judge.Judge(renderer, target, weights)
    truth = params.to_unit(presets.preset("red-plastic"))  # roughness 0.3: past NEAR_ZERO, not tried
    assert scene_plain.at_zero(judge, truth) == (truth, {"near": [], "tried": [], "zero": []})
    rough = truth.copy()
    rough[params.INDEX["roughness"]] = 0.2  # near 0, but the picture's highlight is broad: kept
    point, done = scene_plain.at_zero(judge, rough)
    np.testing.assert_array_equal(point, rough)
    assert done["near"] == ["roughness"] and done["zero"] == []  # density: an opaque material's medium shows not
    [tried] = done["tried"]  # type: ignore[misc]
    assert tried["behind"] > scene_plain.PLAIN_LEAD * tried["standard_error"]  # 2.3 +- 0.6, squared
    # a picture of that material made sharper: the renders at roughness 0 are closer, and it goes to 0
    sharp = truth.copy()
    sharp[params.INDEX["roughness"]] = 0.0
    mirror = scene_judge.Judge(renderer, judge.render(params.from_unit(sharp), seed=7), weights)
    point, done = scene_plain.at_zero(mirror, rough)
    np.testing.assert_array_equal(point, sharp)
    assert done["zero"] == ["roughness"]


def test_a_lobe_the_picture_does_not_ask_for_is_turned_off_and_one_it_does_stays(red_knot_fit):
    # the red plastic's coat (0.5) shows in its picture; a sheen of 0.3 on top of it, which the picture lacks, does not
    renderer, target, weights = red_knot_fit
    judge = scene_judge.Judge(renderer, target, weights)
    problem = scene_fit.problem_of(renderer, target, weights, "prb")
    truth = params.to_unit(presets.preset("red-plastic"))
    sheened = truth.copy()
    sheened[params.INDEX["sheen"]] = 0.3
    heard = []
    point, done, losses = scene_plain.plain(judge, problem, sheened, 2, seed=0, progress=lambda *a: heard.append(a))
    assert done["on"] == ["clearcoat", "sheen"] and done["off"] == ["sheen"]
    tried = done["tried"]
    assert [t["off"] for t in tried] == [["clearcoat", "sheen"], ["clearcoat"], ["sheen"]]  # type: ignore[index]
    assert [t["kept"] for t in tried] == [False, False, True]  # type: ignore[index]
    # the coat off is behind by many standard errors: the picture asks for it
    together = tried[0]  # type: ignore[index]
    assert together["behind"] > 2 * scene_plain.PLAIN_LEAD * together["standard_error"]
    assert point[params.INDEX["sheen"]] == 0.0 and point[params.INDEX["clearcoat"]] > 0.4  # held off, coat kept
    assert len(losses) == 2 and len(heard) == 2 * 3
    # a material without optional lobes: nothing to try, nothing rendered
    plain_truth = truth.copy()
    plain_truth[params.INDEX["clearcoat"]] = 0.0
    point, done, losses = scene_plain.plain(judge, problem, plain_truth, 2, seed=0)
    np.testing.assert_array_equal(point, plain_truth)
    assert done == {"on": [], "silent": [], "tried": [], "off": []} and losses == []


def test_a_lobe_that_cannot_show_is_turned_off_without_a_try(red_knot_fit):
    # sheen belongs to Mitsuba's diffuse lobe: on a full metal, or through full transmission, it cannot show
    gold = presets.preset("gold")
    assert gold[params.INDEX["metallic"]] == 1.0 and scene_plain.silent(gold) == ("sheen",)
    glass = presets.preset("glass")
    assert glass[params.INDEX["spec_trans"]] == 1.0 and scene_plain.silent(glass) == ("sheen",)
    assert scene_plain.silent(presets.preset("red-plastic")) == ()
    renderer, target, weights = red_knot_fit
    judge = scene_judge.Judge(renderer, target, weights)
    problem = scene_fit.problem_of(renderer, target, weights, "prb")
    sheened = params.to_unit(gold)
    sheened[params.INDEX["sheen"]] = 0.3
    # the same picture, but for float rounding (a lobe of weight 0 is still evaluated where sheen is on)
    np.testing.assert_allclose(judge.render(params.from_unit(sheened)), judge.render(gold), rtol=0, atol=1e-4)
    point, done, losses = scene_plain.plain(judge, problem, sheened, 2, seed=0)
    np.testing.assert_array_equal(point, params.to_unit(gold))  # sheen off, nothing else to try
    assert done == {"on": [], "silent": ["sheen"], "tried": [], "off": []} and losses == []
