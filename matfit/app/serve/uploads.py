"""What the page may send: the caps on request bodies and uploads, and the check of the 19 values it sends.

Uploads are written under a private temporary folder (never under a name the browser sent) and
read by the CLI's own reader (`fitfile.read_target`).

Request bodies are capped and counted as they arrive (nothing beyond the cap is read): MAX_JSON_BYTES
for the JSON requests and a params.json upload, MAX_FIT_BYTES for a fit's form (a picture and a mask
of at most MAX_UPLOAD_BYTES each); a larger body is answered 413 with a one-line message.
"""

from __future__ import annotations

import numpy as np

from matfit import params
from matfit.errors import ParameterError

MAX_UPLOAD_BYTES = 50 * 1024 * 1024  # an upload larger than this is refused before it is read
MAX_JSON_BYTES = 1024 * 1024  # the body of a JSON request (19 values: a few hundred bytes) or of a params.json upload
MAX_FIT_BYTES = 2 * MAX_UPLOAD_BYTES + MAX_JSON_BYTES  # a fit's form: a picture, a mask, the initial values
MAX_UPLOAD_PIXELS = 16_000_000  # and one with more pixels before they are decoded
TOO_LARGE = "upload size"  # the `field` of an upload refused for its size: answered 413, other bad uploads 400
VALUES_FIX = 'send {"values": [19 numbers]}, one per parameter of `matfit params`'
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".hdr")


def check_values(values: object) -> np.ndarray:
    """Returns 19 physical parameter values from the page, checked against their ranges as params.json is."""
    if not isinstance(values, list) or len(values) != params.COUNT:
        raise ParameterError(f"values must be a list of {params.COUNT} numbers, one per parameter of `matfit params`")
    return params.from_mapping(dict(zip(params.NAMES, values, strict=True)))
