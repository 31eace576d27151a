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
import os

from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response

from matfit import params, shipped
from matfit.app.serve import uploads
from matfit.app.serve.jobs import FILES, fit_files
from matfit.app.serve.studio import Studio
from matfit.app.serve.uploads import MAX_FIT_BYTES, MAX_JSON_BYTES, TOO_LARGE, capped, check_values
from matfit.app.serve.watch import Watcher
from matfit.errors import MatfitError, ParameterError
from matfit.rendering import presets

API = ("/api/parameters", "/api/fit", "/api/jobs/{id}", "/api/preview", "/api/render", "/api/params", "/api/watch")
PAGE_FILES = ("index.html", "app.js", "style.css")  # the files of matfit/static/ the page is made of


def create_app(studio: Studio, watch: str | None = None):
    """Returns the Starlette application of a studio (and of the watched file or folder, if any)."""
    from starlette.applications import Starlette
    from starlette.routing import Route

    api = Api(studio, watch)
    watcher = Watcher(studio, watch)
    routes = [
        Route("/", api.page),
        Route("/static/{name}", api.page),
        Route("/api/parameters", api.parameters),
        Route("/api/fit", api.start_fit, methods=["POST"]),
        Route("/api/jobs/{job}", api.job_state),
        Route("/api/jobs/{job}/cancel", api.cancel, methods=["POST"]),
        Route("/api/jobs/{job}/files/{name}", api.download),
        Route("/api/preview", api.preview, methods=["POST"]),
        Route("/api/render", api.render, methods=["POST"]),
        Route("/api/params", api.parse_params, methods=["POST"]),
        Route("/api/watch", watcher.events),
    ]
    handlers = {HTTPException: http_error, Exception: internal_error}
    return Starlette(routes=routes, lifespan=watcher.lifespan, exception_handlers=handlers)  # type: ignore[arg-type]


async def http_error(request: Request, problem: HTTPException) -> Response:
    """Returns Starlette's own refusals (no such route, a method the route does not take) as every other error of the
    API is: {"error": the one-line message}, naming the request and the fix."""
    where = f"{request.method} {request.url.path}"
    if problem.status_code == 404:
        message = f"no {request.url.path} here: open / for the page (its API: {', '.join(API)})"
    elif problem.status_code == 405:
        # Starlette names a route's methods in a set's order, HEAD beside GET: sorted, HEAD left implied by GET
        named = {method.strip() for method in (problem.headers or {}).get("Allow", "").split(",") if method.strip()}
        allowed = ", ".join(sorted(named - {"HEAD"} if "GET" in named else named)) or "another method"
        message = f"{where} is not served: {request.url.path} takes {allowed}"
    else:
        message = f"{where}: {problem.detail}"
    return JSONResponse({"error": message}, status_code=problem.status_code, headers=problem.headers)


async def internal_error(request: Request, problem: Exception) -> Response:
    """Returns a failure of matfit's own while answering a request as a 500 with {"error": its first line}."""
    first = str(problem).splitlines()[0] if str(problem) else type(problem).__name__
    return error(f"{request.method} {request.url.path} failed: {first}", 500)


def error(message: str, status: int = 400) -> JSONResponse:
    """Returns the page's answer to a request it cannot serve: {"error": the one-line message}."""
    return JSONResponse({"error": message}, status_code=status)


def refused(problem: MatfitError) -> JSONResponse:
    """Returns the answer to a request refused for what it sent: 413 when too large, else 400."""
    return error(str(problem), 413 if problem.field == TOO_LARGE else 400)


class Api:
    """The handlers of the page's requests, over one studio (and the watched file or folder, if any)."""

    def __init__(self, studio: Studio, watch: str | None):
        self.studio = studio
        self.watch = watch

    async def page(self, request: Request) -> Response:
        """GET / and /static/{name}: the page's files."""
        name = request.path_params.get("name", "index.html")
        if name not in PAGE_FILES:
            return error(f"no page {name!r}: open /", 404)
        return FileResponse(str(shipped.STATIC / name))

    async def parameters(self, request: Request) -> Response:
        """GET /api/parameters: the 19 parameters, the presets, the model's resolution and the watched path."""
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
                "resolution": self.studio.model.resolution,
                "watch": self.watch,
            }
        )

    async def start_fit(self, request: Request) -> Response:
        """POST /api/fit: queues a fit of the uploaded picture (and mask, and initial values); 202 and its job.

        Everything is checked here, off the event loop (the mask against the picture, the initial values): a refused
        upload is a 4xx naming what was sent, and leaves no copy."""
        target = mask = None
        try:
            request = capped(request, MAX_FIT_BYTES, "upload a smaller picture")
            async with request.form(max_files=3, max_part_size=MAX_JSON_BYTES) as form:
                target = await uploads.read_upload(form, "image", "picture", self.studio.folder)
                if target is None:
                    return error("no picture in the upload: choose or drop an image file")
                mask = await uploads.read_upload(form, "mask", "mask", self.studio.folder)
                if mask is not None:
                    name = getattr(form.get("mask"), "filename", None) or "mask"
                    await asyncio.to_thread(uploads.check_mask, mask, target, self.studio.model.resolution, name)
                init = form.get("init")
                init_values = None
                if isinstance(init, str) and init:
                    init_values = await asyncio.to_thread(uploads.init_values, init)
                label = getattr(form.get("image"), "filename", None) or "upload"
        except MatfitError as problem:
            answer = refused(problem)
        except (ValueError, HTTPException) as problem:  # a malformed form: Starlette raises HTTPException
            detail = getattr(problem, "detail", problem)
            answer = error(f"the upload could not be read ({detail}): choose the file again")
        except BaseException:  # the page went away mid-upload
            uploads.discard(target, mask)
            raise
        else:
            job = self.studio.submit_fit(target, os.path.basename(label), mask, init_values)
            return JSONResponse({"job": job.id}, status_code=202)
        uploads.discard(target, mask)
        return answer

    async def job_state(self, request: Request) -> Response:
        """GET /api/jobs/{job}: the job's answer, with its HTTP status."""
        try:
            job = self.studio.job(request.path_params["job"])
        except KeyError:
            return error(f"no job {request.path_params['job']!r}: fit a picture first", 404)
        return JSONResponse(job.answer(), status_code=job.status)

    async def cancel(self, request: Request) -> Response:
        """POST /api/jobs/{job}/cancel: marks the job cancelled; its answer."""
        try:
            return JSONResponse(self.studio.cancel(request.path_params["job"]).answer())
        except KeyError:
            return error(f"no job {request.path_params['job']!r}", 404)

    async def download(self, request: Request) -> Response:
        """GET /api/jobs/{job}/files/{name}: a file the CLI writes for the same fit, as an attachment."""
        name = request.path_params["name"]
        job = self.studio.jobs.get(request.path_params["job"])
        if job is None or job.outcome is None:
            return error("that fit has no result (yet): wait for it to finish", 404)
        if name not in FILES:
            return error(f"no file {name!r}: ask for one of {', '.join(FILES)}", 404)
        content = (await asyncio.to_thread(fit_files, job.outcome))[name]
        disposition = {"Content-Disposition": f'attachment; filename="{name}"'}
        return Response(content, media_type=FILES[name], headers=disposition)

    async def preview(self, request: Request) -> Response:
        """POST /api/preview: the decoder's picture of the values, as PNG."""
        try:
            values = check_values((await uploads.json_body(request)).get("values"))
        except MatfitError as problem:
            return refused(problem)
        return Response(await asyncio.to_thread(self.studio.preview, values), media_type="image/png")

    async def render(self, request: Request) -> Response:
        """POST /api/render: queues a Mitsuba render of the values at a size and spp; 202 and its job."""
        try:
            body = await uploads.json_body(request)
            values = check_values(body.get("values"))
            size, spp = body.get("size", 256), body.get("spp", 64)
            if not all(isinstance(v, int) and not isinstance(v, bool) for v in (size, spp)):
                raise ParameterError(f"size {size!r} and spp {spp!r} must be whole numbers")
            job = self.studio.submit_render(values, size, spp)
        except MatfitError as problem:
            return refused(problem)
        return JSONResponse({"job": job.id}, status_code=202)

    async def parse_params(self, request: Request) -> Response:
        """POST /api/params: the 19 values of an uploaded params.json, checked as `matfit render` checks them."""
        try:
            request = capped(request, MAX_JSON_BYTES, "choose a params.json that matfit wrote")
            async with request.form(max_files=1, max_part_size=MAX_JSON_BYTES) as form:
                upload = form.get("params")
                if upload is None or isinstance(upload, str):
                    return error("no params.json in the upload: choose one")
                data = await upload.read(MAX_JSON_BYTES + 1)
            # The CLI's reader (a byte order mark accepted, the size capped), off the event loop: a large document
            # must not hold every other request.
            values = await asyncio.to_thread(params.parse_params_json, data, upload.filename or "params.json")
        except HTTPException as problem:
            return error(f"the upload could not be read ({problem.detail}): choose the file again")
        except MatfitError as problem:
            return refused(problem)
        return JSONResponse({"values": values.tolist()})
