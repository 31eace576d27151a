"""The studio: the loaded model, its renderers, the one worker that runs every fit and render, and every job.

One `Studio` owns the loaded model in a `matfit.Fitter` (the public API, with its render processes) and a
Mitsuba renderer for other sizes; one worker thread runs every fit and every Mitsuba render in turn (JAX and
Dr.Jit stay on one thread, fits queue on the one model), so every fit after the first is a warm fit. Each
request gets its own job id and its own result. The neural preview (the decoder alone, far cheaper than a fit)
runs beside the queue, on the request's thread.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import os
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from matfit import files, images, interrupt, params
from matfit.api.fitter import Fitter
from matfit.api.material import Material
from matfit.api.results import Fit
from matfit.app.serve import uploads
from matfit.app.serve.jobs import Job, fit_result, png_bytes, png_data_url
from matfit.app.serve.watch import GONE, gone
from matfit.errors import MatfitError, ParameterError
from matfit.fitting import search, verify
from matfit.model import models
from matfit.rendering.engine import Renderer

MAX_RENDER_SIZE = 1024
MAX_RENDER_SPP = 4096
RENDER_PASSES = 8  # a Mitsuba render from the page: spp split into passes, for progress and cancellation


class SupersededError(Exception):
    """A fit's job was cancelled or superseded while it ran: raised at its next stage's answer, ending the fit."""


class Studio:
    """The loaded model, its renderer, the one worker that runs fits and renders, and every job."""

    def __init__(
        self, model: models.Model, model_label: str, settings: search.Settings | None = None, variant: str | None = None
    ):
        self.model = model
        self.variant = variant  # the Mitsuba variant (None: render.choose_variant's)
        self.model_label = model_label
        self.settings = settings or search.Settings()
        self.folder = uploads.private_folder()  # the uploads, each removed when its job ends
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="matfit-fit")
        self.jobs: dict[str, Job] = {}
        self.counter = itertools.count(1)
        self.lock = threading.Lock()
        # The fits, and renders at the model's resolution, through the public API: its render processes, one a core.
        self.fitter = Fitter(model, variant=variant)
        self.renderers: dict[int, Renderer] = {}  # larger (or smaller) pictures: one render on every core
        self.watch_jobs: list[str] = []  # job ids of the watched file's fits, newest last
        self.watch_error: str | None = None

    def close(self) -> None:
        """Stops taking jobs and removes the temporary folder."""
        self.worker.shutdown(wait=False, cancel_futures=True)
        self.fitter.close()
        with contextlib.suppress(OSError):
            for name in os.listdir(self.folder):
                os.unlink(os.path.join(self.folder, name))
                interrupt.unregister(os.path.join(self.folder, name))
            os.rmdir(self.folder)
        interrupt.unregister(self.folder)

    def render(self, values: np.ndarray, size: int, *, seed: int, spp: int) -> np.ndarray:
        """Returns the linear render of physical values at `size`: at the model's resolution on the fitter's render
        processes (the fits' own renders, bit for bit), any other size in this process on every core (its renderer
        loaded once, on the worker thread)."""
        if size == self.model.resolution:
            return self.fitter.render(Material.from_array(values), seed=seed, spp=spp)
        if size not in self.renderers:
            self.renderers[size] = Renderer(size, verify.SPP, self.variant, threads=os.cpu_count() or 1)
        return self.renderers[size].render(values, seed=seed, spp=spp)

    def new_job(self, kind: str) -> Job:
        """Returns a new job, registered."""
        with self.lock:
            job = Job(f"{kind}-{next(self.counter)}", kind)
            self.jobs[job.id] = job
        return job

    def warm_up(self) -> None:
        """Compiles the fit and loads the renderer before the first page asks (a fit of a grey picture)."""
        grey = np.full((self.model.resolution, self.model.resolution, 3), 0.5, np.float32)
        search.neural_search(self.model, grey, settings=self.settings)
        self.fitter.render(Material.from_array(params.DEFAULTS), spp=1)  # the render processes load the scene
        self.preview(params.DEFAULTS)

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
        try:
            self._run_fit(job, target, label, mask, init, watched)
        finally:
            uploads.discard(mask, None if watched else target)  # the job has ended: its uploads are no longer needed

    def _run_fit(
        self, job: Job, target: str, label: str, mask: str | None, init: np.ndarray | None, watched: bool
    ) -> None:
        if job.cancelled.is_set():
            job.state = job.stage = "superseded" if job.state == "superseded" else "cancelled"
            return
        job.state, job.stage, job.progress = "running", "fitting", 0.1
        started = time.perf_counter()
        picture = None
        try:
            picture = self.snapshot(target) if watched else target  # the editor may save or delete it meanwhile
            source = None if init is None else Material.from_array(init)
            landed = functools.partial(self._landed, job)
            fitted = self.fitter.fit(picture, mask=mask, init=source, settings=self.settings, answers=landed)
            if watched and not os.path.exists(target):
                raise gone(target, "while it was fitted")
            fitted.document.update(target=label, target_sha256=files.sha256(picture), model=self.model_label)
            if init is not None:
                fitted.document["init"] = "uploaded params.json"
            if mask is not None:
                fitted.document["mask"] = "painted in the page"
            fitted.document["wall_time_s"] = round(time.perf_counter() - started, 3)
            job.outcome, job.result = fitted, fit_result(fitted)
            job.state, job.stage, job.progress = "done", "done", 1.0
        except SupersededError:  # cancelled, or a newer save of the watched file: the rest of the fit is not run
            job.state = job.stage = "superseded" if watched else "cancelled"
            job.result = None  # an earlier stage's answer is no fit's
        except MatfitError as error:
            status = 410 if error.field == GONE else 422
            message = str(error).replace(picture, target) if watched and picture else str(error)  # the file it names
            job.state, job.stage, job.error, job.status, job.result = "error", "error", message, status, None
        except Exception as error:  # a failure of matfit's own: the job ends (never "running" for ever), said in a line
            message = str(error).splitlines()[0] if str(error) else type(error).__name__
            job.state, job.stage, job.error, job.status = "error", "error", f"the fit failed: {message}", 500
            job.result = None  # an earlier stage's answer is no fit's
        finally:
            if watched and picture is not None:
                with contextlib.suppress(OSError):
                    os.unlink(picture)
                interrupt.unregister(picture)
            job.finished = time.perf_counter()
            if job.cancelled.is_set() and job.state == "done":
                job.state = job.stage = "superseded"

    @staticmethod
    def _landed(job: Job, answer: Fit) -> None:
        """Shows the page a stage's answer of a running fit as soon as it exists, the neural search's first (not yet
        checked in Mitsuba), until the next one, and then the fit's own, replaces it. A job cancelled meanwhile (or
        superseded by a newer save) ends here, its later stages not run (`SupersededError`)."""
        if job.cancelled.is_set():
            raise SupersededError
        if job.state == "running":
            job.result = fit_result(answer)

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
        for k in range(passes):
            if job.cancelled.is_set():
                job.state = job.stage = "cancelled"
                job.finished = time.perf_counter()
                return
            samples = spp // passes + (1 if k < spp % passes else 0)
            total += samples * self.render(values, size, seed=k, spp=samples)
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
        """Marks a job cancelled: a queued one never runs, a render stops after its current pass, a fit at its next
        stage's answer."""
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
