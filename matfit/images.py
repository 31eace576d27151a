"""Image files and colour encoding: the only module that imports OpenImageIO.

Renders are linear RGB. Everything compared or reported (losses, RMSE) is on sRGB-encoded values,
as in the paper: `rmse` measures on 0-255 sRGB. PNG, JPEG and TIFF are written as 8-bit sRGB; EXR and
HDR as linear float.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, overload

import numpy as np
import OpenImageIO as oiio

from matfit.errors import ImageError, printable
from matfit.files import Named, check_outputs, check_writable, final_name, write_bytes

if TYPE_CHECKING:
    import jax
    from jaxtyping import Float

LINEAR_EXTENSIONS = (".exr", ".hdr")
DISPLAY_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


def srgb_encode(linear: Float[np.ndarray, "*shape"]) -> Float[np.ndarray, "*shape"]:
    """Returns sRGB-encoded values in [0, 1] for linear values (clipped to [0, 1] first)."""
    x = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def srgb_decode(encoded: Float[np.ndarray, "*shape"]) -> Float[np.ndarray, "*shape"]:
    """Returns linear values for sRGB-encoded values in [0, 1]."""
    x = np.clip(np.asarray(encoded, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


def srgb_slope(linear: Float[np.ndarray, "*shape"]) -> Float[np.ndarray, "*shape"]:
    """Returns the slope of `srgb_encode`'s curve at linear values in [0, 1], ignoring its clip (1.055/2.4 at 1)."""
    x = np.asarray(linear, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92, 1.055 / 2.4 * np.maximum(x, 0.0031308) ** (1.0 / 2.4 - 1.0))


@overload
def rmse(
    images: Float[np.ndarray, "*batch H W 3"],
    targets: Float[np.ndarray, "*#batch H W 3"],
    weights: Float[np.ndarray, "H W"] | None = None,
) -> Float[np.ndarray, "*batch"]: ...
@overload
def rmse(
    images: Float[jax.Array, "*batch H W 3"],
    targets: Float[np.ndarray | jax.Array, "*#batch H W 3"],
    weights: Float[np.ndarray | jax.Array, "H W"] | None = None,
) -> Float[jax.Array, "*batch"]: ...
def rmse(
    images: Float[np.ndarray | jax.Array, "*batch H W 3"],
    targets: Float[np.ndarray | jax.Array, "*#batch H W 3"],
    weights: Float[np.ndarray | jax.Array, "H W"] | None = None,
) -> Float[np.ndarray | jax.Array, "*batch"]:
    """Returns the RMSE on the 0-255 scale of sRGB images (..., H, W, 3) against targets: one figure per image.

    Targets are (H, W, 3), one for every image, or (..., H, W, 3), one each. With per-pixel weights
    (H, W) (a mask) it is 255 sqrt(sum_p w_p |I_p - t_p|^2 / (3 sum_p w_p)); without, every pixel
    counts once. The one RMSE of matfit: training, evaluation, fitting and the bench use it. It is
    written with array methods only, so NumPy arrays give NumPy figures and JAX arrays (traced,
    batched, differentiated) give JAX figures.
    """
    if images.ndim < 3 or targets.ndim < 3 or tuple(images.shape[-3:]) != tuple(targets.shape[-3:]):
        raise ValueError(f"Shape mismatch: got {tuple(images.shape)} and {tuple(targets.shape)}.")
    rank = max(images.ndim, targets.ndim)
    images = images.reshape((1,) * (rank - images.ndim) + tuple(images.shape))
    targets = targets.reshape((1,) * (rank - targets.ndim) + tuple(targets.shape))
    squared = (images - targets) ** 2
    if weights is None:
        return 255.0 * squared.mean(axis=(-3, -2, -1)) ** 0.5
    if tuple(weights.shape) != tuple(images.shape[-3:-1]):
        raise ValueError(f"Shape mismatch: weights {tuple(weights.shape)} for images {tuple(images.shape)}.")
    weighted = weights.reshape((1,) * (rank - 3) + (*weights.shape, 1)) * squared
    return 255.0 * (weighted.sum(axis=(-3, -2, -1)) / (3.0 * weights.sum())) ** 0.5


def residual_products(
    renders: Float[np.ndarray, "m H W 3"], target: Float[np.ndarray, "H W 3"], weights: Float[np.ndarray, "H W"]
) -> Float[np.ndarray, "m m"]:
    """Returns the (m, m) weighted mean products of m sRGB renders' residuals against `target` (`rmse`'s weighting):
    entry (i, j) is sum_p w_p (R_i - t)_p . (R_j - t)_p / (3 sum_p w_p)."""
    m = len(renders)
    residuals = (np.asarray(renders, np.float64) - np.asarray(target, np.float64)).reshape(m, -1, 3)
    weighted = residuals * (np.asarray(weights, np.float64).reshape(1, -1, 1) / (3.0 * float(np.sum(weights))))
    return np.einsum("ipc,jpc->ij", weighted, residuals)


def noise_free_mse(
    renders: Float[np.ndarray, "m H W 3"], target: Float[np.ndarray, "H W 3"], weights: Float[np.ndarray, "H W"]
) -> float:
    """Returns the unbiased estimate of the weighted mean squared error (`rmse`'s weighting, sRGB units squared) of
    a material's noise-free render against `target`, from m >= 2 independent sRGB renders of it (m, H, W, 3).

    It is the mean over pairs i != j of `residual_products`: the cross terms of independent renders have the squared
    error of the mean render as their expectation and the noise's variance none. A render's own noise, which `rmse`
    counts, favours the material that renders with less noise; this does not. Below the error's resolution it can
    be negative.
    """
    m = len(renders)
    if m < 2:
        raise ValueError(f"{m} render: the estimate needs at least 2 independent renders")
    gram = residual_products(renders, target, weights)
    return float((gram.sum() - np.diag(gram).sum()) / (m * (m - 1)))


def noise_free_difference(
    renders: Float[np.ndarray, "m H W 3"],
    others: Float[np.ndarray, "m H W 3"],
    target: Float[np.ndarray, "H W 3"],
    weights: Float[np.ndarray, "H W"],
) -> tuple[float, float]:
    """Returns (d, its standard error): d is `noise_free_mse` of `renders` less that of `others` (m >= 2
    independent sRGB renders of each of two materials, best at common seeds), sRGB units squared.

    The standard error is over the pixels: each pixel's own estimate of the difference (the mean over pairs i != j
    of its residuals' products, less the others'), spread about d, weighted as d is. It measures how far d would
    move with other renders and other pixels of the same kind; a difference of a few standard errors is one the
    renders decide."""
    m = len(renders)
    if m < 2 or len(others) != m:
        raise ValueError(f"{m} and {len(others)} renders: the difference needs at least 2 of each, as many")

    def pixels(stack: np.ndarray) -> np.ndarray:
        residuals = np.asarray(stack, np.float64) - np.asarray(target, np.float64)
        total = residuals.sum(axis=0)
        return ((total * total).sum(axis=-1) - (residuals * residuals).sum(axis=(0, -1))) / (3.0 * m * (m - 1))

    w = np.asarray(weights, np.float64)
    x = pixels(renders) - pixels(others)
    d = float((w * x).sum() / w.sum())
    return d, float(np.sqrt((w * w * (x - d) ** 2).sum()) / w.sum())


def box_downsample(linear: Float[np.ndarray, "*batch H W C"], size: int) -> Float[np.ndarray, "*batch size size C"]:
    """Returns images (..., H, W, C) averaged over square blocks down to (..., size, size, C).

    H and W must be equal and a multiple of `size`; averaging linear values is what a render at
    the lower resolution would show.
    """
    linear = np.asarray(linear, dtype=np.float32)
    height, width = linear.shape[-3:-1]
    if height != width or height % size:
        raise ValueError(
            f"cannot box-filter a {height}x{width} image down to {size}x{size}: the side must be a multiple of {size}"
        )
    factor = height // size
    blocks = linear.reshape(*linear.shape[:-3], size, factor, size, factor, linear.shape[-1])
    return blocks.mean(axis=(-4, -2))


def check_extension(path: str) -> str:
    """Returns the lower-case extension of an image path, if it is one matfit writes."""
    extension = os.path.splitext(path)[1].lower()
    if extension not in LINEAR_EXTENSIONS + DISPLAY_EXTENSIONS:
        supported = ", ".join(LINEAR_EXTENSIONS + DISPLAY_EXTENSIONS)
        raise ImageError(f"cannot write {path}: unknown image type {extension or '(none)'}; use one of {supported}")
    return extension


def check_output(path: str, inputs: Named | None = None) -> None:
    """Raises ImageError or OutputError unless an image can be written at `path` (known type, writable place).

    `inputs` ({"params_file": path}, ...): the command's inputs, which the image must not overwrite.
    """
    check_extension(path)
    check_outputs({"output": path}, inputs)


def write(path: str, linear: Float[np.ndarray, "H W C"]) -> None:
    """Writes a linear (H, W, 3) image atomically: sRGB 8-bit for PNG/JPEG/TIFF, float for EXR/HDR.

    The file is encoded in memory first and then written, flushed and size-checked by
    `files.write_bytes`: OpenImageIO's writers report a full disk badly (the PNG writer not at
    all, leaving a truncated file; the JPEG writer by aborting the interpreter), so they never
    write to the disk themselves.
    """
    extension = check_extension(path)
    check_writable(path)
    write_bytes(path, encode(linear, extension, final_name(path)))


def encode(linear: Float[np.ndarray, "H W C"], extension: str, path: str = "the image") -> bytes:
    """Returns the bytes of an image file of type `extension` (".png", ".exr", ...) holding a linear (H, W, 3) image."""
    linear = np.asarray(linear, dtype=np.float32)
    if extension in LINEAR_EXTENSIONS:
        pixels, pixel_type = np.ascontiguousarray(linear), "float"
    else:
        pixels, pixel_type = np.round(srgb_encode(linear) * 255.0).astype(np.uint8), "uint8"
    height, width, channels = pixels.shape
    with memory_file(extension) as (name, handle):
        output = oiio.ImageOutput.create(extension.lstrip("."))
        if output is None:
            raise ImageError(f"cannot write {path}: {oiio.geterror()}")
        spec = oiio.ImageSpec(width, height, channels, pixel_type)
        if extension in DISPLAY_EXTENSIONS:
            spec.attribute("oiio:ColorSpace", "sRGB")
        ok = output.open(name, spec) and output.write_image(pixels)
        error = output.geterror()
        output.close()
        if not ok:
            raise ImageError(f"cannot write {path}: {error}")
        size = os.fstat(handle).st_size
        return os.pread(handle, size, 0)


@contextlib.contextmanager
def memory_file(extension: str) -> Iterator[tuple[str, int]]:
    """Yields (a path OpenImageIO can open, its descriptor) of an anonymous file in memory (without memfd: in /tmp)."""
    if hasattr(os, "memfd_create"):
        handle = os.memfd_create("matfit-image")
        try:
            yield f"/proc/self/fd/{handle}", handle
        finally:
            os.close(handle)
    else:
        with tempfile.NamedTemporaryFile(suffix=extension) as file:
            yield file.name, file.fileno()


def first_line(text: str | None, default: str) -> str:
    """Returns the first non-empty line of an OpenImageIO error message, or `default`."""
    lines = [line.strip() for line in (text or "").splitlines() if line.strip()]
    return lines[0] if lines else default


MAX_PIXELS = 50_000_000  # larger inputs are refused before their pixels are decoded


def header(path: str) -> tuple[int, int, int, int]:
    """Returns (width, height, channels, alpha channel index or -1) from an image file's header only."""
    check_readable(path)
    with quiet_stderr():
        reader = oiio.ImageInput.open(path)
    if reader is None:
        reason = first_line(oiio.geterror(), "unknown format")
        raise ImageError(f"{path} is not an image OpenImageIO can read ({reason}): export it as PNG, TIFF, JPEG or EXR")
    spec = reader.spec()
    reader.close()
    return spec.width, spec.height, spec.nchannels, spec.alpha_channel


def check_readable(path: str) -> None:
    """Raises ImageError unless `path` names a non-empty regular file that OpenImageIO can open by that name."""
    if os.path.isdir(path):
        raise ImageError(f"{printable(path)} is a directory, not a picture: give the image file's path")
    if not os.path.exists(path):
        raise ImageError(f"{printable(path)} does not exist: check the path")
    if not os.path.isfile(path):
        raise ImageError(f"{printable(path)} is not a regular file (a device or a pipe): give the image file's path")
    if os.path.getsize(path) == 0:
        raise ImageError(f"{printable(path)} is empty: export the image again")
    try:
        path.encode()
    except UnicodeEncodeError:
        raise ImageError(
            f"the file name {printable(path)} is not valid UTF-8, which OpenImageIO cannot open: rename the file"
        ) from None


@contextlib.contextmanager
def quiet_stderr() -> Iterator[None]:
    """Sends what C libraries print to standard error (libpng's own warnings) to /dev/null inside the block.

    OpenImageIO reports a damaged file through its error message, which matfit words as one
    line; libpng also prints its own message, twice, straight to file descriptor 2.
    """
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


@dataclass
class Loaded:
    """An image file's pixels (linear float32 (H, W, 3)) and what was done to make them RGB."""

    pixels: Float[np.ndarray, "H W 3"]
    notices: list[str]


def load(path: str, max_pixels: int = MAX_PIXELS) -> Loaded:
    """Returns an image file as linear RGB float32, with notices for dropped alpha or grey input.

    Display formats (PNG, JPEG, TIFF, any bit depth) are sRGB-decoded; EXR and HDR are linear.
    Refuses missing, unreadable, truncated, oversized (more than `max_pixels`) and non-finite images.
    """
    width, height, channels, alpha = header(path)
    if width * height > max_pixels:
        raise ImageError(
            f"{path} is {width}x{height} = {width * height / 1e6:.0f} Mpixel, more than {max_pixels / 1e6:.0f}: "
            "scale it down first"
        )
    pixels = decode_jpeg(path) if is_jpeg(path) else decode(path)
    pixels = np.asarray(pixels, dtype=np.float32).reshape(height, width, channels)
    notices = []
    if channels in (1, 2):
        notices.append(f"{path}: greyscale image, replicated to RGB")
        pixels = np.repeat(pixels[:, :, :1], 3, axis=2)
    elif channels >= 3:
        if channels > 3:
            dropped = "alpha" if alpha == 3 else f"channels 4 to {channels}"
            notices.append(f"{path}: {dropped} dropped (the colour is used as it is, not composited)")
        pixels = pixels[:, :, :3]
    if not np.all(np.isfinite(pixels)):
        raise ImageError(f"{path} contains NaN or infinite values: fix or clamp them in your editor")
    if os.path.splitext(path)[1].lower() not in LINEAR_EXTENSIONS:
        pixels = srgb_decode(pixels)
    return Loaded(np.ascontiguousarray(pixels), notices)


def decode(path: str) -> Float[np.ndarray, "H W C"]:
    """Returns the pixels of an image file as OpenImageIO decodes them (float); ImageError if damaged or truncated."""
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # the colour as painted, not multiplied by alpha
    with quiet_stderr():
        buffer = oiio.ImageBuf(path, 0, 0, config)
        pixels = buffer.get_pixels(oiio.FLOAT)
    if buffer.has_error or pixels is None or pixels.size == 0:
        message = first_line(buffer.geterror() if buffer.has_error else "", "no pixels")
        raise ImageError(f"{path} is damaged or truncated ({message}): export it again")
    return pixels


JPEG_START = b"\xff\xd8\xff"


def is_jpeg(path: str) -> bool:
    """Returns whether a file begins as a JPEG does (whatever its name says)."""
    with open(path, "rb") as file:
        return file.read(len(JPEG_START)) == JPEG_START


def decode_jpeg(path: str) -> Float[np.ndarray, "H W C"]:
    """Returns the pixels of a JPEG file (float); ImageError if it is truncated or its data is corrupt.

    libjpeg only warns of a truncated file or corrupt data (and fills the rest with grey); OpenImageIO's
    ImageBuf drops those warnings, but the reader keeps them in its error state, which is checked here.
    """
    with quiet_stderr():
        reader = oiio.ImageInput.open(path)
        if reader is None:
            raise ImageError(
                f"{path} is damaged or truncated ({first_line(oiio.geterror(), 'no header')}): export it again"
            )
        pixels = reader.read_image(oiio.FLOAT)
        message = reader.geterror()
        reader.close()
    if message or pixels is None or pixels.size == 0:
        reason = first_line(message, "no pixels").replace(f' ("{path}")', "")
        raise ImageError(f"{path} is damaged or truncated ({reason}): export it again")
    return pixels


def read(path: str) -> Float[np.ndarray, "H W 3"]:
    """Returns an image file as linear float32 (H, W, 3); display formats are sRGB-decoded."""
    return load(path).pixels


# Downsampling filter: matches Mitsuba's default Gaussian reconstruction filter, so that a large
# render resized to the model's resolution looks like a render made at that resolution. Measured
# on a 256 px render of red plastic against a 64 px one: RMSE 1.2 with this filter, 6.1 with
# OpenImageIO's default, 3.5 with a box (both at 256-512 spp, whose noise is about 1.5).
DOWNSAMPLE_FILTER = ("gaussian", 2.0)


def resample(linear: Float[np.ndarray, "H W C"], width: int, height: int) -> Float[np.ndarray, "height width C"]:
    """Returns a linear image (H, W, C) resized to (height, width, C) with OpenImageIO.

    Shrinking uses DOWNSAMPLE_FILTER (width in output pixels); enlarging uses OpenImageIO's default.
    """
    linear = np.ascontiguousarray(linear, dtype=np.float32)
    if linear.shape[:2] == (height, width):
        return linear
    channels = linear.shape[2]
    roi = oiio.ROI(0, width, 0, height, 0, 1, 0, channels)
    source = oiio.ImageBuf(linear)
    if width < linear.shape[1] and height < linear.shape[0]:
        name, filter_width = DOWNSAMPLE_FILTER
        resized = oiio.ImageBufAlgo.resize(source, filtername=name, filterwidth=filter_width, roi=roi)
    else:
        resized = oiio.ImageBufAlgo.resize(source, roi=roi)
    if resized.has_error:
        raise ImageError(f"cannot resample the image to {width}x{height}: {resized.geterror()}")
    return np.asarray(resized.get_pixels(oiio.FLOAT), np.float32).reshape(height, width, channels)


def label(image_srgb: Float[np.ndarray, "H W 3"], text: str, height: int = 14) -> Float[np.ndarray, "H+height W 3"]:
    """Returns an sRGB image with a caption strip of `height` pixels rendered under it."""
    width = image_srgb.shape[1]
    strip = oiio.ImageBuf(oiio.ImageSpec(width, height, 3, "float"))
    oiio.ImageBufAlgo.fill(strip, (0.0, 0.0, 0.0))
    oiio.ImageBufAlgo.render_text(strip, 3, height - 3, text, fontsize=height - 3, textcolor=(1.0, 1.0, 1.0))
    caption = np.asarray(strip.get_pixels(oiio.FLOAT), dtype=np.float32).reshape(height, width, 3)
    return np.concatenate([image_srgb, caption], axis=0)
