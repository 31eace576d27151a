import numpy as np
import pytest
from helpers import decode, random_model, true_point

from matfit import images
from matfit.app.bench import fits, optimisers, reachable, scenes, suite_report
from matfit.app.bench.sequence import black_level, sequence_table
from matfit.fitting import scene_fit, scene_judge, search


@pytest.fixture(scope="module")
def model():
    return random_model()


def test_black_level_maps_the_black_point_to_zero():
    values = np.array([0.0, 0.2, 0.6, 1.0])
    np.testing.assert_allclose(black_level(values, 0.2), [0.0, 0.0, 0.5, 1.0])
    np.testing.assert_array_equal(black_level(values, 0.0), values)


@pytest.mark.slow
def test_compare_and_tables(model):
    targets = reachable.Targets(
        np.stack([true_point(1), true_point(2)]), np.stack([decode(model, true_point(1)), decode(model, true_point(2))])
    )
    configurations = {
        "nn (best-of-n)": search.Settings(method="nn"),
        "hybrid 60": search.Settings(method="hybrid", evaluations=60),
    }
    table = fits.compare(model, targets, configurations)
    assert np.all(
        table["hybrid 60"]["rmse"] <= table["nn (best-of-n)"]["rmse"] + 1e-6
    )  # hybrid starts from the nn answer
    text = fits.markdown(table, "hybrid 60", {})
    assert "| nn (best-of-n) |" in text and "2/2" in text
    frames = [black_level(decode(model, true_point(3)), level) for level in (0.0, 0.05, 0.1)]
    sequence = sequence_table(model, frames, budgets=(30,), every=1)
    assert sequence.count("\n") == 2 + 3 + 2 - 1 and "| sum |" in sequence and "/3 |" in sequence


@pytest.mark.slow
def test_optimiser_comparison_runs_every_optimiser_from_both_starts(model):
    target = decode(model, true_point(5))
    row = optimisers.compare_optimisers(model, target, evaluations=30, basin_seconds=0.2)
    for optimiser in ("L-BFGS-B", "SLSQP", "CG", "L-BFGS-B, ours", "Nelder-Mead", "basin-hopping"):
        for start in ("random", "best-of-9"):
            assert row[f"{optimiser} ({start}) evaluations"] > 0
            assert 0.0 <= row[f"{optimiser} ({start})"] < 255.0 and 0.0 < row[f"{optimiser} ({start}) seconds"] < 60.0
    best_of_n = search.neural_search(model, target, settings=search.Settings(method="nn")).rmse
    assert row["L-BFGS-B (best-of-9)"] <= best_of_n + 1e-4 and row["L-BFGS-B, ours (best-of-9)"] <= best_of_n + 1e-4
    assert row["Nelder-Mead (best-of-9) evaluations"] == 30


def test_budget_plot_is_a_readable_picture(tmp_path):
    rows = [
        {
            "optimize_50": 9.0,
            "optimize_300": 7.0,
            "optimize_1500": 6.0,
            "hybrid_50": 5.0,
            "hybrid_300": 4.5,
            "hybrid_1500": 4.0,
            "best_of_n": 5.5,
        }
    ]
    path = tmp_path / "plot.png"
    suite_report.budget_plot(rows, str(path))
    picture = images.read(str(path))
    assert picture.shape == (400, 640, 3)
    red, blue = np.array([0.839, 0.153, 0.157]), np.array([0.122, 0.467, 0.706])  # matplotlib's tab:red and tab:blue
    encoded = images.srgb_encode(picture)
    for colour in (red, blue):
        assert np.sum(np.all(np.abs(encoded - colour) < 0.02, axis=-1)) > 100  # each line is drawn
    assert [p.name for p in tmp_path.iterdir()] == ["plot.png"]  # no temporary file left behind


def test_an_answer_judged_again_counts_as_no_worse_than_itself_despite_render_jitter():
    # two renders of one material with one seed differ in the sixth decimal of their RMSE (threads sum in any order)
    np.testing.assert_array_equal(reachable.no_worse([1.000002, 0.9, 1.2], [1.0, 1.0, 1.1]), [True, True, False])


def calibrated_case(name: str, truth: np.ndarray) -> dict:
    """A finished case of `bench-ranges` as its results file holds it: every parameter decided on [0.4, 0.6] with
    the mean as tau, and with the 95th percentile on [0.3, 0.7] but parameter 0 partly, on [0.1, 0.9]."""
    from matfit import params
    from matfit.app.bench import ranges

    def ranges_of(low: float, high: float, tau: float) -> dict:
        lows, highs = np.full(params.COUNT, low), np.full(params.COUNT, high)
        if tau > 2:
            lows[0], highs[0] = 0.1, 0.9
        verdicts = ["partly" if tau > 2 and i == 0 else "decided" for i in range(params.COUNT)]
        inside = (truth >= lows) & (truth <= highs)
        return {"threshold": tau, "verdicts": verdicts, "low": lows.tolist(), "high": highs.tolist(),
                "inside": inside.tolist(), "seconds": 0.1, "truth_rmse": 1.0}  # fmt: skip

    calibration = {"mean": ranges_of(0.4, 0.6, 1.8), "p95": ranges_of(0.3, 0.7, 2.9)}
    assert set(calibration) == set(ranges.STATISTICS)
    return {"name": name, "answer": [0.5] * params.COUNT, "settings": ranges.settings(), "truth": truth.tolist(),
            **calibration["mean"], "calibration": calibration, "fit_seconds": 2.0, "range_seconds": 0.1,
            "simplest_seconds": 0.01, "dropped": [], "free_before": 0, "checks": [{"parameter": "sheen",
            "verdict": "decided", "neural": 1.0, "mitsuba": 1.5}]}  # fmt: skip


def test_bench_ranges_goes_on_from_its_results_file_and_tabulates_each_tau(tmp_path, monkeypatch, model):
    import json

    from matfit.app.bench import ranges

    truth = np.full(19, 0.65)  # inside every p95 range, outside every mean one
    stale = {**calibrated_case("reachable-1", truth), "settings": {"checks": 3}, "answer": [0.25] * 19}
    results = tmp_path / "ranges.json"
    cases = [calibrated_case("reachable-0", truth), stale, {"name": "reachable-2"}]
    results.write_text(json.dumps({"cases": cases}))
    measured = []

    def measure(model, renderer, target, truth, index, judge, fitted=None):
        measured.append((index, fitted))
        return {key: value for key, value in calibrated_case("", truth).items() if key != "name"}

    monkeypatch.setattr(ranges, "case", measure)
    assert list(ranges.finished(str(results))) == ["reachable-0", "reachable-1"]  # reachable-2 holds no answer
    monkeypatch.setattr(ranges, "warm_up", lambda *args: None)
    figures = ranges.run(model, 3, 0, [], log=lambda line: None, results=str(results))
    assert figures["cases"][0] == calibrated_case("reachable-0", truth)  # measured with today's settings: kept
    # measured with other settings: measured again from its stored answer; never fitted: fitted now
    assert [(index, fitted and (fitted[0].tolist(), fitted[1])) for index, fitted in measured] == [
        (1, ([0.25] * 19, 2.0)),
        (2, None),
    ]
    assert [c["name"] for c in figures["cases"]] == ["reachable-0", "reachable-1", "reachable-2"]
    assert json.loads(results.read_text()) == figures
    # interrupted after its first case was measured again, a run keeps the file's other answers for the next one
    olds = [{**stale, "name": f"reachable-{k}"} for k in range(3)]
    results.write_text(json.dumps({"cases": olds}))
    calls = []

    def interrupted(*args, **kwargs):
        calls.append(args)
        if len(calls) > 1:
            raise KeyboardInterrupt
        return measure(*args, **kwargs)

    monkeypatch.setattr(ranges, "case", interrupted)
    with pytest.raises(KeyboardInterrupt):
        ranges.run(model, 3, 0, [], log=lambda line: None, results=str(results))
    kept = json.loads(results.read_text())["cases"]
    assert [c["name"] for c in kept] == ["reachable-0", "reachable-1", "reachable-2"]
    assert kept[0]["settings"] == ranges.settings() and kept[1:] == olds[1:]
    text = ranges.table({"cases": figures["cases"][:1]})
    first, second = text.index("tau = the decoder's mean"), text.index("95th-percentile")
    assert first < second  # the default tau's table comes first
    assert "| base_color_r | 0% (1) | - (0) | - (0) | 0.2 reflectance | - |" in text[first:second]
    assert "| all | 0% (19) | - (0) | - (0) | | |" in text[first:second]
    # the truth decodes 1.0 from the answer, within tau: every miss is a range that fell short
    assert "Of the 19 decided ranges that miss the true value, 19 belong to a target" in text[first:second]
    assert "decided ranges that miss" not in text[second:]  # with the 95th percentile none misses
    assert "| base_color_r | - (0) | 100% (1) | - (0) | - | 0.8 reflectance |" in text[second:]
    assert "| base_color_g | 100% (1) | - (0) | - (0) | 0.4 reflectance | - |" in text[second:]
    assert "| all | 100% (18) | 100% (1) | - (0) | | |" in text[second:]
    assert "| decided | 1 | 1.00 | 1.50 | 100% |" in text  # Mitsuba 1.5 within the default tau, 1.8


@pytest.mark.usefixtures("tiny_scene_fits")  # tests/conftest.py
def test_a_scene_bench_row_holds_the_judges_own_floor_and_the_fits_cpu_seconds(tmp_path):
    case = scenes.cases(quick=True)[0]
    row = scenes.run_case(case, str(tmp_path), 1, size=32, judge_size=16)
    assert row["case"] == "knot-studio-opaque" and row["start"] > 5.0  # the start is 0.2 off in every coordinate
    assert 0.0 <= row["judge_floor"] < 1.0 < row["start"]  # the truth against itself reads near 0, the start does not
    assert row["cpu_seconds"] > 0.0 and row["floor"] > 0.0
    assert isinstance(row["at_zero"], list)  # what the fit set to 0 (`scene_plain.at_zero`), [] where nothing
    assert row["plain"]["off"] == row["lobes_off"] and isinstance(row["plain"]["tried"], list)
    # an opaque fit's judge: the kurtosis of its renders' noise where the descent ended, and whether it looked past
    assert row["noise_kurtosis"] > 0 and row["robust_judge"] == (row["noise_kurtosis"] > scene_judge.HEAVY_TAILED)
    # and its steps' residual: encoded, a step's image of the red knot reads a little darker than its mean
    assert 0.0 < row["darkening"] < scene_fit.DARKENING and row["linear_residual"] is False
    text = scenes.table([row, {k: v for k, v in row.items() if k not in ("judge_floor", "cpu_seconds")}])
    lines = text.splitlines()
    assert "judge's floor" in lines[0] and "CPU seconds" in lines[0]
    assert lines[2].count("|") == lines[3].count("|") == 11
    assert lines[2].split("|")[6].strip() == f"{row['judge_floor']:.2f}" and lines[3].split("|")[6].strip() == ""
