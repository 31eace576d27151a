"""The watched file or folder: which saved picture to refit, when it is complete enough to read, and the pages told
of each fit it starts (`Watcher`, the event stream of GET /api/watch).

A watched file that changes while its fit runs supersedes it; a file still being written
(unreadable, or growing) is retried, not reported. A watched file deleted before or while it is
fitted ends its job as an error answered 410.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time

from matfit import images
from matfit.app.serve import uploads
from matfit.app.serve.uploads import IMAGE_EXTENSIONS
from matfit.errors import ImageError

GONE = "gone"  # the `field` of a watched file deleted before or while it was fitted: answered 410
SETTLE_SECONDS = 0.15  # a watched file that does not decode yet must keep its size this long before it is retried
RETRY_SECONDS = 3.0  # an unreadable watched file (still being written) is retried this long before it is an error


def gone(path: str, when: str) -> ImageError:
    """Returns the error of a watched file deleted `when` ("while it was fitted"), answered 410."""
    return ImageError(f"the watched file {path} was deleted {when}: save it again from your editor", field=GONE)


async def settled(path: str) -> tuple[str, int] | None:
    """Returns None once `path` is a complete picture, or (the error, its HTTP status) after RETRY_SECONDS: 410 for a
    file that is gone, 422 for one that stays unreadable.

    A picture that decodes, and kept its size while it was decoded, is taken at once: a PNG, JPEG, TIFF or EXR cut
    short fails to decode, or (a TIFF cut in the tags after its pixels) decodes to the whole picture's pixels
    (tests/test_serve.py). Only one that does not decode (still being written) waits for its size to hold
    SETTLE_SECONDS before it is tried again.
    """
    deadline = time.monotonic() + RETRY_SECONDS
    error = None
    first = True
    while time.monotonic() < deadline:
        try:
            before = os.path.getsize(path)
            if not first:
                await asyncio.sleep(SETTLE_SECONDS)
                if os.path.getsize(path) != before:
                    continue
            first = False
            images.load(path, uploads.MAX_UPLOAD_PIXELS)
            if os.path.getsize(path) == before:
                return None
        except FileNotFoundError:
            first = False
            await asyncio.sleep(SETTLE_SECONDS)  # an editor may save by deleting and renaming
            error = f"the watched file {path} was deleted: save it again from your editor", 410
        except ImageError as problem:
            error = str(problem), 422
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


class Watcher:
    """The watched file or folder of a studio (None: no watch), followed while the server runs; each save queues a
    fit and tells every page listening on the event stream its job."""

    def __init__(self, studio, watch: str | None):
        self.studio = studio
        self.watch = watch
        self.queues: list[asyncio.Queue] = []  # one per page listening
        self.stopping = asyncio.Event()

    async def events(self, request):
        """Returns the server-sent events of GET /api/watch: a job id each time the watched file is saved."""
        from starlette.responses import StreamingResponse

        queue: asyncio.Queue = asyncio.Queue()
        self.queues.append(queue)
        return StreamingResponse(
            self.stream(request, queue), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
        )

    async def stream(self, request, queue: asyncio.Queue):
        """Yields one page's events until it disconnects: its messages, a keep-alive every half second."""
        try:
            yield "retry: 500\n\n"
            while not await request.is_disconnected():
                try:
                    message = await asyncio.wait_for(queue.get(), 0.5)
                except TimeoutError:
                    yield ": keep-alive\n\n"
                    continue
                yield f"data: {json.dumps(message)}\n\n"
        finally:
            self.queues.remove(queue)

    def announce(self, message: dict) -> None:
        """Sends a message to every page listening."""
        for queue in list(self.queues):
            queue.put_nowait(message)

    async def follow(self) -> None:
        """Queues a fit of each saved picture once it has settled (or a failed job), and announces its job."""
        from watchfiles import awatch

        watch = self.watch
        assert watch is not None  # followed only when there is a file to watch
        folder = watch if os.path.isdir(watch) else os.path.dirname(os.path.abspath(watch))
        async for changes in awatch(folder, debounce=50, step=20, stop_event=self.stopping):
            picture = watched_picture(watch, {path for _, path in changes})
            if picture is None:
                continue
            problem = await settled(picture)
            job = self.studio.watched_change(picture) if problem is None else self.studio.failed(*problem)
            self.announce({"job": job.id, "file": os.path.basename(picture)})

    @contextlib.asynccontextmanager
    async def lifespan(self, app):
        """Follows the watched file (if any) while the server runs."""
        task = asyncio.create_task(self.follow()) if self.watch is not None else None
        try:
            yield
        finally:
            self.stopping.set()
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
