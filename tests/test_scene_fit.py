"""The fit in a scene of the user's own (`fitting/scene_fit`): tiny scenes and few steps, real renders."""

import numpy as np
import pytest

from matfit import images, params
from matfit.errors import SceneError
from matfit.fitting import refine, scene_fit, scene_plain
from matfit.rendering import presets, scene_file

pytestmark = pytest.mark.usefixtures("tiny_scene_fits")  # tests/conftest.py


def test_the_starts_keep_the_colour_over_metallic_and_roughness_or_roughness_for_glass():
    plastic = presets.preset("red-plastic")
    found = scene_fit.starts(plastic)
    assert [name for name, _ in found] == [
        "given",
        "metallic 0.0 roughness 0.15",
        "metallic 0.0 roughness 0.55",
        "metallic 1.0 roughness 0.15",
        "metallic 1.0 roughness 0.55",
    ]
    colour = slice(params.INDEX["base_color_r"], params.INDEX["base_color_b"] + 1)
    assert all(np.array_equal(values[colour], plastic[colour]) for _, values in found)
    assert found[3][1][params.INDEX["metallic"]] == 1.0 and found[3][1][params.INDEX["roughness"]] == 0.15
    # glass: all of it transmitted already, and clear glass is its roughness 0.02 start: one descent each
    glass = scene_fit.starts(presets.preset("glass"))
    assert [name for name, _ in glass] == ["given", "roughness 0.02", "roughness 0.35"]
    partly = scene_fit._probe(presets.preset("jade"), spec_trans=0.8, roughness=0.2, clearcoat=0.3)
    found = scene_fit.starts(partly)
    assert [name for name, _ in found] == [
        "given",
        "roughness 0.02",
        "roughness 0.35",
        "all transmitted",
        "clear glass",
    ]
    np.testing.assert_array_equal(found[3][1], scene_fit._probe(partly, spec_trans=1.0))
    assert found[4][1][params.INDEX["spec_trans"]] == 1.0 and found[4][1][params.INDEX["clearcoat"]] == 0.0
    assert [name for name, _ in scene_fit.starts(scene_fit._probe(partly, roughness=0.35))] == [
        "given",
        "roughness 0.02",
        "all transmitted",
        "clear glass",
    ]


def test_a_picture_of_another_aspect_is_refused_before_any_render(knot):
    with pytest.raises(SceneError, match=r"is 64x64 \(aspect 1.000\), the scene's camera 32x24"):
        scene_fit.check_aspect(knot, 64, 64, "the picture")
    scene_fit.check_aspect(knot, 48, 64, "the picture")  # the camera's aspect at another size is the scene's


def test_the_region_holds_the_shape_and_its_shadow_not_the_whole_picture(knot):
    renderer = scene_file.Renderer(knot, knot.size(64))
    region, without = scene_fit.region(renderer)
    assert region.shape == (48, 64) and without.shape == (48, 64, 3)
    assert 0.1 < region.mean() < 0.9
    assert region[24, 32]  # the knot sits in the middle of the picture


def test_a_fit_from_a_start_far_off_comes_closer_and_says_what_the_view_decides(knot, red_picture):
    start = presets.preset("red-plastic").copy()
    start[params.INDEX["base_color_r"] : params.INDEX["base_color_b"] + 1] = [0.2, 0.5, 0.2]
    start[params.INDEX["roughness"]] = 0.7
    heard = []
    outcome = scene_fit.fit(knot, red_picture, start=start, steps=8, progress=lambda *a: heard.append(a))
    assert outcome.accepted and outcome.rmse < 0.8 * outcome.start_rmse
    np.testing.assert_array_equal(outcome.start_values, start)
    assert outcome.integrator == "prb" and outcome.target.shape == (24, 32, 3)  # FIT_SIZE, tiny
    # a quarter of the steps a start, then 8, then a quarter more if a parameter left at a trapping bound moved, and
    # a quarter more if optional lobes were turned off (the steps of the try kept)
    moved = outcome.bounds["moved"] is not None
    plainer = bool(outcome.plain["off"])
    assert len(outcome.starts) == 5 and len(outcome.losses) == 2 + 8 + (2 if moved else 0) + (2 if plainer else 0)
    assert [a[0] for a in heard][:10] == ["starts"] * 10 and heard[-1][0] == "judge"
    tries = len(outcome.plain["tried"])  # type: ignore[arg-type]
    assert [a[0] for a in heard].count("plain") == 2 * tries
    assert heard[-1][1] == heard[-1][2] == 5 * 2 + 8 + 2 + 2 * (1 + len(scene_plain.OPTIONAL))
    assert set(outcome.ranges) == set(params.NAMES)
    assert outcome.ranges["base_color_r"]["verdict"] == "decided"
    assert outcome.ranges["density"]["verdict"].startswith("not decided")  # an opaque fit shows no medium


def test_a_fit_holds_its_optional_lobes_and_a_transmissive_ones_transmission_for_half_the_descent():
    lobes = (params.INDEX["clearcoat"], params.INDEX["sheen"], params.INDEX["anisotropic"])
    assert scene_fit.holding(presets.preset("red-plastic"), 48) == (lobes, 24)
    assert scene_fit.holding(presets.preset("gold"), 7) == (lobes, 3)
    assert scene_fit.holding(presets.preset("glass"), 48) == ((params.INDEX["spec_trans"], *lobes), 24)
    half = scene_fit._probe(presets.preset("jade"), spec_trans=0.5)  # transmissive from 0.5 on, as `starts` splits
    assert scene_fit.holding(half, 48)[0] == (params.INDEX["spec_trans"], *lobes)
    assert scene_fit.holding(scene_fit._probe(half, spec_trans=0.49), 48)[0] == lobes


def test_a_transmissive_fit_descends_from_every_start_and_keeps_the_one_that_ends_closest(knot, monkeypatch):
    glass = presets.preset("glass")
    picture = scene_file.Renderer(knot, knot.size(64)).render(glass, seed=11, spp=64)
    start = scene_fit._probe(glass, spec_trans=0.8, roughness=0.2)
    descents, path = [], refine.path

    def heard_path(problem, point, steps, **options):  # the real descent, its holding noted
        descents.append((steps, options["hold"], options["held"]))
        return path(problem, point, steps, **options)

    monkeypatch.setattr(refine, "path", heard_path)
    outcome = scene_fit.fit(knot, picture, start=start, steps=4)
    held = scene_fit.holding(start, 4)
    assert held == ((params.INDEX["spec_trans"], *(params.INDEX[n] for n in scene_plain.OPTIONAL)), 2)
    # the five starts' short runs hold it all through (1 step each), their descents the first half (2 of 4), then the
    # chosen start's two more descents alike
    assert descents[:5] == [(1, held[0], 1)] * 5 and descents[5:12] == [(4, held[0], 2)] * 7
    names = ["given", "roughness 0.02", "roughness 0.35", "all transmitted", "clear glass"]
    assert [s["name"] for s in outcome.starts] == names
    assert outcome.again["start"] in names and outcome.again["kept"] in outcome.again["errors"]
    assert list(outcome.again["errors"]) == ["descent 1", "descent 2", "descent 3", "mean"]
    chosen = next(s for s in outcome.starts if s["name"] == outcome.again["start"])
    assert outcome.again["errors"]["descent 1"] == chosen["descended"] == min(s["descended"] for s in outcome.starts)
    assert all(s["descended"] > 0 for s in outcome.starts)  # each went on the 4 steps, judged where it ended
    assert outcome.integrator == "prb" and outcome.rmse <= outcome.start_rmse  # glass shows no medium
    # the chosen start's short run, its descent, a move off a bound, optional lobes off
    moved, plainer = outcome.bounds["moved"] is not None, bool(outcome.plain["off"])
    assert len(outcome.losses) == 1 + 4 + (1 if moved else 0) + (1 if plainer else 0)


def test_a_coloured_mediums_fit_steps_the_quieter_way_and_by_channel_descends_again_once(tmp_path, monkeypatch):
    from matfit.rendering import scene_library

    box = scene_file.read(scene_library.write(str(tmp_path), "box", "sky", width=32, height=24), "object")
    jade = presets.preset("jade")
    picture = scene_file.Renderer(box, box.size(64)).render(jade, seed=11, spp=64)
    noise = []
    measured = refine.channel_noise

    def heard(problem, unit, spp, seeds):  # the real measurement, its figures noted
        noise.append(measured(problem, unit, spp, seeds))
        return noise[-1]

    monkeypatch.setattr(refine, "channel_noise", heard)
    outcome = scene_fit.fit(box, picture, start=scene_fit._probe(jade, roughness=0.3), steps=4)
    ((one, by_channel),) = noise
    assert outcome.residual["by_channel"] is (by_channel < one) and outcome.integrator == "prbvolpath"
    assert outcome.residual["noise"] == [round(1e6 * one, 2), round(1e6 * by_channel, 2)]
    descents = ["descent 1", "descent 2"] if by_channel < one else ["descent 1", "descent 2", "descent 3"]
    assert list(outcome.again["errors"]) == [*descents, "mean"]
    assert outcome.rmse <= outcome.start_rmse
    glass = scene_fit.fit(box, picture, start=scene_fit._probe(presets.preset("glass"), spec_trans=0.8), steps=1)
    assert "by_channel" not in glass.residual and len(noise) == 1  # a grey medium: one render, nothing measured


@pytest.mark.parametrize("darkening", [0.0, 1e9])
def test_an_opaque_fits_descent_takes_the_linear_residual_where_its_images_darken(
    knot, red_picture, darkening, monkeypatch
):
    # where a step's image encodes darker than its mean by more than DARKENING, the descent and the stages after it
    # step on the residual linear in the image; the short runs before it, and every step where it does not, encoded
    monkeypatch.setattr(scene_fit, "DARKENING", darkening)
    linear, path = [], refine.path

    def heard_path(problem, point, steps, **options):
        linear.append(problem.linear)
        return path(problem, point, steps, **options)

    monkeypatch.setattr(refine, "path", heard_path)
    start = presets.preset("red-plastic").copy()
    start[params.INDEX["roughness"]] = 0.6
    outcome = scene_fit.fit(knot, red_picture, start=start, steps=4)
    fired = darkening == 0.0
    assert outcome.residual["linear"] is fired and outcome.residual["darkening"] > 0  # type: ignore[operator]
    assert linear[:5] == [False] * 5 and linear[5:] == [fired] * len(linear[5:]) and len(linear) > 5


def test_a_fit_never_returns_something_worse_than_its_start(knot, red_picture):
    truth = presets.preset("red-plastic")
    outcome = scene_fit.fit(knot, red_picture, start=truth, steps=1)
    assert outcome.rmse <= outcome.start_rmse
    if not outcome.accepted:
        np.testing.assert_array_equal(outcome.values, truth)


def test_a_picture_of_another_scene_or_without_the_shape_is_refused(knot, red_picture):
    noise = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    with pytest.raises(SceneError, match="is not a render of"):
        scene_fit.fit(knot, noise, steps=1)
    without = scene_file.Renderer(knot, knot.size(64)).render_without(seed=2, spp=128)
    with pytest.raises(SceneError, match="shows the scene without the shape"):
        scene_fit.fit(knot, without, steps=1)


def test_a_mask_decides_where_the_fit_looks(knot, red_picture):
    mask = np.zeros((48, 64), np.float32)
    mask[:, :32] = 1.0
    outcome = scene_fit.fit(knot, red_picture, start=presets.preset("red-plastic"), mask=mask, steps=1)
    # the mask decides where, each pixel's precision how much (`precision`: at most the mask's own weight)
    assert outcome.weights[:, 20:].max() < 0.01 and outcome.weights[:, :12].min() > 0.05  # at FIT_SIZE, tiny
    assert outcome.weights.max() <= 1.0 and np.median(outcome.weights[:, :12]) < 0.9
    with pytest.raises(SceneError, match="the mask is black"):
        scene_fit.fit(knot, red_picture, mask=np.zeros((48, 64), np.float32), steps=1)
    # the figure is the noise-free error; the render's own RMSE counts its noise too
    assert 0 < outcome.rmse < images.rmse(outcome.rendered, outcome.target, outcome.weights)


def test_each_pixel_is_weighted_by_how_little_its_render_is_noise():
    rng = np.random.default_rng(5)
    renders = np.full((2, 20, 40, 3), 0.5)
    for columns, spread in ((slice(0, 10), 0.001), (slice(10, 30), 0.01), (slice(30, 40), 0.1)):  # the last: a caustic
        renders[:, :, columns] += rng.normal(0, spread, (2, 20, columns.stop - columns.start, 3))
    weights = np.ones((20, 40), np.float32)
    weighted = scene_fit.precision((renders[0], renders[1]), weights)
    assert weighted[:, :8].min() > 0.95  # a hundredth of the median's variance: its weight kept
    assert np.median(weighted[:, 13:27]) == pytest.approx(0.5, abs=0.05)  # the median's: half
    assert weighted[:, 33:].max() < 0.05  # a hundred times the median's
    region = np.zeros((20, 40), np.float32)
    region[:, :10] = 1.0  # the median is the weighted pixels' own
    inside = scene_fit.precision((renders[0], renders[1]), region)
    assert inside[:, 10:].max() == 0.0 and np.median(inside[:, :8]) == pytest.approx(0.5, abs=0.05)
    np.testing.assert_array_equal(scene_fit.precision((renders[0], renders[0]), weights), weights)  # no noise


def test_the_path_holds_every_visited_point_and_descend_keeps_its_lowest_loss(red_knot_fit):
    renderer, target, weights = red_knot_fit
    problem = scene_fit.problem_of(renderer, target, weights, "prb")
    assert problem.robust == scene_fit.ROBUST == 3.0  # Huber's loss, its corner 3 robust spreads
    assert scene_fit.problem_of(renderer, target, weights, "prb", linear=True).robust is None  # a transmissive fit's
    start = params.to_unit(presets.preset("red-plastic"))
    start[params.INDEX["base_color_g"]] = 0.6  # a greener red: the steps bring it back down
    points, losses = refine.path(problem, start, 3, seed=7)
    assert len(points) == 4 and len(losses) == 3
    np.testing.assert_array_equal(points[0], start)
    assert points[-1][params.INDEX["base_color_g"]] < 0.6 - 0.02  # Adam's three steps of 0.02 each, downhill
    held, held_losses = refine.path(problem, start, 3, seed=7, hold=(params.INDEX["base_color_g"],), held=2)
    assert [p[params.INDEX["base_color_g"]] for p in held[:3]] == [0.6, 0.6, 0.6]  # held for two steps, then free
    assert held[3][params.INDEX["base_color_g"]] < 0.6 - 0.01
    assert held[1][params.INDEX["base_color_r"]] != start[params.INDEX["base_color_r"]]  # the others move meanwhile
    point, again = refine.descend(problem, start, 3, seed=7)
    assert again == pytest.approx(losses, rel=1e-3)  # the same seeds: the same losses, but for the threads' order
    # a step that holds takes Huber's loss (a scene problem's `robust`): at the same seed, the same image, under the
    # squares where a residual is past the corner
    assert held_losses[0] < 0.8 * losses[0]  # 14.4 against 25.7
    np.testing.assert_allclose(point, points[int(np.argmin(again))], atol=1e-4)  # its gradients' sums likewise
