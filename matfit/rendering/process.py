"""Renderers that work beside the caller: on a thread (`Background`) or in a child process (`Process`).

`Background` loads a `Renderer` and renders on one thread of this process while the caller computes;
`Process` runs one in a child interpreter started at once, so Mitsuba's import and variant choice
take another core while the caller imports JAX. The child's main (`serve_requests`) answers the
requests it reads from one pipe on another. `start_child` starts such a child (a dataset's render
workers too, `dataset_workers`); the messages on both pipes are data only
(`write_message`, `read_message`: a JSON header and a float array), so reading one runs no code.

A reply that does not come within `reply_seconds` of being awaited (a child stopped, or stuck) is a
RenderError, and its child is killed; a child that ended is named with how it ended (its exit code or
signal); a request or reply left part-way (a KeyboardInterrupt while it was written or read) leaves its
process unusable. In each case `Pool.healthy` is then False, and its owner (`matfit.Fitter`) starts new
children for the next fit.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import TYPE_CHECKING, BinaryIO, NoReturn

import numpy as np

from matfit import params, shipped
from matfit.errors import RenderError
from matfit.rendering.engine import CUDA_VARIANT, Renderer, choose_variant, cuda_devices, mitsuba

if TYPE_CHECKING:
    from jaxtyping import Float

# The longest a child may take over one reply before it is taken for stuck (stopped, a hung driver), killed and
# replaced: START_SECONDS for what does not grow with the render (Mitsuba's import before "ready"; loading a scene; the
# first render of a sample count, which compiles its kernels; a machine busy with other work), plus SAMPLE_SECONDS for
# each sample of each pixel, about 20 times the slowest cost measured (9 µs: scalar_rgb, jade's scattering medium, on
# one thread of a busy 2-core machine; llvm_ad_rgb 2-5 µs). A 64 px render of 64 samples may take 352 s; read at each
# wait, so a test can make them small.
START_SECONDS = 300.0
SAMPLE_SECONDS = 2e-4
ENDING_SECONDS = 5.0  # how long a child whose replies ended may take to be gone, before it is killed and named so


def reply_seconds(resolution: int, spp: int) -> float:
    """Returns how long a reply of a render of `resolution`² pixels and `spp` samples may take (the rule above)."""
    return START_SECONDS + SAMPLE_SECONDS * resolution * resolution * spp


def ending(code: int) -> str:
    """Returns how a child of return code `code` ended, in words: "exit code 3", "killed by signal 9 (SIGKILL)"."""
    if code >= 0:
        return f"exit code {code}"
    try:
        name = f" ({signal.Signals(-code).name})"
    except ValueError:
        name = ""
    return f"killed by signal {-code}{name}"


class Background:
    """A `Renderer` loaded, and renders made, on one background thread while the caller computes.

    Importing Mitsuba, loading the scene, the first `update()` of its parameters and the first
    render's kernels take time that a fit need not wait for (XLA releases the interpreter), and a
    render asked for early (`prefetch`, such as the fit's start as soon as best-of-n has chosen it)
    runs during the fit's next stage. One thread does it all, so the scene is never used by two
    renders at once; `render` waits for it before rendering itself, and answers a prefetched
    (values, seed, spp) with that image (each render is seeded, so it is the same picture). A
    failure to load is raised by `renderer()` and `render`. Its thread finishes its jobs before
    the interpreter exits (Ctrl-C included), so Mitsuba is never torn down mid-render.
    """

    def __init__(self, resolution: int, spp: int, variant: str | None = None):
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="matfit-renderer")
        self._loaded = self._executor.submit(self._load, resolution, spp, variant)
        self._prefetched: dict[tuple, Future] = {}

    @staticmethod
    def _load(resolution: int, spp: int, variant: str | None) -> Renderer:
        renderer = Renderer(resolution, spp, variant, threads=1)  # its renders decide: bit-identical run to run
        renderer.render(params.DEFAULTS, spp=1)  # warms the kernels; changes no later (seeded) render
        return renderer

    @staticmethod
    def _key(values: np.ndarray, seed: int, spp: int | None) -> tuple:
        return np.asarray(values, np.float64).tobytes(), int(seed), spp

    def prefetch(self, values: Float[np.ndarray, " 19"], seed: int = 0, spp: int | None = None) -> None:
        """Starts rendering a material in the background, for a later `render` of the same arguments."""
        key = self._key(values, seed, spp)
        if key not in self._prefetched:
            self._prefetched[key] = self._executor.submit(lambda: self._loaded.result().render(values, seed, spp))

    def renderer(self) -> Renderer:
        """Returns the loaded renderer once every background render is done (raises a failure to load)."""
        wait(self._prefetched.values())
        return self._loaded.result()

    def render(
        self, values: Float[np.ndarray, " 19"], seed: int = 0, spp: int | None = None
    ) -> Float[np.ndarray, "R R 3"]:
        """Returns what `Renderer.render` returns: the prefetched image of these arguments, or a new render."""
        renderer = self.renderer()
        job = self._prefetched.get(self._key(values, seed, spp))
        return job.result() if job is not None else renderer.render(values, seed, spp)


def start_child(
    module: str, function: str, *arguments: object, pipe_bytes: int | None = None
) -> tuple[subprocess.Popen, BinaryIO, BinaryIO]:
    """Returns (the child, the file to write its requests to, the file to read its replies from): a new interpreter of
    this very matfit that runs `module.function(requests, replies, *arguments)`, the first two the file descriptors
    of its ends of two pipes.

    The child imports the matfit this process runs, wherever it lies (clone or site-packages), whatever the working
    directory holds. It runs in a session of its own, so the terminal's Ctrl-C reaches only this process, which
    stops it. It holds only its own ends of the pipes, so it sees its requests end as soon as this process ends,
    however it ends (`kill -9` included). Nothing of multiprocessing is used, so no semaphore or resource tracker
    outlives a killed parent either. `arguments` are written into its command line by `repr` (numbers, strings,
    None). `pipe_bytes`: room asked for in the replies pipe (Linux), so that the child need not wait for a read.
    Both ends of both pipes are closed here if the child cannot start.
    """
    requests_read, requests_write = os.pipe()
    replies_read, replies_write = os.pipe()
    if pipe_bytes is not None:
        with contextlib.suppress(ImportError, AttributeError, OSError):  # Linux: a pipe holds more than 64 KiB if asked
            import fcntl

            fcntl.fcntl(replies_write, fcntl.F_SETPIPE_SZ, pipe_bytes)
    package = str(shipped.PACKAGE.parent)
    parent, _, name = module.rpartition(".")
    call = ", ".join(repr(value) for value in (requests_read, replies_write, *arguments))
    code = f"import sys; sys.path.insert(0, {package!r}); from {parent} import {name}; {name}.{function}({call})"
    try:
        child = subprocess.Popen(
            [sys.executable, "-c", code], pass_fds=(requests_read, replies_write), start_new_session=True
        )
    except BaseException:
        os.close(requests_write)
        os.close(replies_read)
        raise
    finally:
        os.close(requests_read)
        os.close(replies_write)
    # Replies unbuffered: what the pipe holds is all that arrived, so `select` tells whether a reply waits (`Process`).
    return child, os.fdopen(requests_write, "wb"), os.fdopen(replies_read, "rb", buffering=0)


class Process:
    """A `Renderer` in a child process, which imports Mitsuba as soon as it is made, beside whatever the caller loads.

    A cold `matfit fit` spends its first second importing JAX on one core; Mitsuba's import and the
    choice of its variant then take the other, where on a thread they would wait for the
    interpreter, which both imports hold. Made at once, before the caller's own heavy imports,
    `load(resolution, spp)` then loads the scene, and `prefetch` and `render` behave as
    `Background`'s: requests are answered in order, a prefetched (values, seed, spp) is rendered
    once, and the images are those of `Renderer.render` in this process, seed for seed (up to the
    last bits, as two renders in one process are). A failure in the child (no usable variant, a bad
    material) is raised here as its RenderError. The child ignores Ctrl-C (it is in a session of its
    own) and ends when this side closes its requests (`close`, or this process ending any way,
    `kill -9` included): it never outlives the caller for longer than the render in hand.
    """

    PIPE_BYTES = 1 << 20  # room for the replies of every prefetched render, so the child never waits for a read

    def __init__(self, variant: str | None = None):
        self._child, self._requests, self._replies = start_child(
            "matfit.rendering.process", "serve_requests", variant, pipe_bytes=self.PIPE_BYTES
        )
        self._ready: tuple | None = None  # the child's first reply: (variant, notice)
        # (key, seconds its reply may take) of the requests sent and not yet answered, in order
        self._pending: list[tuple[tuple, float]] = []
        self._answers: dict[tuple, np.ndarray | RenderError] = {}  # key -> image, or the RenderError of its render
        self._resolution: int | None = None
        self._spp = 0  # the loaded scene's samples, those of a render that names none
        # Why the child is of no more use (it failed to start, ended, was stuck, or was left part-way through a
        # message), raised again at every use; None while it serves.
        self._failure: RenderError | None = None
        # True from the start of a request's write or a reply's read until it is filed: still True after an exception
        # that broke into one (an interrupt), when the pipes' state is unknown and the process no longer usable.
        self._unsettled = False

    @property
    def variant(self) -> str:
        """The variant the child renders with (waits until it has imported Mitsuba)."""
        return self._started()[0]

    @property
    def notice(self) -> str | None:
        """The child's notice about its variant (the scalar fallback), if any."""
        return self._started()[1]

    def load(self, resolution: int, spp: int) -> None:
        """Has the child load the scene at `resolution` (and warm its kernels) before the first render; a scene loaded
        at that resolution already is kept (a warm process's next fit renders at once)."""
        if self._resolution == resolution:
            return
        self._resolution, self._spp = resolution, int(spp)
        seconds = reply_seconds(resolution, 1)  # the scene, and a render of one sample that compiles its kernels
        self._send({"load": [int(resolution), int(spp)]}, key=("load", resolution), seconds=seconds)

    def prefetch(self, values: Float[np.ndarray, " 19"], seed: int = 0, spp: int | None = None) -> None:
        """Asks for a render now, for a later `render` of the same arguments."""
        key = Background._key(values, seed, spp)
        if key not in self._answers and all(key != pending for pending, _ in self._pending):
            seconds = reply_seconds(self._resolution or 0, int(spp or self._spp))
            self._send({"seed": int(seed), "spp": spp}, np.asarray(values, np.float64), key=key, seconds=seconds)

    def render(
        self, values: Float[np.ndarray, " 19"], seed: int = 0, spp: int | None = None
    ) -> Float[np.ndarray, "R R 3"]:
        """Returns what `Renderer.render` returns: the linear float32 (H, W, 3) image of a material."""
        if self._resolution is None:
            raise RenderError("the render process has no scene yet: call load(resolution, spp) first")
        key = Background._key(values, seed, spp)
        self.prefetch(values, seed, spp)
        while key not in self._answers:
            self._receive()
        answer = self._answers.pop(key)
        if isinstance(answer, RenderError):
            raise answer
        return answer

    def outstanding(self) -> int:
        """Returns how many requests the child has not answered yet: the replies that arrived are read first (without
        waiting), so a render finished but not yet asked for by `render` does not count."""
        while self._pending and self._failure is None and select.select([self._replies], [], [], 0)[0]:
            self._receive()
        return len(self._pending)

    def healthy(self) -> bool:
        """Returns whether the child runs and can be used: it started, has not ended, was not found stuck, and was not
        left part-way through a request or a reply."""
        return self._failure is None and not self._unsettled and self._child.poll() is None

    def renderer(self) -> Process:
        """Returns this process once the child has started (raises its failure to start): as `Background.renderer`."""
        self._started()
        return self

    def close(self) -> None:
        """Ends the child: it sees its requests end and exits by itself once its render in hand is done (nobody waits
        for it: the caller may be about to exit). A child never asked for anything (the caller failed first) is
        killed at once: it holds nothing but Mitsuba's import."""
        with contextlib.suppress(OSError):
            self._requests.close()
        if self._ready is None and not self._pending and self._failure is None:
            self._child.kill()
        with contextlib.suppress(OSError):
            self._replies.close()
        threading.Thread(target=self._child.wait, name="matfit-render-reaper", daemon=True).start()

    def __enter__(self) -> Process:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _started(self) -> tuple:
        while self._ready is None:
            self._receive()
        return self._ready

    def _usable(self) -> None:
        """Raises why the child is of no more use, if it is not."""
        if self._failure is None and self._unsettled:  # an exception broke into a message: its end is unknown
            self._failure = RenderError(
                "the render process was interrupted in the middle of a request or reply: the next fit starts new "
                "render processes"
            )
        if self._failure is not None:
            raise self._failure

    def _send(self, header: dict, array: np.ndarray | None = None, *, key: tuple, seconds: float) -> None:
        """Writes a request and files it as pending (`key`, `seconds` its reply may take)."""
        self._usable()
        self._unsettled = True
        try:
            write_message(self._requests, header, array)
        except (BrokenPipeError, ValueError):  # ended, or closed: the reason is the child's
            self._failed()
        self._pending.append((key, seconds))
        self._unsettled = False

    def _receive(self) -> None:
        """Reads the child's next reply and files it: its start, a load, or the oldest pending render; a reply that
        does not come in time (`reply_seconds` of its request, START_SECONDS for the start) kills the child."""
        self._usable()
        seconds = self._pending[0][1] if self._ready is not None and self._pending else START_SECONDS
        self._unsettled = True
        try:
            header, image = read_message(self._replies, time.monotonic() + seconds)
        except TimeoutError:
            self._stuck(seconds)
        except (EOFError, OSError, ValueError):
            self._failed()
        failure = None
        if "ready" in header:
            self._ready = (header["ready"], header["notice"])
        elif "failed" in header:  # it could not start, and has ended: every later use fails the same way
            self._failure = failure = RenderError(header["failed"])
        else:
            key, _ = self._pending.pop(0)
            answer = RenderError(header["error"]) if "error" in header else image
            if key[0] != "load":
                self._answers[key] = answer if answer is not None else RenderError("the render process sent no image")
            elif isinstance(answer, RenderError):
                failure = answer
        self._unsettled = False
        if failure is not None:
            raise failure

    def _stuck(self, seconds: float) -> NoReturn:
        """Kills the child, whose reply did not come within `seconds`, and raises (at every later use too) why."""
        self._child.kill()
        key = self._pending[0][0] if self._ready is not None and self._pending else ("start",)
        asked = (
            "its start"
            if key[0] == "start"
            else f"a {key[1]} px scene's load"
            if key[0] == "load"
            else f"a {self._resolution} px render of {key[2] or self._spp} samples"
        )
        self._failure = RenderError(
            f"the render process gave no reply in {seconds:.0f} s, the most {asked} may take (stopped, or stuck): "
            "it was killed; the next fit starts new render processes"
        )
        raise self._failure

    def _failed(self) -> NoReturn:
        """Raises (at every later use too) that the child ended, and how: its exit code or signal."""
        try:
            code = self._child.wait(ENDING_SECONDS)  # its pipes close as it exits, a moment before it is gone
        except subprocess.TimeoutExpired:  # it runs, but its replies ended or could not be read
            self._child.kill()
            self._failure = RenderError(
                "the render process broke off its replies while it ran: it was killed; the next fit starts new "
                "render processes"
            )
            raise self._failure from None
        self._failure = RenderError(
            f"the render process ended unexpectedly ({ending(code)}): the next fit starts new render processes; "
            "if it ends again, run `matfit render` on a preset to see Mitsuba's own message"
        )
        raise self._failure


def cores() -> int:
    """Returns how many cores this process may run on (its CPU affinity where the system tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


class Pool:
    """`Process`es, one render child a core, that render a batch of requests at once: every core renders, and every
    image is still bit-identical from run to run and whatever the number of children.

    Each child renders on one thread (`Renderer`'s `threads=1`), so an image depends only on its material, seed and
    samples, never on which child made it, what it made before, or how many children there are: a fit's answer is
    the same with one child or sixteen. (Several threads in one render are not: the gaussian filter's footprint
    crosses pixels that other threads write at the same time, in no fixed order.) Parallelism is across renders:
    verification asks for all the batches it needs (`prefetch`) before reading the first, and each request goes to
    the child with the fewest requests outstanding. It behaves as `Process` otherwise (`load`, `prefetch`,
    `render`, `close`, a context manager); `children` None: one a core (`cores`), or one where the renders run on
    an NVIDIA GPU (`cuda_ad_rgb`: one render uses the whole GPU, and each child would hold a CUDA context of its own).
    """

    def __init__(self, variant: str | None = None, children: int | None = None):
        on_gpu = variant == CUDA_VARIANT or (variant is None and cuda_devices() > 0)
        count = (1 if on_gpu else cores()) if children is None else int(children)
        if count < 1:
            raise ValueError(f"a render pool needs at least one child, got {count}")
        self._children: list[Process] = []
        try:
            for _ in range(count):
                self._children.append(Process(variant))
        except BaseException:
            self.close()
            raise
        self._owners: dict[tuple, Process] = {}  # key -> the child asked for it, until `render` reads it
        self._spp = 0  # the loaded scene's samples, those of a request that names none
        self.renders = 0  # renders asked of the children so far (a prefetched one counts once)
        self.samples = 0  # samples per pixel of those renders, summed

    @property
    def children(self) -> int:
        """How many render children the pool holds."""
        return len(self._children)

    @property
    def variant(self) -> str:
        """The variant the children render with (waits until the first has imported Mitsuba)."""
        return self._children[0].variant

    @property
    def notice(self) -> str | None:
        """The children's notice about their variant (the scalar fallback), if any."""
        return self._children[0].notice

    def load(self, resolution: int, spp: int) -> None:
        """Has every child load the scene at `resolution` (and warm its kernels) before the first render."""
        self._spp = int(spp)
        for child in self._children:
            child.load(resolution, spp)

    def prefetch(self, values: Float[np.ndarray, " 19"], seed: int = 0, spp: int | None = None) -> None:
        """Asks the least busy child for a render now, for a later `render` of the same arguments."""
        key = Background._key(values, seed, spp)
        if key not in self._owners:
            child = min(self._children, key=Process.outstanding)  # the first of those with the fewest renders to make
            child.prefetch(values, seed, spp)
            self._owners[key] = child
            self.renders += 1
            self.samples += int(spp or self._spp)

    def render(
        self, values: Float[np.ndarray, " 19"], seed: int = 0, spp: int | None = None
    ) -> Float[np.ndarray, "R R 3"]:
        """Returns what `Renderer.render` returns: the linear float32 (H, W, 3) image of a material."""
        self.prefetch(values, seed, spp)
        return self._owners.pop(Background._key(values, seed, spp)).render(values, seed, spp)

    def healthy(self) -> bool:
        """Returns whether every child runs and can be used (`Process.healthy`): a pool fit to keep for the next fit
        after one that failed (the picture's fault, not the renderer's) or was interrupted between two messages."""
        return all(child.healthy() for child in self._children)

    def renderer(self) -> Pool:
        """Returns this pool once every child has started (raises the first failure to start)."""
        for child in self._children:
            child.renderer()
        return self

    def close(self) -> None:
        """Ends every child (`Process.close`)."""
        for child in self._children:
            child.close()

    def __enter__(self) -> Pool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def serve_requests(requests: int, replies: int, variant: str | None) -> None:
    """The child of `Process`: imports Mitsuba, then answers its requests, read from the file descriptor `requests`, on
    `replies`, until they end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        answer_requests(requests, replies, variant)
    except BrokenPipeError:  # the caller ended (Ctrl-C, kill -9) while this answered: nobody is left to tell
        os._exit(0)  # not sys.exit: the interpreter's own final flush would hit the same closed pipe


def answer_requests(requests: int, replies: int, variant: str | None) -> None:
    """`serve_requests`'s loop: starts Mitsuba, then answers each request on `replies` until `requests` ends."""
    with os.fdopen(requests, "rb") as incoming, os.fdopen(replies, "wb") as outgoing:
        try:
            chosen, notice = choose_variant(variant)
            mitsuba(chosen)
        except Exception as error:  # RenderError, or Mitsuba failing to import
            failure = str(error) if isinstance(error, RenderError) else f"Mitsuba could not start: {error}"
            write_message(outgoing, {"failed": failure})
            return
        write_message(outgoing, {"ready": chosen, "notice": notice})
        renderer = None
        while True:
            try:
                request, values = read_message(incoming)
            except (EOFError, OSError, ValueError):  # the caller closed its end, or ended
                return
            try:
                if "load" in request:
                    resolution, spp = request["load"]
                    renderer = Renderer(resolution, spp, chosen, threads=1)  # its renders decide: bit-identical
                    renderer.render(params.DEFAULTS, spp=1)  # warms the kernels, as Background does
                    write_message(outgoing, {"done": True})
                else:
                    if renderer is None or values is None:  # `Process` loads first and sends values with a render
                        raise RenderError("a render request came before the scene, or without parameters")
                    image = renderer.render(values, request["seed"], request["spp"])
                    write_message(outgoing, {"done": True}, image)
            except RenderError as error:
                write_message(outgoing, {"error": str(error)})
            except Exception as error:  # anything else Mitsuba raises: the caller reports it in one line
                write_message(outgoing, {"error": f"Mitsuba failed: {type(error).__name__}: {error}"})


FRAME = struct.Struct("<II")  # a message's header length, then its array's length (0: none)


def write_message(file, header: dict, array: np.ndarray | None = None) -> None:
    """Writes one message of `Process`'s pipes: a JSON header and, if given, a float array (its dtype and shape
    named in the header). Data only: reading a message runs no code."""
    data = b""
    if array is not None:
        array = np.ascontiguousarray(array)
        header = {**header, "dtype": array.dtype.str, "shape": list(array.shape)}
        data = array.tobytes()
    text = json.dumps(header).encode()
    file.write(FRAME.pack(len(text), len(data)) + text + data)
    file.flush()


def read_message(file, deadline: float | None = None) -> tuple[dict, np.ndarray | None]:
    """Returns (header, array or None) of the next message `write_message` wrote; EOFError when the pipe ended.

    `deadline`: the `time.monotonic()` by which the whole message must have come, else TimeoutError (`file` must then
    be unbuffered, so that `select` sees every byte not yet read); None waits for ever."""

    def exactly(size: int, *, first: bool = False) -> bytes:
        data = b""
        while len(data) < size:  # an unbuffered pipe returns what has arrived: read on until the message is whole
            if deadline is not None and not select.select([file], [], [], max(deadline - time.monotonic(), 0))[0]:
                raise TimeoutError("no message came in time" if first and not data else "a message stopped part-way")
            more = file.read(size - len(data))
            if not more:
                raise EOFError("the pipe ended" if first and not data else "the pipe ended inside a message")
            data += more
        return data

    sizes = exactly(FRAME.size, first=True)
    text_size, data_size = FRAME.unpack(sizes)
    header = json.loads(exactly(text_size))
    if not data_size:
        return header, None
    array = np.frombuffer(bytearray(exactly(data_size)), dtype=np.dtype(header["dtype"])).reshape(header["shape"])
    return header, array
