import json
import math
import time

import numpy as np
import pytest

from matfit import params
from matfit.params import ParameterError
from matfit.rendering import presets


def test_table_has_nineteen_named_bounded_parameters():
    assert params.COUNT == 19
    assert len(set(params.NAMES)) == 19
    for p in params.PARAMETERS:
        assert p.low < p.high
        assert p.low <= p.default <= p.high
        assert p.meaning and p.unit
        assert 0.0 <= p.low_corner + p.high_corner < 1.0


def test_unit_cube_round_trip_is_exact_and_maps_bounds():
    rng = np.random.default_rng(1)
    values = params.from_unit(rng.random((50, 19)))
    np.testing.assert_allclose(params.from_unit(params.to_unit(values)), values, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(params.to_unit(params.LOW), np.zeros(19))
    np.testing.assert_array_equal(params.to_unit(params.HIGH), np.ones(19))
    assert params.from_unit(np.full(19, 0.5))[params.INDEX["phase_g"]] == pytest.approx(0.0)


def test_sampling_is_deterministic_per_index_and_stays_in_the_cube():
    a = params.sample_index(7, 3)
    b = params.sample_index(7, 3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(params.sample_index(7, 4), a)
    assert not np.array_equal(params.sample_index(8, 3), a)
    samples = np.stack([params.sample_index(0, i) for i in range(4000)])
    assert samples.min() >= 0.0 and samples.max() <= 1.0


def test_sampling_covers_the_corners():
    samples = np.stack([params.sample_index(0, i) for i in range(4000)])
    for name in ("metallic", "spec_trans"):
        column = samples[:, params.INDEX[name]]
        p = params.PARAMETERS[params.INDEX[name]]
        # corner mass plus the uniform interior's own 5% share of each band
        expected_low = p.low_corner + (1 - p.low_corner - p.high_corner) * params.CORNER_WIDTH
        expected_high = p.high_corner + (1 - p.low_corner - p.high_corner) * params.CORNER_WIDTH
        assert np.mean(column <= 0.05) == pytest.approx(expected_low, abs=0.03)
        assert np.mean(column >= 0.95) == pytest.approx(expected_high, abs=0.03)
    roughness = samples[:, params.INDEX["roughness"]]
    assert np.mean(roughness < 0.1) > 0.3  # uniform would give 0.1
    assert np.mean(samples[:, params.INDEX["phase_g"]] < 0.5) == pytest.approx(0.5, abs=0.04)


def drawn(sampler: str, count: int = 2000) -> np.ndarray:
    """Returns `count` physical vectors of a sampler (seed 0), after checking that they lie in the unit cube."""
    unit = np.stack([params.sample_index(0, i, sampler) for i in range(count)])
    assert unit.min() >= 0.0 and unit.max() <= 1.0
    return params.from_unit(unit)


def test_dense_media_sampler_draws_dense_transmissive_nearly_lossless_media():
    physical = drawn("dense-media")
    assert physical[:, params.INDEX["spec_trans"]].min() >= 0.95
    density = physical[:, params.INDEX["density"]]
    assert density.min() >= 0.5 and density.max() <= 4.0
    assert np.mean(density) == pytest.approx(2.25, abs=0.1)  # uniform in [0.5, 4]
    albedo = physical[:, params.INDEX["scattering"]]
    assert albedo.min() >= 0.85
    assert np.mean(albedo >= 0.99) == pytest.approx((0.01 / 0.15) ** (1 / 3), abs=0.04)  # 1 - 0.15 u^3 >= 0.99
    # the uniform sampler draws such materials a fraction of a percent of the time
    uniform = drawn("uniform")
    milky = (
        (uniform[:, params.INDEX["spec_trans"]] >= 0.95)
        & (uniform[:, params.INDEX["density"]] >= 0.5)
        & (uniform[:, params.INDEX["scattering"]] >= 0.99)
    )
    assert np.mean(milky) < 0.02
    # the other parameters are drawn as the training distribution draws them
    roughness = physical[:, params.INDEX["roughness"]]  # its range is the unit interval
    assert np.mean(roughness < 0.1) > 0.3
    np.testing.assert_array_equal(params.sample_index(0, 5, "dense-media"), params.sample_index(0, 5, "dense-media"))


def test_glass_sampler_draws_white_and_grey_dielectrics_clear_tinted_and_milky():
    physical = drawn("glass")
    column = {name: physical[:, params.INDEX[name]] for name in params.NAMES}
    assert column["spec_trans"].min() >= 0.95 and column["metallic"].max() <= 0.05
    colour = physical[:, :3]
    assert np.mean(np.ptp(colour, axis=1) == 0.0) == pytest.approx(0.5, abs=0.04)  # exactly grey
    assert np.ptp(colour, axis=1).max() <= 0.05  # never more than a tint
    assert np.mean(colour.min(axis=1) >= 0.95) == pytest.approx(0.35, abs=0.04)  # white: every transmissive preset
    # the uniform sampler draws a white base colour once in thousands
    uniform = drawn("uniform")
    assert np.mean(uniform[:, :3].min(axis=1) >= 0.95) < 0.002
    # half the media are the dense-media corner's, the other half as drawn (clear glass among them)
    dense = (column["density"] >= 0.5) & (column["scattering"] >= 0.85)
    assert np.mean(dense) == pytest.approx(0.5 + 0.5 * 0.15, abs=0.05)
    assert np.mean(column["density"] <= 0.2) == pytest.approx(0.5 * 0.4, abs=0.05)
    np.testing.assert_array_equal(params.sample_index(0, 5, "glass"), params.sample_index(0, 5, "glass"))


def test_tinted_glass_sampler_draws_absorbing_coloured_media_in_white_and_grey_dielectrics():
    physical = drawn("tinted-glass")
    column = {name: physical[:, params.INDEX[name]] for name in params.NAMES}
    assert column["spec_trans"].min() >= 0.95 and column["metallic"].max() <= 0.05
    assert np.ptp(physical[:, :3], axis=1).max() <= 0.05  # the glass sampler's base colours
    assert column["scattering"].max() <= 0.05  # absorbing only
    assert column["density"].min() >= 0.25 and column["density"].max() <= 2.5
    assert np.mean(column["density"]) == pytest.approx(1.375, abs=0.05)
    medium = physical[:, params.INDEX["medium_color_r"] : params.INDEX["medium_color_b"] + 1]
    assert np.mean(medium, axis=0) == pytest.approx([0.505] * 3, abs=0.03)  # uniform over [0.01, 1] per channel
    # amber's kind of tint (a channel at most 0.15, another at least 0.8): 0.142 for three independent channels
    amber_like = (medium.min(axis=1) <= 0.15) & (medium.max(axis=1) >= 0.8)
    assert np.mean(amber_like) == pytest.approx(0.142, abs=0.025)  # 0.1525 in these 2000 draws
    np.testing.assert_array_equal(params.sample_index(7, 3, "tinted-glass"), params.sample_index(7, 3, "tinted-glass"))


def test_unknown_sampler_is_refused():
    expected = "unknown sampler 'milk': use uniform or dense-media or glass or tinted-glass"
    with pytest.raises(ParameterError, match=expected):
        params.sample_index(0, 0, "milk")


def test_params_json_partial_files_take_defaults_in_both_layouts():
    flat = params.parse_params_json('{"roughness": 0.2, "metallic": 1}')
    nested = params.parse_params_json(json.dumps({"params": {"roughness": 0.2, "metallic": 1}, "method": "hybrid"}))
    np.testing.assert_array_equal(flat, nested)
    expected = params.DEFAULTS.copy()
    expected[params.INDEX["roughness"]] = 0.2
    expected[params.INDEX["metallic"]] = 1.0
    np.testing.assert_array_equal(flat, expected)


def test_params_document_round_trips_through_json():
    values = params.from_unit(params.sample_index(3, 0))
    text = json.dumps(params.params_document(values, method="test"))
    np.testing.assert_allclose(params.parse_params_json(text), values, atol=1e-6)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{not json", "is not valid JSON"),
        ("[1, 2]", "must hold a JSON object"),
        ('{"rougness": 0.3}', "did you mean 'roughness'"),
        ('{"zzzz": 0.3}', "unknown parameter 'zzzz'"),
        ('{"roughness": 1.5}', "use a value in [0.0, 1.0]"),
        ('{"density": -1}', "use a value in [0.0, 4.0]"),
        ('{"roughness": NaN}', "is nan"),
        ('{"roughness": "high"}', "must be a number"),
        ('{"metallic": true}', "must be a number"),
        ('{"metallic": ' + "9" * 400 + "}", "'metallic' is inf"),  # was an OverflowError
        ('{"metallic": ' + "9" * 5000 + "}", "'metallic' is inf"),  # was a ValueError (Python's digit limit)
        ('{"params": {"metallic": 0.5}, "metallic": 7}', 'names metallic outside "params" as well'),
        ('{"metallic": 0.1, "roughness": 0.2, "metallic": 0.9}', "'metallic' given more than once"),
        ('{"params": {"roughness": 0.1, "roughness": 0.2}}', "'roughness' given more than once"),
        ('{"params": [1, 2]}', '"params" must be a JSON object of names and values'),
        ("[" * 100000, "is not valid JSON (nested too deeply to read): give a params.json that matfit wrote"),
        ('{"p":' * 100000, "is not valid JSON (nested too deeply to read)"),  # was a RecursionError
    ],
)
def test_bad_params_json_gives_one_line_errors(text, message):
    with pytest.raises(ParameterError) as error:
        params.parse_params_json(text, "edit.json")
    assert message in str(error.value)
    assert str(error.value).startswith("edit.json")
    assert "\n" not in str(error.value)


def test_many_keys_are_checked_in_linear_time_and_a_byte_order_mark_is_accepted(tmp_path):
    # 40 000 keys (430 KB): a count per key took minutes; one pass takes milliseconds.
    many = "{" + ", ".join(f'"k{i}": 0.5' for i in range(40_000)) + ', "k7": 0.5}'
    started = time.perf_counter()
    with pytest.raises(ParameterError, match=r"^edit.json: 'k7' given more than once: keep one value$"):
        params.parse_params_json(many, "edit.json")
    assert time.perf_counter() - started < 5
    text = '{"roughness": 0.3}'
    (tmp_path / "bom.json").write_bytes(b"\xef\xbb\xbf" + text.encode())  # as Windows' Notepad saves
    for read in (
        params.read_file(str(tmp_path / "bom.json")),
        params.parse_params_json("\ufeff" + text),
        params.parse_params_json(b"\xef\xbb\xbf" + text.encode()),
    ):
        assert read[params.INDEX["roughness"]] == pytest.approx(0.3)


def test_medium_coefficients_follow_the_documented_formula():
    values = params.from_mapping(
        {"medium_color_r": 0.5, "medium_color_g": 0.25, "medium_color_b": 1.0, "density": 2.0, "scattering": 0.3}
    )
    sigma_t, albedo = params.medium_coefficients(values)
    np.testing.assert_allclose(sigma_t, [2 * math.log(2), 2 * math.log(4), params.MINIMUM_EXTINCTION])
    np.testing.assert_allclose(albedo, [0.3, 0.3, 0.3])
    # light kept after one radius at density 1 is the absorption colour itself
    one = params.from_mapping({"medium_color_r": 0.5, "density": 1.0})
    assert math.exp(-params.medium_coefficients(one)[0][0]) == pytest.approx(0.5)


def test_table_difference_is_described():
    assert params.describe_table_difference(params.table_fingerprint()) is None
    changed = params.table_fingerprint()
    changed["parameters"][4] = {**changed["parameters"][4], "high": 2.0}
    assert "roughness" in params.describe_table_difference(changed)
    fewer = {"version": 1, "parameters": changed["parameters"][:18]}
    assert "phase_g" in params.describe_table_difference(fewer)


def test_presets_are_valid_and_distinct():
    vectors = {name: presets.preset(name) for name in presets.PRESETS}
    assert len(vectors) >= 8
    for values in vectors.values():
        assert np.all(values >= params.LOW) and np.all(values <= params.HIGH)
    assert len({tuple(v) for v in vectors.values()}) == len(vectors)
    with pytest.raises(ParameterError, match="choose one of"):
        presets.preset("unobtainium")


def test_huge_integers_passed_in_code_are_out_of_range():
    with pytest.raises(ParameterError, match="'metallic' is out of range"):
        params.from_mapping({"metallic": 10**400})


def test_a_params_file_nested_too_deeply_is_one_line_naming_the_file(tmp_path):
    (tmp_path / "deep.json").write_text("[" * 100000)
    with pytest.raises(ParameterError, match=rf"^{tmp_path}/deep\.json is not valid JSON \(nested too deeply"):
        params.read_file(str(tmp_path / "deep.json"))


def test_parameters_that_are_not_finite_are_never_written():
    values = presets.preset("gold").copy()
    values[params.INDEX["roughness"]] = np.nan
    with pytest.raises(ParameterError, match=r"not finite \(roughness nan\): nothing is written"):
        params.params_document(values)
