"""What the page may send: the caps on request bodies and uploads, the private copies of uploaded pictures and their
checks, the JSON bodies and the 19 values in them.

Uploads are written under a private temporary folder (never under a name the browser sent) and
read by the CLI's own reader (`fitfile.read_target`).

Request bodies are capped and counted as they arrive (nothing beyond the cap is read): MAX_JSON_BYTES
for the JSON requests and a params.json upload, MAX_FIT_BYTES for a fit's form (a picture and a mask
of at most MAX_UPLOAD_BYTES each); a larger body is answered 413 with a one-line message.
"""

from __future__ import annotations

import asyncio
import os
import tempfile

import numpy as np

from matfit import documents, images, interrupt, params
from matfit.errors import ImageError, MatfitError, ParameterError

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


def save_upload(folder: str, data: bytes, filename: str | None, kind: str) -> str:
    """Returns the path of a private temporary copy, in `folder`, of an uploaded picture; only the name's extension
    is kept."""
    if len(data) > MAX_UPLOAD_BYTES:
        raise ImageError(
            f"the {kind} is {len(data) / 1e6:.0f} MB, more than {MAX_UPLOAD_BYTES / 1e6:.0f} MB: scale it down",
            field=TOO_LARGE,
        )
    if not data:
        raise ImageError(f"the {kind} is empty: choose the picture again")
    extension = os.path.splitext(filename or "")[1].lower()
    if extension not in IMAGE_EXTENSIONS:
        raise ImageError(
            f"the {kind} {filename!r} is not a picture matfit reads: upload a PNG, JPEG, TIFF or EXR "
            f"({', '.join(IMAGE_EXTENSIONS)})"
        )
    handle, path = tempfile.mkstemp(suffix=extension, dir=folder)
    interrupt.register(path)  # removed even when Ctrl-C ends the process without its teardown
    with os.fdopen(handle, "wb") as file:
        file.write(data)
    check_picture(path, kind)
    return path


def check_picture(path: str, kind: str) -> None:
    """Raises ImageError for a picture the CLI's reader refuses (damaged, truncated), or one with too many pixels
    (before its pixels are decoded), before queueing."""
    try:
        width, height, _, _ = images.header(path)
        if width * height > MAX_UPLOAD_PIXELS:
            raise ImageError(
                f"the {kind} is {width}x{height}, more than {MAX_UPLOAD_PIXELS / 1e6:.0f} Mpixel: scale it down",
                field=TOO_LARGE,
            )
        images.load(path, MAX_UPLOAD_PIXELS)
    except ImageError as error:
        raise ImageError(str(error).replace(path, f"the uploaded {kind}"), field=error.field) from None


async def read_upload(form, key: str, kind: str, folder: str) -> str | None:
    """Returns the path of the private copy of the form's picture `key` (None if the form has none), read up to
    MAX_UPLOAD_BYTES and checked off the event loop (the check decodes it)."""
    upload = form.get(key)
    if upload is None or isinstance(upload, str):
        return None
    data = await upload.read(MAX_UPLOAD_BYTES + 1)
    return await asyncio.to_thread(save_upload, folder, data, upload.filename, kind)  # it decodes the picture


def capped(request, cap: int, fix: str):
    """Returns the request with its body counted as it arrives: an error (answered 413) once it passes `cap`
    bytes, or at once when its Content-Length says it will. Nothing beyond the cap is read."""
    from starlette.requests import Request

    def too_large() -> MatfitError:
        return MatfitError(f"the request body is more than {cap / 2**20:g} MB, the most it may be: {fix}", TOO_LARGE)

    length = request.headers.get("content-length", "")
    if length.isdigit() and int(length) > cap:
        raise too_large()
    received = 0

    async def receive():
        nonlocal received
        message = await request.receive()
        if message["type"] == "http.request":
            received += len(message.get("body", b""))
            if received > cap:
                raise too_large()
        return message

    return Request(request.scope, receive)


async def json_body(request) -> dict:
    """Returns the request's JSON object, read up to MAX_JSON_BYTES; MatfitError (400, or 413 when too large)."""
    body = bytearray()
    async for chunk in capped(request, MAX_JSON_BYTES, VALUES_FIX).stream():
        body += chunk
    document = documents.parse(bytes(body), "the request", VALUES_FIX, ParameterError)
    if not isinstance(document, dict):
        raise ParameterError(f'the request must be a JSON object with "values": {VALUES_FIX}')
    return document
