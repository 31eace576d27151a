import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from matfit import params, presets
from matfit.errors import RenderError
from matfit.render_process import RendererProcess
from tests.conftest import TEST_RESOLUTION, TEST_SPP


@pytest.fixture(scope="module")
def process():
    child = RendererProcess()
    child.open(TEST_RESOLUTION, TEST_SPP)
    yield child
    child.close()


def test_renders_what_the_renderer_in_this_process_renders(process, renderer):
    for name in ("gold", "jade"):
        values = presets.preset(name)
        here = renderer.render(values, seed=7, spp=32)
        there = process.render(values, seed=7, spp=32)
        assert there.shape == (TEST_RESOLUTION, TEST_RESOLUTION, 3) and there.dtype == np.float32
        # the same samples; only the order in which threads add them into the film may differ
        np.testing.assert_allclose(there, here, rtol=1e-4, atol=1e-5)
    assert process.variant == renderer.variant and process.resolution == TEST_RESOLUTION
    other = process.render(presets.preset("gold"), seed=8, spp=32)
    assert not np.allclose(other, process.render(presets.preset("gold"), seed=7, spp=32))


def test_opening_twice_at_another_size_is_refused(process):
    process.open(TEST_RESOLUTION, TEST_SPP)  # the same: nothing to do
    with pytest.raises(RenderError, match="renders 16 px; it cannot switch to 32 px"):
        process.open(32, TEST_SPP)


def test_a_failure_in_the_child_is_the_same_render_error():
    with RendererProcess(variant="cuda_ad_rgb") as child:
        child.open(TEST_RESOLUTION, TEST_SPP)
        for _ in range(2):  # and stays one: the pipe is not left waiting
            with pytest.raises(RenderError, match="unknown variant 'cuda_ad_rgb'"):
                child.render(params.DEFAULTS)
    with RendererProcess() as child, pytest.raises(RenderError, match="not opened: call open"):
        child.render(params.DEFAULTS)


def test_a_killed_child_is_a_render_error_naming_the_fix():
    with RendererProcess() as child:
        child.open(TEST_RESOLUTION, TEST_SPP)
        child.render(params.DEFAULTS, spp=1)
        child._process.kill()
        child._process.wait()
        with pytest.raises(RenderError, match=r"ended unexpectedly \(exit code -9\).*--no-verify"):
            child.render(params.DEFAULTS, spp=1)


@pytest.mark.parametrize("ending", ["exit", "kill"])
def test_the_child_ends_with_its_parent(tmp_path, ending):
    script = (
        "import os, signal, sys\n"
        "from matfit.render_process import RendererProcess\n"
        "child = RendererProcess()\n"
        "child.open(16, 4)\n"
        "child.render([0.5] * 19, spp=1)\n"
        "print(child._process.pid, flush=True)\n"
        + ("os._exit(0)\n" if ending == "exit" else "os.kill(os.getpid(), signal.SIGKILL)\n")
    )
    parent = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=False, timeout=120)
    pid = int(parent.stdout.split()[0])
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and _alive(pid):
        time.sleep(0.05)
    assert not _alive(pid), "the rendering child outlived its parent"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as stat:  # a zombie waiting for init to reap it is gone for our purpose
        return stat.read().split()[2] != "Z"


def test_ctrl_c_reaches_the_parent_only():
    child = RendererProcess()
    child.open(TEST_RESOLUTION, TEST_SPP)
    child.render(params.DEFAULTS, spp=1)
    os.kill(child._process.pid, signal.SIGINT)
    np.testing.assert_array_equal(
        child.render(params.DEFAULTS, seed=3, spp=2), child.render(params.DEFAULTS, seed=3, spp=2)
    )
    assert child._process.poll() is None
    child.close()
    assert child._process.poll() is not None
