import numpy as np
import pytest

from matfit.fitting import clean, stages


class Found:
    """Stands in for the ranges of a unit: which unit, and which call made it."""

    def __init__(self, unit, call):
        self.unit, self.call = unit, call


@pytest.fixture
def counted(monkeypatch):
    calls = []

    def ranges_stage(model, model_path, unit, weights):
        if np.any(np.isnan(unit)):
            raise ValueError("a unit with NaN")
        calls.append(np.asarray(unit, np.float64).copy())
        return Found(unit, len(calls))

    def candidates(decode, variables, answer, weights, found):
        return [(("sheen",), answer * 0.5, 0.1), ("found", found)]

    class Decoder:
        module, variables = None, None

    class Model:
        decoder = Decoder()

    monkeypatch.setattr(stages, "ranges_stage", ranges_stage)
    monkeypatch.setattr(clean, "candidates", candidates)
    monkeypatch.setattr(stages.ranges, "Decoding", lambda module: None)
    return calls, Model()


def test_work_done_ahead_for_a_point_is_used_for_that_point_only(counted):
    calls, model = counted
    ahead = stages.Ahead(model, "model", None, clean=True)
    point, other = np.full(19, 0.25), np.full(19, 0.5)
    ahead.answer(point)  # while verification's judge renders
    assert len(calls) == 1
    found = ahead.ranges_of(point.copy())  # the same point kept: nothing worked out again
    assert len(calls) == 1 and found.call == 1
    kept = ahead.candidates_of(point, found)
    assert kept is not None and kept[1] == ("found", found)
    assert ahead.candidates_of(point, Found(point, 9)) is None  # other ranges: the candidates are the stage's to find
    assert ahead.candidates_of(other, found) is None
    assert ahead.ranges_of(other).call == 2 and len(calls) == 2  # another point kept: worked out now


def test_work_ahead_that_fails_is_done_again_by_its_stage_which_raises(counted):
    calls, model = counted
    ahead = stages.Ahead(model, "model", None, clean=False)
    broken = np.full(19, np.nan)
    ahead.answer(broken)  # nothing raised while the renders are in flight
    ahead.clean_answer(broken)
    assert calls == [] and ahead.candidates == {}
    with pytest.raises(ValueError, match="a unit with NaN"):
        ahead.ranges_of(broken)
