"""A descent's answer and the stages that descend again from it (`fitting/scene_descent`): tiny scenes and few steps,
real renders."""

import numpy as np
import pytest

from matfit import params
from matfit.fitting import refine, scene_descent, scene_fit, scene_judge
from matfit.rendering import presets

pytestmark = pytest.mark.usefixtures("tiny_scene_fits")  # tests/conftest.py


def test_the_answer_is_the_candidate_of_lowest_noise_free_error_not_the_lowest_step_loss(red_knot_fit):
    renderer, target, weights = red_knot_fit
    truth = params.to_unit(presets.preset("red-plastic"))
    green = truth.copy()
    green[params.INDEX["base_color_g"]] = 0.8
    # a lucky step's loss at a green point (winner's curse) and the truth last: the judge's render decides
    judge = scene_judge.Judge(renderer, target, weights)
    point, squared = scene_descent.closest(judge, [green, green, truth, truth], [1.0, 9.0, 9.0])
    np.testing.assert_array_equal(point, truth)
    assert squared == judge.squared(params.from_unit(truth))
    assert scene_judge.root(judge.squared(params.from_unit(green))) > scene_judge.root(squared) + 10  # far from it
    assert scene_descent.closest(judge, [truth], []) == (truth, squared)


def test_the_chosen_start_descends_again_with_other_seeds_and_the_closest_answer_or_their_mean_is_kept(
    red_knot_fit, monkeypatch
):
    renderer, target, weights = red_knot_fit
    judge = scene_judge.Judge(renderer, target, weights)
    problem = scene_fit.problem_of(renderer, target, weights, "prb", linear=True)
    start = params.to_unit(scene_fit._probe(presets.preset("red-plastic"), base_color_r=0.3, roughness=0.5))
    points, losses = refine.path(problem, start, 3, seed=refine.SEED + 1)
    answer, squared = scene_descent.closest(judge, points, losses)
    chosen = {"name": "given", "point": start, "answer": answer, "answer_squared": squared, "more": losses}
    descents, path = [], refine.path

    def heard_path(problem, point, steps, **options):  # the real descent, where it starts and its seeds noted
        descents.append((point.copy(), steps, options["seed"]))
        found = path(problem, point, steps, **options)
        answers.append(found)
        return found

    answers: list = []
    monkeypatch.setattr(refine, "path", heard_path)
    kept, kept_losses, done = scene_descent.again(judge, problem, chosen, 3, seed=refine.SEED + 1, hold=(), held=0)
    # two more descents of the same steps from the chosen start's point, their seeds apart from its and each other's
    assert [(steps, seed) for _, steps, seed in descents] == [(3, refine.SEED + 1001), (3, refine.SEED + 2001)]
    assert all(np.array_equal(point, start) for point, _, _ in descents)
    assert not np.array_equal(answers[0][0][-1], answers[1][0][-1])  # other seeds, other descents
    errors = done["errors"]
    assert done["start"] == "given" and errors["descent 1"] == round(scene_judge.root(squared), 3)
    assert errors[done["kept"]] == min(errors.values())  # the judge's pick: the answer of lowest noise-free error
    mean = np.mean([answer, *(scene_descent.closest(judge, *found)[0] for found in answers)], axis=0)
    candidates = {"descent 1": answer, "mean": mean} | {
        f"descent {k + 2}": scene_descent.closest(judge, *found)[0] for k, found in enumerate(answers)
    }
    np.testing.assert_allclose(kept, candidates[done["kept"]])
    assert errors["mean"] == round(scene_judge.root(judge.squared(params.from_unit(mean))), 3)
    assert len(kept_losses) == 3


def test_roughness_the_descent_left_at_0_is_tried_inward_and_a_closer_point_kept(red_knot_fit):
    renderer, target, weights = red_knot_fit
    problem = scene_fit.problem_of(renderer, target, weights, "prb")
    stuck = params.to_unit(presets.preset("red-plastic"))  # the truth (roughness 0.3) but for its roughness at 0
    stuck[params.INDEX["roughness"]] = 0.0
    point, done, losses = scene_descent.off_bounds(
        scene_judge.Judge(renderer, target, weights), problem, stuck, 2, seed=0
    )
    assert done["tried"] == 2 * len(scene_descent.INWARD) == 4  # roughness and sheen are at 0; clearcoat is not
    assert done["moved"] == "roughness" and len(losses) == 2
    assert point[params.INDEX["roughness"]] >= 0.1
    stuck_error, moved_error = done["errors"][0], min(done["errors"][1:])  # noise-free, from two seeds' renders
    assert moved_error < stuck_error - 0.3  # the truth's roughness is closer than 0
    free = params.to_unit(presets.preset("red-plastic"))
    free[params.INDEX["sheen"]] = 0.3
    kept, nothing, none = scene_descent.off_bounds(
        scene_judge.Judge(renderer, target, weights), problem, free, 2, seed=0
    )
    assert nothing == {"error": nothing["error"], "tried": 0, "moved": None} and none == []
    np.testing.assert_array_equal(kept, free)
