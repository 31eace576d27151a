"""The watched file or folder: which saved picture to refit, and when it is complete enough to read.

A watched file that changes while its fit runs supersedes it; a file still being written
(unreadable, or growing) is retried, not reported. A watched file deleted before or while it is
fitted ends its job as an error answered 410.
"""

from __future__ import annotations

import asyncio
import os
import time

from matfit import images
from matfit.app.serve import uploads
from matfit.app.serve.uploads import IMAGE_EXTENSIONS
from matfit.errors import ImageError

GONE = "gone"  # the `field` of a watched file deleted before or while it was fitted: answered 410
SETTLE_SECONDS = 0.15  # a watched file must keep its size this long before it is read
RETRY_SECONDS = 3.0  # an unreadable watched file (still being written) is retried this long before it is an error


def gone(path: str, when: str) -> ImageError:
    """Returns the error of a watched file deleted `when` ("while it was fitted"), answered 410."""
    return ImageError(f"the watched file {path} was deleted {when}: save it again from your editor", field=GONE)


async def settled(path: str) -> tuple[str, int] | None:
    """Returns None once `path` is a complete picture (size steady, readable), or (the error, its HTTP status) after
    RETRY_SECONDS: 410 for a file that is gone, 422 for one that stays unreadable."""
    deadline = time.monotonic() + RETRY_SECONDS
    error = None
    while time.monotonic() < deadline:
        try:
            before = os.path.getsize(path)
            await asyncio.sleep(SETTLE_SECONDS)
            if os.path.getsize(path) != before:
                continue
            images.load(path, uploads.MAX_UPLOAD_PIXELS)
            return None
        except FileNotFoundError:
            await asyncio.sleep(SETTLE_SECONDS)  # an editor may save by deleting and renaming
            error = f"the watched file {path} was deleted: save it again from your editor", 410
        except ImageError as problem:
            error = str(problem), 422
            await asyncio.sleep(SETTLE_SECONDS)
    return error


def watched_picture(watch: str, changed: set[str]) -> str | None:
    """Returns the picture to refit among changed paths: the watched file, or the folder's newest picture."""
    if not os.path.isdir(watch):
        return watch if any(os.path.abspath(p) == os.path.abspath(watch) for p in changed) else None
    pictures = [p for p in changed if os.path.splitext(p)[1].lower() in IMAGE_EXTENSIONS]
    existing = [p for p in pictures if os.path.exists(p)]
    return max(existing, key=os.path.getmtime) if existing else (pictures[0] if pictures else None)


def check_watch(watch: str | None) -> None:
    """Raises ImageError unless `watch` is None, an existing folder, or a picture file (existing or in a folder)."""
    if watch is None:
        return
    if os.path.isdir(watch):
        return
    if os.path.splitext(watch)[1].lower() not in IMAGE_EXTENSIONS:
        raise ImageError(f"watch {watch} is not a picture or a folder: give the file your editor saves, e.g. edit.png")
    if not os.path.isdir(os.path.dirname(os.path.abspath(watch))):
        raise ImageError(f"watch {watch}: its folder does not exist: give the file your editor saves")
