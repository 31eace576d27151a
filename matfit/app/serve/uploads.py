"""What the page may send: the caps on request bodies and uploads, the private copies of uploaded pictures and their
checks, the JSON bodies and the 19 values in them.

Uploads are written under a private temporary folder (never under a name the browser sent) and
read by the CLI's own reader (`fitfile.read_target`). Each is removed when it is refused or when its job ends;
the folder is named after its server (`matfit-serve-<pid>@<host>-...`), and a new server removes the folders
of servers that are gone (`kill -9` leaves its folder behind).

Request bodies are capped and counted as they arrive (nothing beyond the cap is read): MAX_JSON_BYTES
for the JSON requests and a params.json upload, MAX_FIT_BYTES for a fit's form (a picture and a mask
of at most MAX_UPLOAD_BYTES each); a larger body is answered 413 with a one-line message.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import re
import tempfile

import numpy as np

from matfit import documents, files, images, interrupt, params
from matfit.errors import FitError, ImageError, MatfitError, ParameterError

MAX_UPLOAD_BYTES = 50 * 1024 * 1024  # an upload larger than this is refused before it is read
MAX_JSON_BYTES = 1024 * 1024  # the body of a JSON request (19 values: a few hundred bytes) or of a params.json upload
MAX_FIT_BYTES = 2 * MAX_UPLOAD_BYTES + MAX_JSON_BYTES  # a fit's form: a picture, a mask, the initial values
MAX_UPLOAD_PIXELS = 16_000_000  # and one with more pixels before they are decoded
TOO_LARGE = "upload size"  # the `field` of an upload refused for its size: answered 413, other bad uploads 400
VALUES_FIX = 'send {"values": [19 numbers]}, one per parameter of `matfit params`'
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".hdr")
FOLDER_PREFIX = "matfit-serve-"  # a server's private folder: matfit-serve-<pid>@<host>-<random>
UPLOAD_NAME = re.compile(r"tmp[A-Za-z0-9_]+(" + "|".join(re.escape(e) for e in IMAGE_EXTENSIONS) + ")")


def private_folder() -> str:
    """Returns a new private temporary folder for this server's uploads, named after its owner, once the folders of
    servers of this host that are gone are removed (`remove_orphans`)."""
    remove_orphans(tempfile.gettempdir())
    folder = tempfile.mkdtemp(prefix=f"{FOLDER_PREFIX}{files.owner()}-")
    interrupt.register(folder)  # a Ctrl-C that skips the studio's `close` still removes it
    return folder


def remove_orphans(directory: str) -> list[str]:
    """Removes the upload folders in `directory` whose server, a process of this host, is gone; returns them.

    Only what a server writes is removed: folders of this user named `matfit-serve-<pid>@<host>-...`, and in them
    regular files named as `save_upload` names them, each looked up relative to the folder opened without following
    links (a link planted there costs no one's file). A folder still holding anything else is left.
    """
    host = files.owner().partition("@")[2]
    owned = re.compile(re.escape(FOLDER_PREFIX) + r"(\d+)@" + re.escape(host) + r"-[A-Za-z0-9_]+")
    try:
        with os.scandir(directory) as listing:
            names = [entry.name for entry in listing]
    except OSError:
        return []
    removed = []
    for name in names:
        match = owned.fullmatch(name)
        if match is None or files.running(int(match.group(1))):
            continue
        path = os.path.join(directory, name)
        with contextlib.suppress(OSError):  # another server removing it too, or something of someone else's in it
            _remove_uploads(path)
            os.rmdir(path)
            removed.append(path)
    return removed


def _remove_uploads(path: str) -> None:
    """Removes the uploads (regular files named as `save_upload` names them) of the folder `path`, if it is a folder
    of this user and not a link; every name is looked up relative to the open folder."""
    folder = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    try:
        if os.fstat(folder).st_uid != os.getuid():
            raise PermissionError(path)
        with os.scandir(folder) as listing:
            names = [e.name for e in listing if UPLOAD_NAME.fullmatch(e.name) and e.is_file(follow_symlinks=False)]
        for name in names:
            os.unlink(name, dir_fd=folder)
    finally:
        os.close(folder)


def discard(*paths: str | None) -> None:
    """Removes the private copies of uploads (a refused one, or one whose job has ended)."""
    for path in paths:
        if path is not None:
            with contextlib.suppress(OSError):
                os.unlink(path)
            interrupt.unregister(path)


def check_values(values: object) -> np.ndarray:
    """Returns 19 physical parameter values from the page, checked against their ranges as params.json is."""
    if not isinstance(values, list) or len(values) != params.COUNT:
        raise ParameterError(f"values must be a list of {params.COUNT} numbers, one per parameter of `matfit params`")
    return params.from_mapping(dict(zip(params.NAMES, values, strict=True)))


def init_values(text: str) -> np.ndarray:
    """Returns the 19 physical values of a fit form's `init` field: {"values": [19 numbers]}, as the other requests
    send them, or the list alone."""
    document = documents.parse(text, "the init field", VALUES_FIX, ParameterError)
    return check_values(document.get("values") if isinstance(document, dict) else document)


def check_mask(mask: str, target: str, resolution: int, name: str) -> None:
    """Raises FitError (answered 400) for an uploaded mask the fit would refuse (another size than the picture, black
    everywhere), naming the upload `name` rather than its private copy."""
    from matfit.fitting import fitfile

    width, height = images.header(target)[:2]
    try:
        fitfile.read_mask(mask, (height, width), resolution)
    except MatfitError as error:
        raise FitError(str(error).replace(mask, repr(name)), field=error.field) from None


def save_upload(folder: str, data: bytes, filename: str | None, kind: str, size: int | None = None) -> str:
    """Returns the path of a private temporary copy, in `folder`, of an uploaded picture; only the name's extension
    is kept. `size`: the upload's whole size in bytes where `data` is only its start (None: `data` is all of it).

    A picture refused here leaves no copy."""
    size = len(data) if size is None else size
    if size > MAX_UPLOAD_BYTES or len(data) > MAX_UPLOAD_BYTES:
        raise ImageError(f"the {kind} is {megabytes(max(size, len(data)))}: scale it down", field=TOO_LARGE)
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
    try:
        with os.fdopen(handle, "wb") as file:
            file.write(data)
        check_picture(path, kind)
    except BaseException:
        discard(path)
        raise
    return path


def megabytes(size: int) -> str:
    """Returns "N MB, more than the M MB an upload may be" for an upload of `size` bytes over MAX_UPLOAD_BYTES: N
    rounded up to a tenth, so that it reads as more than M (1 MB: 2**20 bytes, as the request caps say)."""
    shown = math.ceil(size / 2**20 * 10) / 10
    return f"{shown:g} MB, more than the {MAX_UPLOAD_BYTES / 2**20:g} MB an upload may be"


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
    # the check decodes the picture: off the event loop
    return await asyncio.to_thread(save_upload, folder, data, upload.filename, kind, upload.size)


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
