"""A `render.Renderer` in a child process, started before the parent imports JAX.

A cold `matfit fit` spends most of its first second in one thread: importing JAX and Flax, loading
the networks, tracing the compiled stages. Verification then needs Mitsuba: importing it, loading
the scene and loading its kernels cost ~0.5 s more, in series. `RendererProcess` starts a Python
child at once that imports Mitsuba on the other core while the parent works; `open` (as soon as the
model's resolution is known) has it load the scene and render once, so that the kernels are loaded
too; `render` then answers like `Renderer.render`.

The child is private to its parent: requests and replies are JSON headers (and an image's raw
float32 bytes) over two pipes; its own stdout and stderr stay closed, so nothing of Mitsuba's
reaches the terminal. It ignores Ctrl-C (the parent handles it) and ends when its request pipe
closes, which happens however the parent ends (normally, `os._exit` after Ctrl-C, kill -9). A
failure in the child reaches the parent as the same `RenderError` an in-process renderer raises.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import struct
import subprocess
import sys
from typing import BinaryIO

import numpy as np

from matfit.errors import RenderError

WARM_UP_SPP = 1
HEADER = struct.Struct("<I")  # a message: its JSON header's length, the header, then the payload it announces


def write_message(stream: BinaryIO, header: dict, payload: bytes = b"") -> None:
    """Writes one message (a JSON header and optional raw bytes) and flushes it."""
    text = json.dumps(header).encode()
    stream.write(HEADER.pack(len(text)) + text + payload)
    stream.flush()


def _read_exactly(stream: BinaryIO, size: int) -> bytes:
    data = stream.read(size)
    if len(data) != size:
        raise EOFError("the pipe closed")
    return data


def read_message(stream: BinaryIO) -> dict:
    """Reads one message's header, with an image's array under "image" when it announces one."""
    header = json.loads(_read_exactly(stream, HEADER.unpack(_read_exactly(stream, HEADER.size))[0]))
    if "shape" in header:
        shape = tuple(header["shape"])
        data = _read_exactly(stream, int(np.prod(shape)) * 4)
        header["image"] = np.frombuffer(data, np.float32).reshape(shape).copy()
    return header


class RendererProcess:
    """`render.Renderer`'s `render`, `resolution`, `spp`, `variant` and `notice`, served by a child process."""

    def __init__(self, variant: str | None = None):
        request_read, self._request_write = os.pipe()
        self._reply_read, reply_write = os.pipe()
        self._process = subprocess.Popen(
            [sys.executable, "-m", "matfit.render_process", str(request_read), str(reply_write), variant or ""],
            pass_fds=(request_read, reply_write),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        os.close(request_read)
        os.close(reply_write)
        self._requests = os.fdopen(self._request_write, "wb")
        self._replies = os.fdopen(self._reply_read, "rb")
        self.resolution: int | None = None
        self.spp: int | None = None
        self._opened: tuple[str, str | None] | RenderError | None = None  # the child's answer to `open`

    def open(self, resolution: int, spp: int) -> None:
        """Asks the child to load the scene at `resolution` px (without waiting for it); once per process."""
        if self.resolution is not None:
            if (resolution, spp) != (self.resolution, self.spp):
                raise RenderError(f"this renderer renders {self.resolution} px; it cannot switch to {resolution} px")
            return
        self.resolution, self.spp = resolution, spp
        self._send({"op": "open", "resolution": int(resolution), "spp": int(spp)})

    def _opened_reply(self) -> tuple[str, str | None]:
        if self.resolution is None:
            raise RenderError("the renderer process was not opened: call open(resolution, spp) first")
        if self._opened is None:
            try:
                reply = self._receive()
                self._opened = (reply["variant"], reply["notice"])
            except RenderError as error:
                self._opened = error
        if isinstance(self._opened, RenderError):
            raise self._opened
        return self._opened

    @property
    def variant(self) -> str:
        """Returns the Mitsuba variant the child renders with."""
        return self._opened_reply()[0]

    @property
    def notice(self) -> str | None:
        """Returns the renderer's notice (such as the scalar fallback), if any."""
        return self._opened_reply()[1]

    def render(self, values: np.ndarray, seed: int = 0, spp: int | None = None) -> np.ndarray:
        """Returns the linear float32 (H, W, 3) image of a material rendered with `seed`, as `Renderer.render`."""
        self._opened_reply()
        values = [float(value) for value in np.asarray(values, np.float64).reshape(-1)]
        self._send({"op": "render", "values": values, "seed": int(seed), "spp": None if spp is None else int(spp)})
        return self._receive()["image"]

    def __enter__(self) -> RendererProcess:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Ends the child now, whatever it is doing (it holds nothing to save; it also ends when this process does)."""
        for stream in (self._requests, self._replies):
            with contextlib.suppress(OSError):
                stream.close()
        self._process.kill()
        self._process.wait()

    def _send(self, message: dict) -> None:
        try:
            write_message(self._requests, message)
        except (BrokenPipeError, ValueError):
            self._stopped()

    def _receive(self) -> dict:
        try:
            reply = read_message(self._replies)
        except (EOFError, OSError, ValueError):
            self._stopped()
        if "error" in reply:
            raise RenderError(reply["error"])
        return reply

    def _stopped(self):
        code = self._process.poll()
        raise RenderError(
            f"Mitsuba's rendering process ended unexpectedly (exit code {code}): "
            "check the installation with `matfit render --preset gold`, or fit with --no-verify"
        )


def serve(request_fd: int, reply_fd: int, variant: str | None) -> None:
    """The child's loop: load Mitsuba, then answer `open` and `render` requests until the request pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C; closing the pipe ends this process
    with os.fdopen(request_fd, "rb") as requests, os.fdopen(reply_fd, "wb") as replies:
        renderer, failure = None, None
        try:
            from matfit import render

            render.mitsuba(render.choose_variant(variant)[0])  # the import: most of what this process saves
        except Exception as error:  # any failure is the parent's RenderError
            failure = str(error)
        while True:
            try:
                request = read_message(requests)
            except (EOFError, OSError, ValueError):
                return
            try:
                if failure is not None:
                    raise RenderError(failure)
                if request["op"] == "open":
                    from matfit import params
                    from matfit.render import Renderer

                    renderer = Renderer(request["resolution"], request["spp"], variant)
                    renderer.render(params.DEFAULTS, seed=0, spp=WARM_UP_SPP)  # loads the kernels
                    write_message(replies, {"variant": renderer.variant, "notice": renderer.notice})
                else:
                    image = renderer.render(np.array(request["values"]), seed=request["seed"], spp=request["spp"])
                    image = np.ascontiguousarray(image, np.float32)
                    write_message(replies, {"shape": list(image.shape)}, image.tobytes())
            except BrokenPipeError:
                return
            except Exception as error:  # reported to the parent, which raises it
                message = str(error) if isinstance(error, RenderError) else f"Mitsuba could not render: {error}"
                write_message(replies, {"error": message})


if __name__ == "__main__":
    serve(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] or None)
