"""The request of one fit made of the public API's arguments (`request_of`): what `Fitter.fit`, `Fitter.fit_all`
and `fit_sequence` hand to the fitting stages, each argument checked first."""

from __future__ import annotations

import hashlib
import os
from typing import TYPE_CHECKING

import numpy as np

from matfit.api.arguments import ARRAY, Picture, linear_pixels, path_text, picture_size, read_pixels
from matfit.api.choices import check_choices, check_options
from matfit.api.material import Material
from matfit.api.results import Outputs
from matfit.errors import ImageError
from matfit.fitting.methods import Settings

if TYPE_CHECKING:
    from matfit.fitting.request import Request
    from matfit.model.models import Loader


def request_of(
    loader: Loader,
    variant: str | None,
    picture: Picture,
    mask: Picture | None,
    init: str | os.PathLike[str] | Material | None,
    settings: Settings | None,
    linear: bool,
    verified: bool,
    corrections: int | None,
    answer: str,
    refine: int,
    seed: int,
    outputs: Outputs | None = None,
) -> tuple[Request, list[str]]:
    """Returns (the request of one fit, notices of the pixels read here): a picture file's as `matfit fit` makes
    it, an array's with its pixels as the target of the model of `loader` (a `Fitter`: its model loads here only
    for an array)."""
    from matfit.fitting import search
    from matfit.fitting.request import Request

    check_choices(settings, init, outputs)
    linear, verified, corrections, refine, seed = check_options(linear, verified, corrections, answer, refine, seed)
    initial = (
        None if init is None else "Material" if isinstance(init, Material) else path_text(init),
        init.array() if isinstance(init, Material) else None,
    )
    target, pixels, digest, notices = ARRAY, None, None, list[str]()
    size: tuple[int, int] | None = None  # an array's (height, width)
    if isinstance(picture, str | os.PathLike):
        if linear:
            raise ImageError(
                "linear=True describes an array's values; a picture file says itself how it is encoded "
                "(EXR and HDR linear, the others sRGB): leave linear out",
                field="linear",
            )
        target = path_text(picture)
    else:
        given, notices = linear_pixels(picture, "picture", linear=linear)
        size = (given.shape[0], given.shape[1])
        pixels, more = search.prepare_target(given, loader.model.resolution, "the picture array")
        digest = hashlib.sha256(np.ascontiguousarray(np.asarray(picture)).tobytes()).hexdigest()
        notices += more
    named_mask, weights = None, None
    if isinstance(mask, str | os.PathLike):
        named_mask = path_text(mask)
        if size is not None:  # the mask of an array is sized by the array: read here
            weights = search.prepare_mask(read_pixels(named_mask, "mask"), size, loader.model.resolution, named_mask)
    elif mask is not None:
        named_mask = ARRAY
        mask_pixels = linear_pixels(mask, "mask", linear=False)[0]
        weights = search.prepare_mask(mask_pixels, size or picture_size(target), loader.model.resolution, "array")
    request = Request(
        target,
        named_mask,
        initial[0],
        init_values=initial[1],
        seed=seed,
        settings=settings or Settings(),
        verified=verified,
        corrections=corrections,
        refine_steps=refine,
        variant=variant,
        answer=answer,
        pixels=pixels,
        weights=weights,
        target_sha256=digest,
        outputs=None if outputs is None else outputs._request(),
    )
    return request, notices
