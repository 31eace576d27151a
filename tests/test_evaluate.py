import numpy as np
import pytest

from matfit import params
from matfit.model import architectures, dataset, evaluate
from matfit.rendering import engine, presets


def test_subsets_split_the_parameter_space_into_thirds():
    values = np.stack(
        [
            params.from_mapping(m)
            for m in (
                {"spec_trans": 0.2},
                {"spec_trans": 0.5},
                {"spec_trans": 0.9, "scattering": 0.6, "density": 1.0},
                {"spec_trans": 0.9, "scattering": 0.6, "density": 0.5},
                {"spec_trans": 0.3, "scattering": 1.0, "density": 4.0},
            )
        ]
    )
    masks = evaluate.subsets(values)
    assert masks["transmissive"].tolist() == [False, True, True, True, False]
    assert masks["scattering"].tolist() == [False, False, True, False, False]
    assert masks["opaque"].tolist() == [True, False, False, False, True]
    preset_masks = evaluate.subsets(np.stack([presets.preset(name) for name in presets.PRESETS]))
    assert [name for name, s in zip(presets.PRESETS, preset_masks["scattering"], strict=True) if s] == ["jade", "milk"]
    assert int(preset_masks["transmissive"].sum()) == 5


def test_preset_references_are_rendered_once_and_kept(tiny_dataset, monkeypatch):
    references = dataset.open_dataset(tiny_dataset)
    first = evaluate.preset_references(references, spp=2)
    assert list(first) == list(presets.PRESETS) and first["gold"].shape == (32, 32, 3)

    def refuse(*args, **kwargs):
        raise AssertionError("rendered again")

    monkeypatch.setattr(engine, "Renderer", refuse)
    again = evaluate.preset_references(references, spp=2)
    np.testing.assert_array_equal(again["jade"], first["jade"])
    with pytest.raises(AssertionError, match="rendered again"):
        evaluate.preset_references(references, spp=3)  # other settings: rendered anew


def test_the_card_says_how_the_decoder_draws_glass():
    default = evaluate.describe_decoder(architectures.architecture("decoder", 64))  # `matfit train` without options
    assert "17 x 6 basis of clear-glass Mitsuba renders" in default and "features of the medium" in default
    assert "grey-medium" not in default and "Beer-Lambert" not in default
    coarse = evaluate.describe_decoder(
        architectures.architecture("decoder", 64, architectures.trained_decoder(64, True))
    )
    assert "path length per 2 x 2 pixels (Beer-Lambert)" in coarse
    scattering = architectures.Decoder(glass_grid=(17, 6), medium_grid=(9, 6))
    assert "9 x 6 basis of grey-medium Mitsuba renders" in evaluate.describe_decoder(
        architectures.architecture("decoder", 64, scattering)
    )
    plain = evaluate.describe_decoder(architectures.architecture("decoder", 64, architectures.Decoder()))
    assert "stages of 64, 48, 32 filters" in plain and "glass" not in plain and "medium" not in plain


def test_the_card_says_what_the_decoder_trained_on():
    first = {"count": 22000, "resolution": 64, "spp": 16, "variant": "llvm_ad_rgb", "seed": 0, "sampler": "uniform"}
    one = {"dataset": first, "validation_samples": 1100, "config": {"validation_fraction": 0.05}}
    assert evaluate.describe_training(one) == (
        "Trained on 22000 Mitsuba renders (64 px, 16 spp, llvm_ad_rgb, sampling seed 0); "
        "the last 5% of each set (1100 renders) were held out for validation."
    )
    media = {**first, "count": 4000, "seed": 2, "sampler": "dense-media"}
    two = {**one, "dataset": [first, media], "validation_samples": 1300}
    sentence = evaluate.describe_training(two)
    assert (
        "the decoder also on 4000 drawn by the dense-media sampler (seed 2), the encoders on the first set alone"
        in (sentence)
    )
    assert "(1300 renders)" in sentence
    glass = {**first, "count": 6000, "seed": 3, "sampler": "glass"}
    three = evaluate.describe_training({**one, "dataset": [first, media, glass], "validation_samples": 1600})
    assert (
        "the decoder also on 4000 drawn by the dense-media sampler (seed 2) and 6000 drawn by the glass sampler "
        "(seed 3), the encoders on the first set alone; the last 5% of each set (1600 renders)" in three
    )
    assert "started from" not in three and "--loss linear" not in three
    tuned = {
        **one,
        "epochs": 5,
        "start_sha256": "f8f0b09830f73b2e" + "0" * 48,
        "config": {
            "validation_fraction": 0.05,
            "start_from": "runs/decoder-base",
            "learning_rate": 2e-4,
            "loss": "linear",
        },
    }
    assert evaluate.describe_training(tuned).endswith(
        "were held out for validation. The decoder's last 5 epochs started from trained weights (SHA-256 "
        "f8f0b09830f7...) at a peak learning rate of 0.0002. The decoder learned the encoding of the mean linear "
        "render (`--loss linear`), not the mean of the encoded noisy renders, which is darker."
    )
