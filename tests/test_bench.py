import numpy as np
import pytest
from helpers import decode, random_model, true_point

from matfit import bench, fit


@pytest.fixture(scope="module")
def model():
    return random_model()


def test_black_level_maps_the_black_point_to_zero():
    values = np.array([0.0, 0.2, 0.6, 1.0])
    np.testing.assert_allclose(bench.black_level(values, 0.2), [0.0, 0.0, 0.5, 1.0])
    np.testing.assert_array_equal(bench.black_level(values, 0.0), values)


def test_compare_and_tables(model):
    targets = bench.Targets(
        np.stack([true_point(1), true_point(2)]), np.stack([decode(model, true_point(1)), decode(model, true_point(2))])
    )
    configurations = {"nn (best-of-n)": fit.Settings(method="nn"), "hybrid 60": fit.Settings(evaluations=60)}
    table = bench.compare(model, targets, configurations)
    assert np.all(table["hybrid 60"]["rmse"] <= table["nn (best-of-n)"]["rmse"] + 1e-6)  # hybrid starts from the nn answer
    text = bench.markdown(table, "hybrid 60", {})
    assert "| nn (best-of-n) |" in text and "2/2" in text
    frames = [bench.black_level(decode(model, true_point(3)), level) for level in (0.0, 0.05, 0.1)]
    sequence = bench.sequence_table(model, frames, budgets=(30,), every=1)
    assert sequence.count("\n") == 2 + 3 + 2 - 1 and "| sum |" in sequence and "/3 |" in sequence
