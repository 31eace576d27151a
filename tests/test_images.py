import os

import numpy as np
import pytest

from matfit import images
from matfit.errors import ImageError
from matfit.files import OutputError


def test_srgb_round_trip_and_known_values():
    x = np.linspace(0, 1, 101, dtype=np.float32)
    np.testing.assert_allclose(images.srgb_decode(images.srgb_encode(x)), x, atol=1e-6)
    assert images.srgb_encode(np.float32(0.5)) == pytest.approx(0.735357, abs=1e-5)
    assert images.srgb_encode(np.float32(0.001)) == pytest.approx(0.01292, abs=1e-6)
    assert images.srgb_encode(np.float32(4.0)) == pytest.approx(1.0, abs=1e-6)


def test_rmse_is_on_the_0_255_scale():
    a = np.zeros((4, 4, 3))
    b = np.full((4, 4, 3), 10 / 255)
    assert images.rmse(a, b) == pytest.approx(10.0)
    b[0, 0, 0] = 1.0
    expected = np.sqrt((47 * 100 + 255**2) / 48)
    assert images.rmse(a, b) == pytest.approx(expected)
    with pytest.raises(ValueError, match=r"Shape mismatch: got \(4, 4, 3\) and \(2, 2, 3\)"):
        images.rmse(a, np.zeros((2, 2, 3)))


def test_the_noise_free_estimate_leaves_out_the_renders_noise_which_rmse_counts():
    # A material off by 0.05 everywhere, rendered twice with noise of spread 0.2: either render's squared error is
    # about 0.05^2 + 0.2^2, the two renders' cross term 0.05^2 (its standard error 0.2^2 / sqrt(3 64^2) = 3.6e-4)
    rng = np.random.default_rng(4)
    target = np.full((64, 64, 3), 0.5)
    renders = target + 0.05 + rng.normal(0, 0.2, (2, *target.shape))
    weights = np.ones((64, 64))
    assert images.noise_free_mse(renders, target, weights) == pytest.approx(0.05**2, abs=3 * 3.6e-4)
    assert (images.rmse(renders[0], target) / 255) ** 2 == pytest.approx(0.05**2 + 0.2**2, rel=0.05)
    # the two render alike where the noise is alike: the noisier material is not the one the estimate favours
    calm = target + 0.08 + rng.normal(0, 0.05, (2, *target.shape))
    assert images.noise_free_mse(calm, target, weights) > images.noise_free_mse(renders, target, weights)
    assert images.rmse(calm[0], target) < images.rmse(renders[0], target)
    half = np.zeros((64, 64))
    half[:32] = 1.0  # weighted like `rmse`: the other half's error has no part
    renders[:, 32:] += 0.5
    assert images.noise_free_mse(renders, target, half) == pytest.approx(0.05**2, abs=3 * 5.1e-4)
    with pytest.raises(ValueError, match="1 render: the estimate needs at least 2 independent renders"):
        images.noise_free_mse(renders[:1], target, weights)


def test_the_noise_free_difference_of_two_materials_comes_with_its_standard_error():
    # two materials off by 0.05 and 0.06 everywhere, rendered twice each with noise of spread 0.2 at other seeds
    rng = np.random.default_rng(5)
    target = np.full((64, 64, 3), 0.5)
    weights = np.ones((64, 64))
    near = target + 0.05 + rng.normal(0, 0.2, (2, *target.shape))
    far = target + 0.06 + rng.normal(0, 0.2, (2, *target.shape))
    difference, error = images.noise_free_difference(far, near, target, weights)
    assert difference == pytest.approx(
        images.noise_free_mse(far, target, weights) - images.noise_free_mse(near, target, weights)
    )
    # each pixel's estimate spreads by about sqrt(2) 0.2^2 / sqrt(3) (two independent products): over 64^2 pixels
    assert error == pytest.approx(np.sqrt(2) * 0.2**2 / np.sqrt(3) / 64, rel=0.1)
    assert difference == pytest.approx(0.06**2 - 0.05**2, abs=3 * error)
    # the same renders on both sides: no difference, none to doubt
    assert images.noise_free_difference(near, near, target, weights) == (0.0, 0.0)
    with pytest.raises(ValueError, match="2 and 1 renders: the difference needs at least 2 of each, as many"):
        images.noise_free_difference(near, near[:1], target, weights)


def test_rmse_per_image_weighted_and_in_jax():
    rng = np.random.default_rng(0)
    batch, target = rng.uniform(size=(2, 4, 4, 3)), rng.uniform(size=(4, 4, 3))
    weights = np.zeros((4, 4))
    weights[:2] = 1.0
    expected = [255 * np.sqrt(np.mean((image[:2] - target[:2]) ** 2)) for image in batch]
    np.testing.assert_allclose(images.rmse(batch, target, weights), expected, rtol=1e-12)
    np.testing.assert_allclose(images.rmse(batch, batch[::-1])[0], 255 * np.sqrt(np.mean((batch[0] - batch[1]) ** 2)))
    import jax.numpy as jnp

    jax_figures = images.rmse(
        jnp.asarray(batch, jnp.float32), jnp.asarray(target, jnp.float32), jnp.asarray(weights, jnp.float32)
    )
    np.testing.assert_allclose(np.asarray(jax_figures), expected, rtol=1e-5)


def test_png_and_exr_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    linear = rng.random((8, 12, 3)).astype(np.float32) * 1.5
    images.write(str(tmp_path / "a.exr"), linear)
    np.testing.assert_array_equal(images.read(str(tmp_path / "a.exr")), linear)
    images.write(str(tmp_path / "a.png"), linear)
    back = images.read(str(tmp_path / "a.png"))
    assert back.shape == (8, 12, 3)
    assert images.rmse(images.srgb_encode(back), images.srgb_encode(linear)) < 0.3  # 8-bit rounding only


def test_write_refuses_bad_paths_and_leaves_nothing(tmp_path):
    with pytest.raises(OutputError, match=r"unknown image type \.bmp"):
        images.write(str(tmp_path / "a.bmp"), np.zeros((2, 2, 3)))
    with pytest.raises(OutputError, match="does not exist"):
        images.write(str(tmp_path / "missing" / "a.png"), np.zeros((2, 2, 3)))
    with pytest.raises(OutputError, match="read-only"):
        images.write("/proc/matfit-test.png", np.zeros((2, 2, 3)))
    assert os.listdir(tmp_path) == []


def test_label_adds_a_caption_strip():
    out = images.label(np.zeros((20, 40, 3), np.float32), "gold", height=12)
    assert out.shape == (32, 40, 3)
    assert out[20:].max() > 0.5 and out[:20].max() == 0.0


def test_load_drops_alpha_and_replicates_grey_with_notices(tmp_path):
    import OpenImageIO as oiio

    rgba = np.zeros((4, 6, 4), np.float32)
    rgba[..., 0], rgba[..., 3] = 1.0, 0.5
    spec = oiio.ImageSpec(6, 4, 4, "uint16")
    spec.alpha_channel = 3
    buffer = oiio.ImageBuf(spec)
    buffer.set_pixels(oiio.ROI(), rgba)
    buffer.write(str(tmp_path / "rgba.png"))
    loaded = images.load(str(tmp_path / "rgba.png"))
    assert loaded.pixels.shape == (4, 6, 3) and loaded.pixels[0, 0, 0] == 1.0
    assert len(loaded.notices) == 1 and "alpha dropped" in loaded.notices[0]
    grey = oiio.ImageBuf(np.full((4, 6, 1), 0.5, np.float32))
    grey.write(str(tmp_path / "grey.tif"))
    loaded = images.load(str(tmp_path / "grey.tif"))
    np.testing.assert_allclose(loaded.pixels[0, 0], [images.srgb_decode(np.float32(0.5))] * 3, rtol=1e-3)
    assert "greyscale" in loaded.notices[0]


def test_unreadable_targets_say_what_they_are(tmp_path):
    with pytest.raises(ImageError, match="is a directory, not a picture"):
        images.load(str(tmp_path))
    with pytest.raises(ImageError, match="is not a regular file"):
        images.load("/dev/zero")
    with pytest.raises(ImageError, match="does not exist"):
        images.load(str(tmp_path / "none.png"))
    name = os.fsdecode(bytes(tmp_path) + b"/edit\xff.png")  # a name that is not UTF-8 (OpenImageIO raised TypeError)
    images.write(str(tmp_path / "ok.png"), np.zeros((4, 4, 3), np.float32))
    os.rename(tmp_path / "ok.png", name)
    with pytest.raises(ImageError, match=r"edit\\xff\.png is not valid UTF-8.*rename the file"):
        images.load(name)


def test_a_truncated_or_corrupt_jpeg_is_refused_and_a_whole_one_read(tmp_path, capfd):
    ramp = np.linspace(0.05, 0.9, 64, dtype=np.float32)
    linear = np.stack(np.broadcast_arrays(ramp[:, None], ramp[None, :], 0.3), axis=-1).astype(np.float32)
    images.write(str(tmp_path / "whole.jpg"), linear)
    data = (tmp_path / "whole.jpg").read_bytes()
    middle = (data.index(b"\xff\xda") + len(data)) // 2  # halfway through the coded pixels (the header is whole)
    (tmp_path / "cut.jpg").write_bytes(data[:middle])
    corrupt = bytearray(data)
    corrupt[middle : middle + 50] = b"\xff" * 50  # a run of bytes overwritten in the coded data
    (tmp_path / "corrupt.jpeg").write_bytes(bytes(corrupt))
    (tmp_path / "named.png").write_bytes(data[:middle])  # a JPEG under another name
    whole = images.read(str(tmp_path / "whole.jpg"))
    assert whole.shape == (64, 64, 3) and np.abs(images.srgb_encode(whole) - images.srgb_encode(linear)).max() < 0.05
    capfd.readouterr()
    for name, reason in (
        ("cut.jpg", "Premature end of JPEG file"),
        ("corrupt.jpeg", "Corrupt JPEG data"),
        ("named.png", "Premature end of JPEG file"),
    ):
        with pytest.raises(
            ImageError, match=rf"^{tmp_path}/{name} is damaged or truncated \(JPEG error: {reason}.*\): export"
        ):
            images.load(str(tmp_path / name))
    assert capfd.readouterr().err == ""


def test_a_truncated_png_is_one_error_and_nothing_on_stderr(tmp_path, capfd):
    images.write(str(tmp_path / "whole.png"), np.random.default_rng(0).random((64, 64, 3)).astype(np.float32))
    (tmp_path / "cut.png").write_bytes((tmp_path / "whole.png").read_bytes()[:3000])
    capfd.readouterr()
    with pytest.raises(ImageError, match=r"cut\.png is damaged or truncated"):
        images.load(str(tmp_path / "cut.png"))
    assert capfd.readouterr().err == ""  # libpng printed its own error twice
