"""Serving the page: the checks made before the model is loaded, the server in a thread (tests, benchmarks), and
`matfit serve` itself."""

from __future__ import annotations

import contextlib
import os
import threading
import time

import matfit
from matfit.app.serve.routes import create_app
from matfit.app.serve.studio import Studio
from matfit.app.serve.watch import check_watch
from matfit.errors import OutputError
from matfit.fitting import document


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

    from matfit.rendering.engine import check_request

    check_watch(watch)
    check_listen(host, port)
    check_request(variant)
    model = matfit.load_model(model_path)
    studio = Studio(model, document.display_path(model_path), variant=variant)
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

        server.startup = startup  # type: ignore[method-assign]  # uvicorn has no hook for "listening"
    try:
        server.run()
    finally:
        studio.close()
    if not server.started:
        raise OutputError(f"cannot listen on {host}:{port} (in use?): choose another --port", field="port")
