"""What matfit promises under faults, tested with real faults: SIGINT through a subprocess, a full disk on a tiny tmpfs.

The full disk is a 16 KiB tmpfs mounted inside a private mount namespace (`unshare --map-root-user
--mount`), so the tests need neither root nor a cleanup; where user namespaces are not allowed
they skip and say so.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from helpers import R, decode, random_model, true_point

from matfit import images
from matfit.fitting import batch
from matfit.model import architectures, weight_files

PROMPT = 10.0  # seconds: the promise is about a second; a hang (the bug) lasted minutes


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    """A random 32 px model saved as a model directory: a subprocess fits with it in milliseconds per step."""
    model = random_model()
    directory = tmp_path_factory.mktemp("model")
    weight_files.save(str(directory / "decoder.msgpack"), model.decoder)
    for network in model.encoders.values():  # described at the decoder's resolution, as training would
        network = dataclasses.replace(network, description=architectures.architecture(network.name, R))
        weight_files.save(str(directory / f"{network.name}.msgpack"), network)
    images.write(str(directory / "target.png"), images.srgb_decode(decode(model, true_point(3))))
    return directory


def interrupt_after(command: list[str], ready, cwd) -> tuple[int, str, float]:
    """Starts `command`, waits until `ready(process)`, sends SIGINT; returns (exit code, stderr, seconds to stop)."""
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd)
    deadline = time.monotonic() + 120
    while not ready(process) and time.monotonic() < deadline:
        time.sleep(0.02)
    sent = time.monotonic()
    process.send_signal(signal.SIGINT)
    try:
        _, error = process.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        process.kill()
        _, error = process.communicate()
    return process.returncode, error, time.monotonic() - sent


def assert_interrupted(code: int, error: str, seconds: float, directory) -> None:
    assert code == 130, error
    assert error.splitlines() == ["interrupted: nothing was written"], error
    assert seconds < PROMPT, f"took {seconds:.1f} s to stop"
    assert sorted(os.listdir(directory)) == [], "an interrupted command left files behind"


FIT_FOREVER = """
import sys
from matfit import images, interrupt; from matfit.fitting import search as fit; from matfit.model import models
interrupt.install()
model = models.load_model(sys.argv[1])
target = images.srgb_encode(images.read(sys.argv[1] + "/target.png"))
print("fitting", flush=True)
try:
    fit.neural_search(model, target, settings=fit.Settings(method="hybrid", evaluations=1_000_000))
except KeyboardInterrupt:  # XLA's compiler checks for signals itself; the command line then leaves like this
    interrupt.exit_now()
"""


def test_ctrl_c_inside_one_compiled_fit_ends_it_at_once(model_dir, tmp_path):
    """The main thread is inside a single XLA call that would run for minutes: the watchdog ends the process."""
    printed = []

    def fitting(process):
        printed.append(process.stdout.readline())
        time.sleep(3.0)  # compiling, then running: either way inside compiled code, holding no Python frame
        return True

    code, error, seconds = interrupt_after([sys.executable, "-c", FIT_FOREVER, str(model_dir)], fitting, tmp_path)
    assert printed == ["fitting\n"]
    assert_interrupted(code, error, seconds, tmp_path)


@pytest.mark.parametrize("after", [0.3, 6.0])
def test_ctrl_c_during_start_up_or_a_long_fit(model_dir, tmp_path, after):
    """At 0.3 s the command is importing; at 6 s it is loading, compiling or fitting 1,000,000 evaluations.

    Nelder-Mead, because its budget is what --evals sets: the default gradient stage stops in a fraction of a second.
    """
    out = tmp_path / "out"
    out.mkdir()
    command = [sys.executable, "-m", "matfit", "fit", str(model_dir / "target.png"), "--model", str(model_dir)]
    command += ["--method", "hybrid", "--evals", "1000000", "-o", str(out / "p.json"), "--report", str(out / "r.png")]
    started = time.monotonic()
    code, error, seconds = interrupt_after(command, lambda _: time.monotonic() - started > after, tmp_path)
    assert_interrupted(code, error, seconds, out)


def test_ctrl_c_during_a_long_render(tmp_path):
    """Mitsuba takes SIGINT inside a render for itself; the command still ends at once, without the image."""
    out = tmp_path / "out"
    out.mkdir()
    command = [
        sys.executable,
        "-m",
        "matfit",
        "render",
        "--preset",
        "gold",
        "--size",
        "256",
        "--spp",
        "65536",
        "-o",
        str(out / "r.png"),
    ]
    started = time.monotonic()
    code, error, seconds = interrupt_after(command, lambda _: time.monotonic() - started > 5.0, tmp_path)
    assert_interrupted(code, error, seconds, out)


def run_on_full_disk(tmp_path, command: list[str], size: str = "16k") -> tuple[subprocess.CompletedProcess, list[str]]:
    """Runs `command` with tmp_path/full a `size` tmpfs of its own; returns (the result, what the tmpfs holds then)."""
    if shutil.which("unshare") is None:
        pytest.skip("unshare (util-linux) is not installed")
    full = tmp_path / "full"
    full.mkdir()
    script = (
        'mount -t tmpfs -o size="$1" tmpfs "$2" || exit 99; '
        'd="$2"; shift 2; "$@"; c=$?; echo "#listing"; ls -A "$d"; exit $c'
    )
    wrapper = ["unshare", "--map-root-user", "--mount", "sh", "-c", script, "sh", size, str(full)]
    result = subprocess.run(wrapper + command, capture_output=True, text=True, cwd=tmp_path, check=False)
    if result.returncode == 99 or "unshare failed" in result.stderr:
        pytest.skip(f"cannot mount a tmpfs in a user namespace here: {result.stderr.strip()}")
    stdout, _, listing = result.stdout.partition("#listing\n")
    return subprocess.CompletedProcess(result.args, result.returncode, stdout, result.stderr), listing.split()


WRITE_EACH = """
import sys
import numpy as np
from matfit import errors, files, images
noise = np.random.default_rng(0).random((256, 256, 3)).astype(np.float32)
for name in sys.argv[2:]:
    path = sys.argv[1] + "/" + name
    try:
        files.write_text(path, "x" * 40000) if name.endswith(".json") else images.write(path, noise)
        print("wrote", name)
    except errors.OutputError as error:
        print("error:", error)
"""


def test_a_full_disk_fails_every_kind_of_write_cleanly(tmp_path):
    """Every kind of output meets a full disk with one error and no file.

    PNG (OpenImageIO's writer says nothing), JPEG (it aborted the interpreter), EXR, TIFF and text.
    """
    names = ["r.png", "r.jpg", "r.exr", "r.tif", "p.json"]
    result, left = run_on_full_disk(tmp_path, [sys.executable, "-c", WRITE_EACH, str(tmp_path / "full"), *names])
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == [
        f"error: cannot write {tmp_path / 'full' / n}: No space left on device" for n in names
    ]
    assert left == []


@pytest.mark.slow
def test_a_full_disk_during_a_fit_leaves_no_output(model_dir, tmp_path):
    """params.json fits on the disk, the report does not: neither is left, nor any temporary file."""
    full = tmp_path / "full"
    command = [
        sys.executable,
        "-m",
        "matfit",
        "fit",
        str(model_dir / "target.png"),
        "--model",
        str(model_dir),
        "--evals",
        "50",
    ]
    command += ["-o", str(full / "p.json"), "--report", str(full / "report.png")]
    result, left = run_on_full_disk(tmp_path, command, size="8k")
    assert result.returncode == 2, result.stderr
    *answers, last = result.stderr.splitlines()  # each stage's answer as it landed, then the one error line
    assert last == f"error: cannot write {full / 'report.png'}: No space left on device"
    assert all(line.split(":")[0].endswith(" answer") for line in answers), answers
    assert left == []


def test_written_files_are_complete(tmp_path):
    """The other side of the promise: what is written reads back as written."""
    noise = np.random.default_rng(1).random((40, 40, 3)).astype(np.float32)
    for name in ("a.png", "a.exr", "a.jpg"):
        images.write(str(tmp_path / name), noise)
    np.testing.assert_allclose(images.read(str(tmp_path / "a.exr")), noise)
    png = images.srgb_encode(images.read(str(tmp_path / "a.png")))
    assert np.abs(png - images.srgb_encode(noise)).max() <= 0.5 / 255 + 1e-6
    assert sorted(os.listdir(tmp_path)) == ["a.exr", "a.jpg", "a.png"]


STRAY = """
import sys
from matfit import files, interrupt
batch = files.Batch()
open(batch.path(sys.argv[1] + "/out.png"), "w").write("half")
interrupt.exit_now()  # what the watchdog does when the main thread cannot stop by itself
"""


def test_an_interruption_that_cannot_wait_removes_the_temporary_files(tmp_path):
    result = subprocess.run([sys.executable, "-c", STRAY, str(tmp_path)], capture_output=True, text=True, check=False)
    assert result.returncode == 130 and result.stderr == "interrupted: nothing was written\n"
    assert os.listdir(tmp_path) == []


def test_an_interruption_removes_registered_temporaries_and_their_folder(tmp_path):
    folder, kept = tmp_path / "matfit-serve-x", tmp_path / "result.png"
    script = f"""
import os
from matfit import interrupt
os.mkdir({str(folder)!r})
open(os.path.join({str(folder)!r}, "upload.png"), "wb").write(b"x")
open({str(kept)!r}, "wb").write(b"done")
interrupt.register({str(folder)!r})
interrupt.register(os.path.join({str(folder)!r}, "upload.png"))
interrupt.exit_now()
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert result.returncode == 130 and result.stderr.startswith("interrupted:")
    assert not folder.exists() and kept.read_bytes() == b"done"


def test_a_dataset_that_passes_the_size_check_but_not_the_disk_is_refused_in_one_line(tmp_path):
    """10 images of 16 px pass the size check (16130 bytes, 24 KiB free), but their files take whole pages, and
    meta.json one more. Written through memory maps, the images died of SIGBUS (exit -7) in the middle of the
    render; their space is now reserved before anything is written, and the refusal leaves nothing."""
    dataset = tmp_path / "full" / "data"
    command = [sys.executable, "-m", "matfit", "render-dataset", str(dataset), "--count", "10"]
    command += ["--resolution", "16", "--spp", "1", "--workers", "1"]
    result, left = run_on_full_disk(tmp_path, command, size="24k")
    assert result.returncode == 2, result.stderr
    assert result.stderr.splitlines() == [
        f"error: cannot make the files of 10 samples in {dataset}: No space left on device: "
        "free some space on the disk, or lower --count or --resolution"
    ]
    assert left == []


def test_a_fit_of_several_pictures_killed_part_way_goes_on_where_it_stopped(model_dir, tmp_path):
    """kill -9 once the first picture is written: the same command again keeps it (not rewritten) and fits the rest."""
    pictures = []
    for name in ("a", "b", "c"):
        shutil.copy(model_dir / "target.png", tmp_path / f"{name}.png")
        pictures.append(str(tmp_path / f"{name}.png"))
    out = tmp_path / "fits"
    command = [sys.executable, "-m", "matfit", "fit", *pictures, "-o", str(out), "--model", str(model_dir)]
    command += ["--no-verify", "--method", "hybrid", "--evals", "3000"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path)
    deadline = time.monotonic() + 120
    journal = out / batch.JOURNAL  # a picture is kept once the journal records it, just after its files are in place

    def recorded() -> bool:
        try:
            return "a.png" in journal.read_text()
        except OSError:
            return False

    while not recorded() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    process.kill()
    process.communicate()
    first = (out / "a.params.json").read_bytes()
    assert not (out / "c.params.json").exists(), "the command ended before it could be killed part way"
    again = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert again.returncode == 0, again.stderr
    assert f"{out / 'a.params.json'}: kept, fitted by an earlier run" in again.stderr
    assert "c.params.json: kept" not in again.stderr
    assert (out / "a.params.json").read_bytes() == first
    assert sorted(os.listdir(out)) == ["a.params.json", "b.params.json", "c.params.json"]
