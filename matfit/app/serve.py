"""The edit-and-see loop: a local web page that fits what the artist saves, with the CLI's own fitting and exports.

One `Studio` owns the loaded model and a Mitsuba renderer; one worker thread runs every fit and
every Mitsuba render in turn (JAX and Dr.Jit stay on one thread, fits queue on the one model), so
every fit after the first is a warm fit. Each request gets its own job id and its own result. The
neural preview (the decoder alone, far cheaper than a fit) runs beside the queue, on the request's thread.

The page (`matfit/static/`, plain HTML/JS, nothing fetched from the internet) talks to a small
JSON API (Starlette, served by uvicorn):

    GET  /api/parameters          the 19 parameters (`params.table`) and the presets
    POST /api/fit                 multipart: image [, mask] [, init params.json]  -> {"job": id}
    GET  /api/jobs/{id}           state, stage, progress; figures, pictures and parameters when done
    POST /api/jobs/{id}/cancel    a queued job never runs; a render stops after its current pass
    GET  /api/jobs/{id}/files/{name}  params.json, material.xml, material.py, report.png of a fit
    POST /api/preview             {"values": [19]}  -> PNG of the decoder's image
    POST /api/render              {"values", "size", "spp"}  -> {"job": id}, a Mitsuba render in passes
    POST /api/params              multipart: a params.json  -> its 19 values (checked as `matfit render` does)
    GET  /api/watch               server-sent events: a job id each time the watched file is saved

Uploads are written under a private temporary folder (never under a name the browser sent) and
read by the CLI's own reader (`fitfile.read_target`); a watched file that changes while its fit
runs supersedes it; a file still being written (unreadable, or growing) is retried, not reported.
A watched file deleted before or while it is fitted ends its job as an error answered 410.

Request bodies are capped and counted as they arrive (nothing beyond the cap is read): MAX_JSON_BYTES
for the JSON requests and a params.json upload, MAX_FIT_BYTES for a fit's form (a picture and a mask
of at most MAX_UPLOAD_BYTES each); a larger body is answered 413 with a one-line message.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import itertools
import json
import os
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from matfit import documents, files, images, interrupt, params, shipped
from matfit.errors import ImageError, MatfitError, OutputError, ParameterError
from matfit.fit import fitfile, search, verify
from matfit.model import models
from matfit.render import export, presets

MAX_UPLOAD_BYTES = 50 * 1024 * 1024  # an upload larger than this is refused before it is read
MAX_JSON_BYTES = 1024 * 1024  # the body of a JSON request (19 values: a few hundred bytes) or of a params.json upload
MAX_FIT_BYTES = 2 * MAX_UPLOAD_BYTES + MAX_JSON_BYTES  # a fit's form: a picture, a mask, the initial values
MAX_UPLOAD_PIXELS = 16_000_000  # and one with more pixels before they are decoded
MAX_RENDER_SIZE = 1024
MAX_RENDER_SPP = 4096
TOO_LARGE = "upload size"  # the `field` of an upload refused for its size: answered 413, other bad uploads 400
GONE = "gone"  # the `field` of a watched file deleted before or while it was fitted: answered 410
VALUES_FIX = 'send {"values": [19 numbers]}, one per parameter of `matfit params`'
RENDER_PASSES = 8  # a Mitsuba render from the page: spp split into passes, for progress and cancellation
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".hdr")
SETTLE_SECONDS = 0.15  # a watched file must keep its size this long before it is read
RETRY_SECONDS = 3.0  # an unreadable watched file (still being written) is retried this long before it is an error
FILES = {
    "params.json": "application/json",
    "material.xml": "application/xml",
    "material.py": "text/x-python",
    "report.png": "image/png",
}


@dataclass
class Job:
    """One fit or render asked for by one page: its progress, and its result or error."""

    id: str
    kind: str  # "fit" or "render"
    state: str = "queued"  # queued, running, done, error, cancelled, superseded
    stage: str = "queued"
    progress: float = 0.0
    error: str | None = None
    status: int = 200  # the HTTP status of the job's answer: 4xx for the user's errors
    result: dict | None = None
    outcome: fitfile.Outcome | None = None
    cancelled: threading.Event = field(default_factory=threading.Event)
    created: float = field(default_factory=time.perf_counter)
    finished: float | None = None

    def answer(self) -> dict:
        """Returns what the page is told about the job (strict JSON: a figure that is not finite is null)."""
        answer = {"job": self.id, "kind": self.kind, "state": self.state, "stage": self.stage}
        answer["progress"] = round(self.progress, 3)
        if self.error is not None:
            answer["error"] = self.error
        if self.result is not None:
            answer["result"] = self.result
        return documents.finite(answer)


def png_data_url(srgb: np.ndarray) -> str:
    """Returns an sRGB image in [0, 1] as a PNG data URL for the page."""
    return "data:image/png;base64," + base64.b64encode(png_bytes(srgb)).decode()


def png_bytes(srgb: np.ndarray) -> bytes:
    """Returns an sRGB image in [0, 1] as PNG bytes (8-bit), encoded by the CLI's own writer."""
    return images.encode(images.srgb_decode(np.clip(np.asarray(srgb, np.float32), 0.0, 1.0)), ".png")


def fit_result(outcome: fitfile.Outcome) -> dict:
    """Returns the page's view of a fit: figures, the five pictures of the report, the 19 parameters."""
    from matfit.fit import report

    result, document = outcome.result, outcome.document
    return {
        "neural_rmse": round(outcome.neural_rmse, 3),
        "mitsuba_rmse": document.get("mitsuba_rmse"),
        "start": result.chosen,
        "start_rmse": round(result.start_rmse, 3),
        "kept": outcome.verified.chosen if outcome.verified is not None else None,
        "evaluations": result.evaluations,
        "seconds": document["wall_time_s"],
        "values": [round(float(v), 6) for v in outcome.values],
        "pictures": {
            "target": png_data_url(outcome.target),
            "start": png_data_url(result.start_image),
            "neural": png_data_url(outcome.image),
            "mitsuba": png_data_url(outcome.rendered),
            "difference": png_data_url(report.difference(outcome.rendered, outcome.target)),
        },
        "notices": outcome.notices,
        "mask": document.get("mask"),
    }


def fit_files(outcome: fitfile.Outcome) -> dict[str, bytes]:
    """Returns the files the CLI writes for the same fit (`fit -o params.json --report --mitsuba-xml --blender`)."""
    return {
        "params.json": fitfile.params_text(outcome).encode(),
        "material.xml": export.mitsuba_xml(outcome.values).encode(),
        "material.py": export.blender_script(outcome.values).encode(),
        "report.png": png_bytes(fitfile.report_picture(outcome)),
    }


def check_values(values: object) -> np.ndarray:
    """Returns 19 physical parameter values from the page, checked against their ranges as params.json is."""
    if not isinstance(values, list) or len(values) != params.COUNT:
        raise ParameterError(f"values must be a list of {params.COUNT} numbers, one per parameter of `matfit params`")
    return params.from_mapping(dict(zip(params.NAMES, values, strict=True)))


class Studio:
    """The loaded model, its renderer, the one worker that runs fits and renders, and every job."""

    def __init__(
        self, model: models.Model, model_label: str, settings: search.Settings | None = None, variant: str | None = None
    ):
        self.model = model
        self.variant = variant  # the Mitsuba variant (None: render.choose_variant's)
        self.model_label = model_label
        self.settings = settings or search.Settings()
        self.folder = tempfile.mkdtemp(prefix="matfit-serve-")
        interrupt.register(self.folder)  # a Ctrl-C that skips `close` still removes it
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="matfit-fit")
        self.jobs: dict[str, Job] = {}
        self.counter = itertools.count(1)
        self.lock = threading.Lock()
        self.renderers: dict[int, object] = {}
        self.watch_jobs: list[str] = []  # job ids of the watched file's fits, newest last
        self.watch_error: str | None = None

    def close(self) -> None:
        """Stops taking jobs and removes the temporary folder."""
        self.worker.shutdown(wait=False, cancel_futures=True)
        with contextlib.suppress(OSError):
            for name in os.listdir(self.folder):
                os.unlink(os.path.join(self.folder, name))
                interrupt.unregister(os.path.join(self.folder, name))
            os.rmdir(self.folder)
        interrupt.unregister(self.folder)

    def renderer(self, size: int):
        """Returns the Mitsuba renderer of a size, loaded once (on the worker thread)."""
        if size not in self.renderers:
            from matfit.render.engine import Renderer

            # The model's resolution verifies fits: one thread, so the page's answer is the command line's, bit for bit;
            # larger pictures render on every core.
            threads = 1 if size == self.model.resolution else (os.cpu_count() or 1)
            self.renderers[size] = Renderer(size, verify.SPP, self.variant, threads=threads)
        return self.renderers[size]

    def new_job(self, kind: str) -> Job:
        """Returns a new job, registered."""
        with self.lock:
            job = Job(f"{kind}-{next(self.counter)}", kind)
            self.jobs[job.id] = job
        return job

    def warm_up(self) -> None:
        """Compiles the fit and loads the renderer before the first page asks (a fit of a grey picture)."""
        grey = np.full((self.model.resolution, self.model.resolution, 3), 0.5, np.float32)
        search.fit(self.model, grey, self.settings)
        self.renderer(self.model.resolution)
        self.preview(params.DEFAULTS)

    def upload_path(self, data: bytes, filename: str | None, kind: str) -> str:
        """Returns the path of a private temporary copy of an uploaded picture; only the name's extension is kept."""
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
        handle, path = tempfile.mkstemp(suffix=extension, dir=self.folder)
        interrupt.register(path)  # removed even when Ctrl-C ends the process without its teardown
        with os.fdopen(handle, "wb") as file:
            file.write(data)
        self.check_picture(path, kind)
        return path

    @staticmethod
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

    def submit_fit(
        self,
        target: str,
        label: str,
        mask: str | None = None,
        init: np.ndarray | None = None,
        *,
        watched: bool = False,
    ) -> Job:
        """Queues a fit of the picture at `target` (a private copy, or the watched file); returns its job."""
        job = self.new_job("fit")
        self.worker.submit(self._fit, job, target, label, mask, init, watched)
        return job

    def _fit(self, job: Job, target: str, label: str, mask: str | None, init: np.ndarray | None, watched: bool) -> None:
        if job.cancelled.is_set():
            job.state = job.stage = "superseded" if job.state == "superseded" else "cancelled"
            return
        job.state, job.stage, job.progress = "running", "fitting", 0.1
        started = time.perf_counter()
        picture = None
        try:
            picture = self.snapshot(target) if watched else target  # the editor may save or delete it meanwhile
            outcome, _ = fitfile.fit_file(
                picture,
                self.model,
                self.settings,
                mask,
                init_values=init,
                renderer=self.renderer(self.model.resolution),
                source="uploaded params.json" if init is not None else None,
            )
            if watched and not os.path.exists(target):
                raise gone(target, "while it was fitted")
            outcome.document.update(target=label, target_sha256=files.sha256(picture), model=self.model_label)
            if mask is not None:
                outcome.document["mask"] = "painted in the page"
            outcome.document["wall_time_s"] = round(time.perf_counter() - started, 3)
            job.outcome, job.result = outcome, fit_result(outcome)
            job.state, job.stage, job.progress = "done", "done", 1.0
        except MatfitError as error:
            status = 410 if error.field == GONE else 422
            message = str(error).replace(picture, target) if watched and picture else str(error)  # the file it names
            job.state, job.stage, job.error, job.status = "error", "error", message, status
        except Exception as error:  # a failure of matfit's own: the job ends (never "running" for ever), said in a line
            message = str(error).splitlines()[0] if str(error) else type(error).__name__
            job.state, job.stage, job.error, job.status = "error", "error", f"the fit failed: {message}", 500
        finally:
            if watched and picture is not None:
                with contextlib.suppress(OSError):
                    os.unlink(picture)
                interrupt.unregister(picture)
            job.finished = time.perf_counter()
            if job.cancelled.is_set() and job.state == "done":
                job.state = job.stage = "superseded"

    def snapshot(self, path: str) -> str:
        """Returns a private copy of the watched file as it is now (fitted and hashed as one picture); the error GONE
        if it was deleted."""
        extension = os.path.splitext(path)[1].lower()
        handle, copy = tempfile.mkstemp(suffix=extension, dir=self.folder)
        interrupt.register(copy)
        try:
            with open(path, "rb") as source, os.fdopen(handle, "wb") as file:
                while block := source.read(1 << 20):
                    file.write(block)
        except FileNotFoundError:
            os.unlink(copy)
            interrupt.unregister(copy)
            raise gone(path, "before it was fitted") from None
        return copy

    def failed(self, message: str, status: int) -> Job:
        """Returns a new job that failed before it could run (a watched file deleted or unreadable)."""
        job = self.new_job("fit")
        job.state, job.stage, job.error, job.status = "error", "error", message, status
        return job

    def submit_render(self, values: np.ndarray, size: int, spp: int) -> Job:
        """Queues a Mitsuba render of physical values at size x size, spp samples in RENDER_PASSES passes."""
        if not 8 <= size <= MAX_RENDER_SIZE:
            raise ParameterError(f"render size {size} is out of range: use 8 to {MAX_RENDER_SIZE}")
        if not 1 <= spp <= MAX_RENDER_SPP:
            raise ParameterError(f"render spp {spp} is out of range: use 1 to {MAX_RENDER_SPP}")
        job = self.new_job("render")
        self.worker.submit(self._render, job, values, size, spp)
        return job

    def _render(self, job: Job, values: np.ndarray, size: int, spp: int) -> None:
        if job.cancelled.is_set():
            job.state = job.stage = "cancelled"
            return
        job.state, job.stage = "running", "rendering"
        passes = min(RENDER_PASSES, spp)
        total = np.zeros((size, size, 3), np.float64)
        done_samples = 0
        started = time.perf_counter()
        renderer = self.renderer(size)
        for k in range(passes):
            if job.cancelled.is_set():
                job.state = job.stage = "cancelled"
                job.finished = time.perf_counter()
                return
            samples = spp // passes + (1 if k < spp % passes else 0)
            total += samples * renderer.render(values, seed=k, spp=samples)
            done_samples += samples
            job.progress = done_samples / spp
        image = images.srgb_encode((total / spp).astype(np.float32))
        job.result = {"picture": png_data_url(image), "size": size, "spp": spp}
        job.result["seconds"] = round(time.perf_counter() - started, 3)
        job.state, job.stage, job.progress, job.finished = "done", "done", 1.0, time.perf_counter()

    def preview(self, values: np.ndarray) -> bytes:
        """Returns the decoder's picture of physical values, as PNG bytes."""
        return png_bytes(self.model.decode(params.to_unit(values))[0])

    def cancel(self, job_id: str) -> Job:
        """Marks a job cancelled: a queued one never runs, a render stops after its current pass."""
        job = self.job(job_id)
        job.cancelled.set()
        return job

    def job(self, job_id: str) -> Job:
        """Returns a job by id; KeyError if there is none."""
        return self.jobs[job_id]

    def watched_change(self, path: str) -> Job:
        """Queues a fit of the watched file and supersedes the previous one; returns the new job."""
        for old in self.watch_jobs:
            previous = self.jobs[old]
            if previous.state in ("queued", "running"):
                previous.state = "superseded" if previous.state == "queued" else previous.state
                previous.cancelled.set()
        job = self.submit_fit(path, os.path.basename(path), watched=True)
        self.watch_jobs.append(job.id)
        return job


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
            images.load(path, MAX_UPLOAD_PIXELS)
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


def create_app(studio: Studio, watch: str | None = None):
    """Returns the Starlette application of a studio (and of the watched file or folder, if any)."""
    from starlette.applications import Starlette
    from starlette.exceptions import HTTPException
    from starlette.requests import Request
    from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
    from starlette.routing import Route

    events: list[asyncio.Queue] = []

    def error(message: str, status: int = 400) -> JSONResponse:
        return JSONResponse({"error": message}, status_code=status)

    async def page(request: Request) -> Response:
        name = request.path_params.get("name", "index.html")
        if name not in ("index.html", "app.js", "style.css"):
            return error(f"no page {name!r}: open /", 404)
        return FileResponse(str(shipped.STATIC / name))

    async def parameters(request: Request) -> Response:
        return JSONResponse(
            {
                "parameters": [
                    {
                        "name": p.name,
                        "low": p.low,
                        "high": p.high,
                        "default": p.default,
                        "unit": p.unit,
                        "meaning": p.meaning,
                    }
                    for p in params.PARAMETERS
                ],
                "presets": {name: presets.preset(name).tolist() for name in presets.PRESETS},
                "resolution": studio.model.resolution,
                "watch": watch,
            }
        )

    def capped(request: Request, cap: int, fix: str) -> Request:
        """Returns the request with its body counted as it arrives: an error (answered 413) once it passes `cap`
        bytes, or at once when its Content-Length says it will. Nothing beyond the cap is read."""

        def too_large() -> MatfitError:
            return MatfitError(
                f"the request body is more than {cap / 2**20:g} MB, the most it may be: {fix}", TOO_LARGE
            )

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

    async def read_upload(form, key: str, kind: str) -> str | None:
        upload = form.get(key)
        if upload is None or isinstance(upload, str):
            return None
        data = await upload.read(MAX_UPLOAD_BYTES + 1)
        return await asyncio.to_thread(studio.upload_path, data, upload.filename, kind)  # it decodes the picture

    async def start_fit(request: Request) -> Response:
        try:
            request = capped(request, MAX_FIT_BYTES, "upload a smaller picture")
            async with request.form(max_files=3, max_part_size=MAX_JSON_BYTES) as form:
                target = await read_upload(form, "image", "picture")
                if target is None:
                    return error("no picture in the upload: choose or drop an image file")
                mask = await read_upload(form, "mask", "mask")
                init = form.get("init")
                init_values = None
                if isinstance(init, str) and init:
                    init_values = check_values(documents.parse(init, "the init field", VALUES_FIX, ParameterError))
                label = getattr(form.get("image"), "filename", None) or "upload"
        except MatfitError as problem:
            return refused(problem)
        except (ValueError, HTTPException) as problem:  # a malformed form: Starlette raises HTTPException
            return error(f"the upload could not be read ({getattr(problem, 'detail', problem)}): choose the file again")
        job = studio.submit_fit(target, os.path.basename(label), mask, init_values)
        return JSONResponse({"job": job.id}, status_code=202)

    async def job_state(request: Request) -> Response:
        try:
            job = studio.job(request.path_params["job"])
        except KeyError:
            return error(f"no job {request.path_params['job']!r}: fit a picture first", 404)
        return JSONResponse(job.answer(), status_code=job.status)

    async def cancel(request: Request) -> Response:
        try:
            return JSONResponse(studio.cancel(request.path_params["job"]).answer())
        except KeyError:
            return error(f"no job {request.path_params['job']!r}", 404)

    async def download(request: Request) -> Response:
        name = request.path_params["name"]
        job = studio.jobs.get(request.path_params["job"])
        if job is None or job.outcome is None:
            return error("that fit has no result (yet): wait for it to finish", 404)
        if name not in FILES:
            return error(f"no file {name!r}: ask for one of {', '.join(FILES)}", 404)
        content = await asyncio.to_thread(lambda: fit_files(job.outcome)[name])
        disposition = {"Content-Disposition": f'attachment; filename="{name}"'}
        return Response(content, media_type=FILES[name], headers=disposition)

    async def json_body(request: Request) -> dict:
        """Returns the request's JSON object, read up to MAX_JSON_BYTES; MatfitError (400, or 413 when too large)."""
        body = bytearray()
        async for chunk in capped(request, MAX_JSON_BYTES, VALUES_FIX).stream():
            body += chunk
        document = documents.parse(bytes(body), "the request", VALUES_FIX, ParameterError)
        if not isinstance(document, dict):
            raise ParameterError(f'the request must be a JSON object with "values": {VALUES_FIX}')
        return document

    def refused(problem: MatfitError) -> JSONResponse:
        return error(str(problem), 413 if problem.field == TOO_LARGE else 400)

    async def preview(request: Request) -> Response:
        try:
            values = check_values((await json_body(request)).get("values"))
        except MatfitError as problem:
            return refused(problem)
        return Response(await asyncio.to_thread(studio.preview, values), media_type="image/png")

    async def render(request: Request) -> Response:
        try:
            body = await json_body(request)
            values = check_values(body.get("values"))
            size, spp = body.get("size", 256), body.get("spp", 64)
            if not all(isinstance(v, int) and not isinstance(v, bool) for v in (size, spp)):
                raise ParameterError(f"size {size!r} and spp {spp!r} must be whole numbers")
            job = studio.submit_render(values, size, spp)
        except MatfitError as problem:
            return refused(problem)
        return JSONResponse({"job": job.id}, status_code=202)

    async def parse_params(request: Request) -> Response:
        try:
            request = capped(request, MAX_JSON_BYTES, "choose a params.json that matfit wrote")
            async with request.form(max_files=1, max_part_size=MAX_JSON_BYTES) as form:
                upload = form.get("params")
                if upload is None or isinstance(upload, str):
                    return error("no params.json in the upload: choose one")
                text = (await upload.read(MAX_JSON_BYTES)).decode("utf-8", errors="strict")
            values = params.parse_params_json(text, upload.filename or "params.json")
        except UnicodeDecodeError:
            return error("the params.json is not UTF-8 text: choose a params.json that matfit wrote")
        except HTTPException as problem:
            return error(f"the upload could not be read ({problem.detail}): choose the file again")
        except MatfitError as problem:
            return refused(problem)
        return JSONResponse({"values": values.tolist()})

    async def watch_events(request: Request) -> Response:
        queue: asyncio.Queue = asyncio.Queue()
        events.append(queue)

        async def stream():
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
                events.remove(queue)

        return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})

    def announce(message: dict) -> None:
        for queue in list(events):
            queue.put_nowait(message)

    async def follow() -> None:
        from watchfiles import awatch

        folder = watch if os.path.isdir(watch) else os.path.dirname(os.path.abspath(watch))
        async for changes in awatch(folder, debounce=50, step=20, stop_event=stopping):
            picture = watched_picture(watch, {path for _, path in changes})
            if picture is None:
                continue
            problem = await settled(picture)
            job = studio.watched_change(picture) if problem is None else studio.failed(*problem)
            announce({"job": job.id, "file": os.path.basename(picture)})

    stopping = asyncio.Event()

    @contextlib.asynccontextmanager
    async def lifespan(app):
        task = asyncio.create_task(follow()) if watch is not None else None
        try:
            yield
        finally:
            stopping.set()
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task

    routes = [
        Route("/", page),
        Route("/static/{name}", page),
        Route("/api/parameters", parameters),
        Route("/api/fit", start_fit, methods=["POST"]),
        Route("/api/jobs/{job}", job_state),
        Route("/api/jobs/{job}/cancel", cancel, methods=["POST"]),
        Route("/api/jobs/{job}/files/{name}", download),
        Route("/api/preview", preview, methods=["POST"]),
        Route("/api/render", render, methods=["POST"]),
        Route("/api/params", parse_params, methods=["POST"]),
        Route("/api/watch", watch_events),
    ]
    return Starlette(routes=routes, lifespan=lifespan)


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


def check_listen(host: str, port: int) -> None:
    """Raises OutputError unless this process can listen on host:port (checked before the model is loaded)."""
    import socket

    try:
        with socket.create_server((host, port)):
            pass
    except OSError as error:
        raise OutputError(
            f"cannot listen on {host}:{port} ({os.strerror(error.errno) if error.errno else error}): "
            "choose another --port or --host",
            field="port",
        ) from None


@contextlib.contextmanager
def running(studio: Studio, watch: str | None = None, host: str = "127.0.0.1", port: int = 0):
    """Runs the page's server in a thread for the block (tests, benchmarks); yields its URL."""
    import uvicorn

    config = uvicorn.Config(create_app(studio, watch), host=host, port=port, log_level="warning")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name="matfit-serve", daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.01)
    if not server.started:
        raise OutputError(f"cannot listen on {host}:{port}: choose another port", field="port")
    bound = server.servers[0].sockets[0].getsockname()[1]
    try:
        yield f"http://{host}:{bound}/"
    finally:
        server.should_exit = True
        thread.join(10)


def serve(
    model_path: str,
    host: str = "127.0.0.1",
    port: int = 8765,
    watch: str | None = None,
    ready=None,
    variant: str | None = None,
) -> None:
    """Loads the model, compiles the fit, and serves the page until Ctrl-C; `ready(url)` is called once it listens.

    `variant`: the Mitsuba variant of its renders (None: `engine.choose_variant`'s)."""
    import uvicorn

    from matfit.render.engine import check_request

    check_watch(watch)
    check_listen(host, port)
    check_request(variant)
    model = fitfile.load_model(model_path)
    studio = Studio(model, fitfile.display_path(model_path), variant=variant)
    studio.worker.submit(studio.warm_up).result()
    app = create_app(studio, watch)
    config = uvicorn.Config(app, host=host, port=port, log_level="warning", timeout_graceful_shutdown=1)
    server = uvicorn.Server(config)
    if ready is not None:
        original = server.startup

        async def startup(sockets=None):
            await original(sockets)
            if server.started:
                ready(f"http://{host}:{port}/")

        server.startup = startup
    try:
        server.run()
    finally:
        studio.close()
    if not server.started:
        raise OutputError(f"cannot listen on {host}:{port} (in use?): choose another --port", field="port")
