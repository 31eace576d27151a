import numpy as np
import pytest
from helpers import R, random_model

from matfit import fit, images, presets, verify
from matfit.params import to_unit
from matfit.render import Renderer


@pytest.fixture(scope="module")
def model():
    return random_model()


@pytest.fixture(scope="module")
def renderer32():
    return Renderer(R, 8)


def test_candidates_start_first_then_distinct_ends(model):
    target = model.decode(np.full((1, 19), 0.3))[0]
    result = fit.fit(model, target, fit.Settings(method="lbfgsb", starts=2, iterations=5))
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
    result = fit.fit(
        model,
        target,
        fit.Settings(method="lbfgsb", starts=3, iterations=30),
        extra=to_unit(presets.preset("jade"))[None],
    )
    assert result.chosen == "extra-1" or result.start_rmse <= result.candidate_rmse["extra-1"]
    checked = verify.verify(renderer32, result, target)
    assert checked.rmse <= checked.start_rmse
    if checked.chosen == "start":
        assert checked.rmse == checked.figures["start"]
    else:  # an end point kept: it led in both renders
        assert checked.rmse == min(checked.figures.values())
        assert checked.confirmation[checked.chosen] < checked.confirmation["start"]
    again = images.srgb_encode(renderer32.render(fit.params.from_unit(checked.unit), seed=verify.SEED, spp=verify.SPP))
    # the kept render is the chosen candidate's (two renders of one material may differ in the last bits)
    np.testing.assert_allclose(again, checked.rendered, atol=1e-5)
    assert set(checked.figures) == set(verify.candidates(result)) and len(checked.figures) >= 2  # every end rendered


def test_the_verification_table_judges_every_spp_by_one_independent_render(model, renderer32, monkeypatch):
    from matfit import bench

    monkeypatch.setattr(bench, "JUDGE_SPP", 32)  # a tiny judge: the table's logic, not its figures
    units = np.stack([np.full(19, 0.3), np.full(19, 0.6)])
    targets = bench.Targets(
        units, np.stack([images.srgb_encode(renderer32.render(fit.params.from_unit(u))) for u in units])
    )
    results = [
        fit.fit(model, target, fit.Settings(method="lbfgsb", starts=2, iterations=5)) for target in targets.images
    ]
    table = bench.verification_table(renderer32, results, targets, spps=(4, 8))
    rows = table.splitlines()
    assert len(rows) == 2 + 2 + 2 and rows[-1].startswith("| the best-of-n start |")
    assert rows[3].startswith("| 8 |") and rows[3].endswith("| 2/2 |")  # the highest spp agrees with itself
    kept = {int(row.split("|")[1]): float(row.split("|")[3]) for row in rows[2:4]}
    oracle, start = (float(row.split("|")[3]) for row in rows[4:6])
    assert all(oracle <= figure + 1e-9 for figure in kept.values()) and oracle <= start + 1e-9


def test_the_judged_table_compares_answers_under_one_independent_render(renderer32, monkeypatch):
    from matfit import bench

    monkeypatch.setattr(bench, "JUDGE_SPP", 8)
    units = np.stack([np.full(19, 0.3), np.full(19, 0.6)]).astype(np.float32)
    targets = bench.Targets(
        units, np.stack([images.srgb_encode(renderer32.render(fit.params.from_unit(u), spp=64)) for u in units])
    )
    far = [np.full(19, 0.9), np.full(19, 0.05)]
    table = bench.judged_table(renderer32, {"start": far, "truth again": list(units)}, targets, "start")
    rows = [row.split("|") for row in table.splitlines()[2:]]
    floor = float(rows[0][2])
    assert rows[1][1].strip() == "start" and rows[1][4].strip() == "2/2"
    # the true parameters again, with the same judge seeds: exactly the floor, and better than the far start
    assert float(rows[2][2]) == pytest.approx(floor) and float(rows[2][3]) == pytest.approx(0.0, abs=1e-3)
    assert float(rows[1][2]) > floor + 5 and rows[2][4].strip() == "2/2"


def test_an_end_point_is_kept_only_when_its_lead_holds_in_the_second_render():
    figures = {"start": 5.0, "end-1": 4.0, "end-2": 4.5}
    assert verify.keep(figures, {"start": 5.1, "end-1": 4.2}) == "end-1"
    assert verify.keep(figures, {"start": 4.9, "end-1": 5.0}) == "start"  # the lead was the first render's noise
    assert verify.keep(figures, {"start": 4.9, "end-1": 4.9}) == "start"  # a tie keeps the start
    assert verify.keep({"start": 3.0, "end-1": 3.5}, {}) == "start"  # nothing to confirm
    assert verify.keep(figures, {}) == "start"  # an unconfirmed lead is not kept


def test_prefetch_start_asks_for_the_very_renders_verify_makes_of_the_start():
    from matfit import params
    from matfit.render import Background

    start = np.asarray(to_unit(presets.preset("jade")), np.float32)  # float32, as the fit hands it over
    expected = params.from_unit(np.asarray(start, np.float64))  # what `verify.candidates` renders
    for corrections, seeds in ((0, {verify.SEED}), (2, {verify.CONFIRM_SEED})):
        background = Background(R, 4)
        verify.prefetch_start(background, start, corrections, spp=4)
        keys = set(background._prefetched)
        assert keys == {Background._key(expected, seed, 4) for seed in seeds}
        background.renderer()
