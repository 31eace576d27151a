"""The page's HTTP routes: a small JSON API (Starlette, served by uvicorn) over a `Studio`.

The page (`matfit/static/`, plain HTML/JS, nothing fetched from the internet) talks to:

    GET  /api/parameters          the 19 parameters (`params.table`) and the presets
    POST /api/fit                 multipart: image [, mask] [, init params.json]  -> {"job": id}
    GET  /api/jobs/{id}           state, stage, progress; figures, pictures and parameters when done
    POST /api/jobs/{id}/cancel    a queued job never runs; a render stops after its current pass
    GET  /api/jobs/{id}/files/{name}  params.json, material.xml, material.py, report.png of a fit
    POST /api/preview             {"values": [19]}  -> PNG of the decoder's image
    POST /api/render              {"values", "size", "spp"}  -> {"job": id}, a Mitsuba render in passes
    POST /api/params              multipart: a params.json  -> its 19 values (checked as `matfit render` does)
    GET  /api/watch               server-sent events: a job id each time the watched file is saved
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os

from matfit import documents, params, shipped
from matfit.app.serve import uploads
from matfit.app.serve.jobs import FILES, fit_files
from matfit.app.serve.studio import Studio
from matfit.app.serve.uploads import MAX_FIT_BYTES, MAX_JSON_BYTES, TOO_LARGE, VALUES_FIX, check_values
from matfit.app.serve.watch import settled, watched_picture
from matfit.errors import MatfitError, ParameterError
from matfit.render import presets


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
        data = await upload.read(uploads.MAX_UPLOAD_BYTES + 1)
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
