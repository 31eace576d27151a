"""The fitting methods' settings (`matfit/fitting/methods.py`): `Settings` checks every value when it is made."""

from __future__ import annotations

import numpy as np
import pytest

from matfit.errors import FitError
from matfit.fitting.methods import Method, Settings


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ({"evaluations": "abc"}, "evaluations 'abc' is not a whole number: use 21 to 1000000"),
        ({"evaluations": 60.5}, "evaluations 60.5 is not a whole number: use 21 to 1000000"),  # failed deep in a fit
        ({"evaluations": True}, "evaluations True is not a whole number"),
        ({"method": "hybrid", "evaluations": 20}, "evaluations 20 is out of range: Nelder-Mead in 19 dimensions needs"),
        ({"starts": 2.5}, "starts 2.5 is not a whole number: use 1 to 64"),
        ({"starts": 0}, "starts 0 is out of range: use 1 to 64"),  # refused when made, not at the fit
        ({"iterations": None}, "iterations None is not a whole number: use 1 to 100000"),
        ({"narrow_after": np.float64(3)}, "narrow_after np.float64(3.0) is not a whole number"),
        ({"polish_steps": -1}, "polish steps -1 is out of range: use 0 to 100000"),
        ({"adaptive": "no"}, "adaptive 'no' is not True or False: give adaptive=True or adaptive=False"),
        ({"adaptive": 1}, "adaptive 1 is not True or False"),
        ({"initial_step": -1.0}, "initial_step -1.0 is out of range: use above 0 up to 1"),
        ({"initial_step": 0}, "initial_step 0 is out of range: use above 0 up to 1"),
        ({"initial_step": "0.1"}, "initial_step '0.1' is not a number: use above 0 up to 1"),
        ({"polish_rate": float("nan")}, "polish_rate nan is out of range: use above 0 up to 1"),
        ({"polish_rate": float("inf")}, "polish_rate inf is out of range"),
        ({"polish_rate": 1e-3 + 0j}, "polish_rate (0.001+0j) is not a number"),
    ],
)
def test_settings_refuse_a_value_of_the_wrong_kind_or_range_when_made(given, message):
    with pytest.raises(FitError) as raised:
        Settings(**given)
    assert str(raised.value).startswith(message) and "\n" not in str(raised.value)
    assert raised.value.field == next(name for name in given if name != "method")


def test_settings_take_numpy_numbers_as_python_ones_and_leave_the_defaults_as_they_were():
    settings = Settings(
        Method.nn, np.int64(50), starts=np.uint8(2), adaptive=np.bool_(False), polish_rate=np.float32(0.5)
    )
    assert settings == Settings(Method.nn, 50, starts=2, adaptive=False, polish_rate=0.5)
    assert [type(settings.evaluations), type(settings.starts), type(settings.adaptive), type(settings.polish_rate)] == [
        int,
        int,
        bool,
        float,
    ]
    assert Settings(method="nn", evaluations=0) == Settings(method="nn", evaluations=0)  # nn runs no Nelder-Mead
    # what the journal of `matfit fit a b -o out/` keys on: unchanged by the checks
    assert repr(Settings()) == (
        "Settings(method=<Method.lbfgsb: 'lbfgsb'>, evaluations=1500, box=<Box.clip: 'clip'>, adaptive=True, "
        "initial_step=0.1, polish_steps=0, polish_rate=0.003, starts=4, iterations=60, narrow_after=35)"
    )
