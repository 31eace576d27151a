"""The clean answer: its candidates on synthetic decoders whose answers are known, and its Mitsuba judgement."""

import jax.numpy as jnp
import numpy as np
import pytest

from matfit import images, params
from matfit.fitting import clean, ranges

SIDE = 4
THRESHOLD = 2.0


def flat(value: jnp.ndarray) -> jnp.ndarray:
    """Returns images (n, SIDE, SIDE, 3) of one grey value per material (n,)."""
    return jnp.broadcast_to(value[:, None, None, None], (value.shape[0], SIDE, SIDE, 3))


def answer(**values: float) -> np.ndarray:
    x = np.full(params.COUNT, 0.5)
    for name, value in values.items():
        x[params.INDEX[name]] = value
    return x


def red_and_sheen(unit, variables):
    # base_color_r and sheen brighten the image together: base_color_r can make up for part of the sheen only
    return flat(0.2 + variables * (unit[:, params.INDEX["base_color_r"]] + unit[:, params.INDEX["sheen"]]))


def test_features_without_effect_are_turned_off_and_one_the_picture_needs_is_kept():
    x = answer(sheen=0.7, clearcoat=0.4, anisotropic=0.3, spec_trans=0.2, density=0.5)
    slope = jnp.float32(0.3)
    found = ranges.measure(red_and_sheen, slope, x, None, THRESHOLD)
    sheen = params.INDEX["sheen"]
    # sheen can fall to 0.2 while base_color_r rises to its face, 1.0 (plus the threshold's slack)
    assert found.verdicts[sheen] == "partly"
    assert found.low[sheen] == pytest.approx(0.2 - THRESHOLD / (255.0 * 0.3), abs=2e-3)
    found_candidates = clean.candidates(red_and_sheen, slope, x, None, found)
    # nested, each one more feature off; the features without effect decode exactly like the answer (D = 0)
    assert [names for names, _, _ in found_candidates] == [
        ("anisotropy",),
        ("anisotropy", "clearcoat"),
        ("anisotropy", "clearcoat", "medium"),
        ("anisotropy", "clearcoat", "medium", "transmission"),
    ]
    assert [distance for _, _, distance in found_candidates] == pytest.approx([0.0] * 4, abs=1e-4)
    simple = found_candidates[-1][1]
    assert simple[sheen] == pytest.approx(0.7, abs=1e-6)
    for name, feature in params.FEATURES.items():
        for parameter, value in feature.items():
            if name != "sheen":
                assert params.from_unit(simple)[params.INDEX[parameter]] == pytest.approx(value, abs=1e-6)
    # free and away from neutral: anisotropic, clearcoat, clearcoat_gloss, spec_trans, the medium's colours,
    # density and scattering (phase_g 0 and sheen_tint 0.5 are neutral already)
    assert clean.free_away_from_neutral(x, found.verdicts) == 9
    assert clean.free_away_from_neutral(simple, found.verdicts) == 0


def test_mitsuba_keeps_the_simplest_candidate_it_cannot_tell_from_the_answer(renderer):
    from matfit.fitting import verify
    from matfit.rendering import presets

    best = params.to_unit(presets.preset("red-plastic"))
    target = images.srgb_encode(renderer.render(params.from_unit(best), seed=7, spp=64))
    unseen = best.copy()  # sheen_tint without sheen: the renders barely show it
    unseen[params.INDEX["sheen_tint"]] = 0.9
    assert best[params.INDEX["sheen"]] == 0.0
    seen = unseen.copy()  # and a base colour the picture plainly decides
    seen[params.INDEX["base_color_g"]] = 0.8
    judged = clean.judge(renderer, best, {"clean-1": unseen, "clean-2": seen}, target, None)
    assert judged["chosen"] == "clean-1" and judged["margins"]["clean-1"] < verify.LEAD
    assert judged["margins"]["clean-2"] >= verify.LEAD and judged["figures"]["clean-2"] > judged["figures"]["best"] + 5
    assert judged["figures"]["clean-1"] == pytest.approx(judged["figures"]["best"], abs=0.5)
    # one look each: verification's first batches decide
    assert judged["batches"] == {"best": verify.BATCHES, "clean-2": verify.BATCHES, "clean-1": verify.BATCHES}
    # a candidate identical to the answer ties with it: no deficit, and the candidate is kept
    tie = clean.judge(renderer, best, {"clean-1": best.copy()}, target, None)
    assert tie["chosen"] == "clean-1" and tie["margins"]["clean-1"] == 0.0
    # verification's batches of the answer stand in for its renders: the same judgement
    rendered: dict[str, list] = {}
    verify.render_batches(renderer, {"best": best}, rendered, ["best"], count=verify.BATCHES, spp=verify.SPP)
    again = clean.judge(renderer, best, {"clean-1": unseen, "clean-2": seen}, target, None, rendered=rendered["best"])
    assert again["chosen"] == "clean-1" and again["batches"] == judged["batches"]
    assert again["figures"]["best"] == pytest.approx(judged["figures"]["best"], rel=1e-4)
    # the simplest alone is measurably worse: the fit's own answer is kept
    alone = clean.judge(renderer, best, {"clean-1": seen}, target, None)
    assert alone["chosen"] == "best" and alone["margins"]["clean-1"] >= verify.LEAD


def test_one_look_a_plain_refusal_goes_on_and_an_undecided_candidate_ends_with_the_answer(renderer):
    from matfit.fitting import verify
    from matfit.rendering import presets

    best = params.to_unit(presets.preset("red-plastic"))
    target = images.srgb_encode(renderer.render(params.from_unit(best), seed=7, spp=64))
    far = best.copy()  # a base colour the picture plainly decides: refused at the first look
    far[params.INDEX["base_color_g"]] = 0.8
    close = best.copy()  # a roughness a hundredth off: behind the answer, though not by LEAD standard errors
    close[params.INDEX["roughness"]] += 0.01
    unseen = best.copy()  # sheen_tint without sheen: it would be kept, were it judged
    unseen[params.INDEX["sheen_tint"]] = 0.9
    judged = clean.judge(renderer, best, {"clean-1": unseen, "clean-2": close, "clean-3": far}, target, None)
    assert judged["margins"]["clean-3"] >= verify.LEAD and judged["batches"]["clean-3"] == verify.BATCHES
    # the close one is undecided after its batches: no more are rendered, the answer stays, and the less simple
    # candidate after it is not rendered at all
    assert 0 < judged["margins"]["clean-2"] < verify.LEAD and judged["batches"]["clean-2"] == verify.BATCHES
    assert judged["chosen"] == "best" and "clean-1" not in judged["batches"]
    assert judged["batches"]["best"] == verify.BATCHES


def red_and_density(unit, variables):
    # a decoder that (wrongly) shows the medium of an opaque material
    return flat(0.2 + variables * (unit[:, params.INDEX["base_color_r"]] + unit[:, params.INDEX["density"]]))


def test_without_transmission_the_medium_is_turned_off_whatever_the_decoder_shows_of_it():
    x = answer(spec_trans=0.0, density=0.6, sheen=0.3)
    slope = jnp.float32(0.3)
    found = ranges.measure(red_and_density, slope, x, None, THRESHOLD)
    assert clean.unseen_medium(x) and not clean.unseen_medium(answer(spec_trans=0.1))
    found_candidates = clean.candidates(red_and_density, slope, x, None, found)
    # the medium first, without a re-fit (base_color_r as in the answer); then what this decoder ignores
    assert [names for names, _, _ in found_candidates] == [
        ("medium",),
        ("medium", "anisotropy"),
        ("medium", "anisotropy", "sheen"),
        ("medium", "anisotropy", "sheen", "clearcoat"),
    ]
    first = found_candidates[0][1]
    assert first[params.INDEX["base_color_r"]] == pytest.approx(0.5, abs=1e-6)
    assert params.from_unit(first)[params.INDEX["density"]] == 0.0
    assert [distance for _, _, distance in found_candidates] == pytest.approx([0.0] * 4, abs=1e-4)
