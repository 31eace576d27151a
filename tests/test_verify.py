import numpy as np
import pytest
from helpers import Noisy, R, random_model

from matfit import images
from matfit.fitting import search, verify
from matfit.params import to_unit
from matfit.rendering import presets
from matfit.rendering.engine import Renderer


@pytest.fixture(scope="module")
def model():
    return random_model()


@pytest.fixture(scope="module")
def renderer32():
    return Renderer(R, 8)


def test_candidates_start_first_then_distinct_ends(model):
    target = model.decode(np.full((1, 19), 0.3))[0]
    result = search.neural_search(model, target, settings=search.Settings(method="lbfgsb", starts=2, iterations=5))
    pool = verify.candidates(result)
    names = list(pool)
    assert names[0] == "start" and 2 <= len(names) <= verify.CANDIDATES
    np.testing.assert_array_equal(pool["start"], result.start)
    assert all(name.startswith("end-") for name in names[1:])
    points = np.stack(list(pool.values()))
    assert len({tuple(np.round(p, 6)) for p in points}) == len(points)


def test_a_fooled_decoder_never_makes_the_answer_physically_worse_than_the_start(model, renderer32):
    # A random decoder knows nothing of the scene: its optimum for a jade render is physically arbitrary.
    target = images.srgb_encode(renderer32.render(presets.preset("jade"), seed=5))
    result = search.neural_search(
        model,
        target,
        settings=search.Settings(method="lbfgsb", starts=3, iterations=30),
        extra=to_unit(presets.preset("jade"))[None],
    )
    assert result.chosen == "extra-1" or result.start_rmse <= result.candidate_rmse["extra-1"]
    checked = verify.verify_candidates(renderer32, result, target)
    assert checked.rmse <= checked.start_rmse and checked.rmse == checked.figures[checked.chosen]
    assert checked.figures["start"] == checked.start_rmse and checked.chosen == min(
        checked.figures, key=checked.figures.get
    )
    assert set(checked.figures) == set(verify.candidates(result)) == set(checked.batches) and len(checked.figures) >= 2
    assert all(verify.BATCHES <= count <= verify.MAX_BATCHES for count in checked.batches.values())
    # every other candidate is decided (LEAD standard errors behind), unless the kept one reached MAX_BATCHES
    assert set(checked.margins) == set(checked.figures) - {checked.chosen}
    assert checked.batches[checked.chosen] == verify.MAX_BATCHES or min(checked.margins.values()) >= verify.LEAD
    again = [
        images.srgb_encode(renderer32.render(search.params.from_unit(checked.unit), seed=verify.BATCH_SEED + j, spp=64))
        for j in range(checked.batches[checked.chosen])
    ]
    # the kept render is the mean of the chosen candidate's batches (two renders may differ in the last bits)
    np.testing.assert_allclose(np.mean(again, axis=0), checked.rendered, atol=1e-5)
    assert len(checked.renders) == checked.batches[checked.chosen]  # the batches themselves, for the clean answer
    np.testing.assert_allclose(np.mean(checked.renders, axis=0), checked.rendered, atol=1e-6)


def test_the_verification_table_judges_every_spp_by_one_independent_render(model, renderer32, monkeypatch):
    from matfit.app.bench import fits, reachable

    monkeypatch.setattr(fits, "JUDGE_SPP", 32)  # a tiny judge: the table's logic, not its figures
    units = np.stack([np.full(19, 0.3), np.full(19, 0.6)])
    targets = reachable.Targets(
        units, np.stack([images.srgb_encode(renderer32.render(search.params.from_unit(u))) for u in units])
    )
    results = [
        search.neural_search(model, target, settings=search.Settings(method="lbfgsb", starts=2, iterations=5))
        for target in targets.images
    ]
    table = fits.verification_table(renderer32, results, targets, spps=(4, 8))
    rows = table.splitlines()
    assert len(rows) == 2 + 2 + 2 and rows[-1].startswith("| the best-of-n start |")
    assert rows[3].startswith("| 8 |") and rows[3].endswith("| 2/2 |")  # the highest spp agrees with itself
    kept = {int(row.split("|")[1]): float(row.split("|")[3]) for row in rows[2:4]}
    oracle, start = (float(row.split("|")[3]) for row in rows[4:6])
    assert all(oracle <= figure + 1e-9 for figure in kept.values()) and oracle <= start + 1e-9


def test_the_judged_table_compares_answers_under_one_independent_render(renderer32, monkeypatch):
    from matfit.app.bench import fits, reachable

    monkeypatch.setattr(fits, "JUDGE_SPP", 8)
    units = np.stack([np.full(19, 0.3), np.full(19, 0.6)]).astype(np.float32)
    targets = reachable.Targets(
        units, np.stack([images.srgb_encode(renderer32.render(search.params.from_unit(u), spp=64)) for u in units])
    )
    far = [np.full(19, 0.9), np.full(19, 0.05)]
    table = fits.judged_table(renderer32, {"start": far, "truth again": list(units)}, targets, "start")
    rows = [row.split("|") for row in table.splitlines()[2:]]
    floor = float(rows[0][2])
    assert rows[1][1].strip() == "start" and rows[1][4].strip() == "2/2"
    # the true parameters again, with the same judge seeds: exactly the floor, and better than the far start
    assert float(rows[2][2]) == pytest.approx(floor) and float(rows[2][3]) == pytest.approx(0.0, abs=1e-3)
    assert float(rows[1][2]) > floor + 5 and rows[2][4].strip() == "2/2"


def test_the_squared_error_estimate_is_the_mean_of_cross_terms_and_its_jackknife_leaves_one_render_out():
    rng = np.random.default_rng(3)
    target = rng.uniform(0, 1, (4, 4, 3))
    renders = rng.uniform(0, 1, (5, 4, 4, 3))
    weights = rng.uniform(0, 1, (4, 4))

    def cross(subset):  # the mean over ordered pairs i != j, computed pair by pair
        terms = [
            np.sum(weights[..., None] * (subset[i] - target) * (subset[j] - target)) / (3 * weights.sum())
            for i in range(len(subset))
            for j in range(len(subset))
            if i != j
        ]
        return np.mean(terms)

    estimate, out = verify.squared_error(list(renders), target, weights)
    assert estimate == pytest.approx(cross(renders), rel=1e-9)
    np.testing.assert_allclose(out, [cross(np.delete(renders, k, axis=0)) for k in range(5)], rtol=1e-9)
    with pytest.raises(ValueError, match="2 renders: the estimate's jackknife needs at least 3"):
        verify.squared_error(list(renders[:2]), target, weights)


def test_the_estimate_leaves_out_the_renders_noise_which_a_renders_rmse_counts():
    # A material off by 0.05 everywhere, rendered with noise of spread 0.2: one render's squared error is about
    # 0.05^2 + 0.2^2; the cross terms of independent renders estimate 0.05^2.
    rng = np.random.default_rng(4)
    target = np.full((64, 64, 3), 0.5)
    renders = [target + 0.05 + rng.normal(0, 0.2, target.shape) for _ in range(8)]
    weights = np.ones((64, 64))
    estimate, _ = verify.squared_error(renders, target, weights)
    assert estimate == pytest.approx(0.05**2, rel=0.1)  # within 3.5 of its standard errors
    assert np.mean((renders[0] - target) ** 2) == pytest.approx(0.05**2 + 0.2**2, rel=0.05)


def scripted(model, materials_of):
    target = np.full((R, R, 3), 0.4, np.float32)
    result = search.neural_search(model, target, settings=search.Settings(method="lbfgsb", starts=2, iterations=5))
    pool = verify.candidates(result, count=2)
    renderer = Noisy(target, {name: (search.params.from_unit(pool[name]), *materials_of[name]) for name in pool})
    return verify.verify_candidates(renderer, result, target, count=2), renderer


def test_the_truly_closer_candidate_is_kept_though_its_noise_makes_each_render_look_worse(model):
    # end-1 is 0.02 off and noisy (spread 0.1), the start 0.05 off and clean: a render of end-1 is further from the
    # target than the start's (0.1^2 + 0.02^2 > 0.05^2), the material closer
    checked, renderer = scripted(model, {"start": (0.05, 0.0), "end-1": (0.02, 0.1)})
    assert checked.chosen == "end-1"
    assert checked.figures["end-1"] < 255 * 0.035  # 0.02 within its estimate's noise at three batches
    assert checked.figures["start"] == pytest.approx(255 * 0.05, rel=1e-3)  # no noise: exactly its offset
    assert checked.margins["start"] >= verify.LEAD and checked.batches == {"start": 3, "end-1": 3}
    # batch j of both materials with the same seed, no other render
    seeds = [verify.BATCH_SEED + j for j in range(verify.BATCHES)]
    assert sorted(renderer.asked) == sorted((name, seed) for name in ("start", "end-1") for seed in seeds)


def test_a_lead_within_the_noise_renders_more_batches_and_a_tie_keeps_the_start(model):
    checked, renderer = scripted(model, {"start": (0.03, 0.0), "end-1": (0.03, 0.0)})  # the same picture
    assert checked.chosen == "start" and checked.batches == {"start": 3, "end-1": 3}  # no spread: decided
    checked, renderer = scripted(model, {"start": (0.0300, 0.3), "end-1": (0.0301, 0.25)})
    # a difference far below the noise (their spreads differ: the common noise does not cancel): batches up to the
    # cap, then the better estimate, whichever it is
    assert checked.batches == {"start": verify.MAX_BATCHES, "end-1": verify.MAX_BATCHES}
    assert checked.chosen == min(checked.figures, key=checked.figures.get)
    assert abs(checked.margins[{"start": "end-1", "end-1": "start"}[checked.chosen]]) < verify.LEAD
    assert len(renderer.asked) == 2 * verify.MAX_BATCHES


def test_verification_is_bit_identical_from_run_to_run(model):
    target = np.full((R, R, 3), 0.4, np.float32)
    result = search.neural_search(model, target, settings=search.Settings(method="lbfgsb", starts=2, iterations=5))
    runs = [verify.verify_candidates(Renderer(R, 8, threads=1), result, target, count=2, spp=8) for _ in range(2)]
    assert runs[0].figures == runs[1].figures and runs[0].margins == runs[1].margins
    np.testing.assert_array_equal(runs[0].rendered, runs[1].rendered)


def test_prefetch_start_asks_for_the_very_renders_verify_makes_of_the_start():
    from matfit import params
    from matfit.rendering.process import Background

    start = np.asarray(to_unit(presets.preset("jade")), np.float32)  # float32, as the fit hands it over
    expected = params.from_unit(np.asarray(start, np.float64))  # what `verify.candidates` renders
    seeds = {verify.BATCH_SEED + j for j in range(verify.BATCHES)}  # its first batches, with or without corrections
    # Every background is kept until none renders: freeing one's scene on this thread while another's thread renders
    # crashed Mitsuba once (a segmentation fault in CI).
    backgrounds = []
    for corrections in (0, 2):
        background = Background(R, 4)
        backgrounds.append(background)
        verify.prefetch_start(background, start, corrections=corrections, spp=4)
        keys = set(background._prefetched)
        assert keys == {Background._key(expected, seed, 4) for seed in seeds}
        background.renderer()
