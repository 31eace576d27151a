import importlib.util
import json
import logging
import os
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest

from matfit import params
from matfit.model import dataset, dataset_workers, dataset_writing
from matfit.model.dataset import DatasetError, Settings
from matfit.rendering import engine

VERSIONS = {"mitsuba": "test", "drjit": "test"}
# The Ray tests need the optional extra `.[cluster]`.
needs_ray = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="Ray is an optional extra: pip install -e '.[cluster]' to run the Ray tests",
)


@pytest.fixture(scope="module")
def settings(renderer):
    return Settings(resolution=16, spp=2, seed=3, variant=renderer.variant)


def make(path, settings, count, workers=0, progress=None, ray_address=None):
    data = dataset_writing.prepare(str(path), settings, count, VERSIONS)
    dataset_writing.render_missing(data, workers, progress, ray_address)
    return dataset.open_dataset(str(path))


def test_default_workers_are_one_per_core_on_the_cpu_and_a_constant_on_a_gpu(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 6)
    assert dataset_workers.default_workers("llvm_ad_rgb") == dataset_workers.default_workers("scalar_rgb") == 6
    assert dataset_workers.default_workers("cuda_ad_rgb") == dataset_workers.GPU_WORKERS
    monkeypatch.setattr(os, "cpu_count", lambda: 200)
    assert dataset_workers.default_workers("llvm_ad_rgb") == dataset_workers.MAX_WORKERS
    assert dataset_workers.default_workers("cuda_ad_rgb") == dataset_workers.GPU_WORKERS
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert dataset_workers.default_workers("scalar_rgb") == 1


def array_bytes(path):
    return {name: (path / name).read_bytes() for name in dataset.ARRAYS}


@pytest.fixture(scope="module")
def reference(tmp_path_factory, settings):
    """An uninterrupted 40-sample dataset, rendered once for every comparison below."""
    path = tmp_path_factory.mktemp("reference")
    make(path, settings, 40)
    return path


def test_layout_and_contents(reference, settings, renderer):
    data = dataset.open_dataset(str(reference))
    assert data.finished == data.count == 40
    assert data.params.shape == (40, 19) and data.params.dtype == np.float32
    assert data.images.shape == (40, 16, 16, 3) and data.images.dtype == np.float16
    np.testing.assert_allclose(data.params[7], params.from_unit(params.sample_index(3, 7)), rtol=1e-6)
    unit = data.unit_params()
    assert unit.min() >= 0 and unit.max() <= 1
    meta = json.loads((reference / "meta.json").read_text())
    assert meta["resolution"] == 16 and meta["spp"] == 2 and meta["seed"] == 3 and meta["variant"] == settings.variant
    assert params.describe_table_difference(meta["parameter_table"]) is None
    # the stored image is the renderer's image for that sample's parameters and seed
    again = engine.Renderer(16, 2, settings.variant).render(
        data.params[5].astype(np.float64), seed=dataset.image_seed(3, 5)
    )
    np.testing.assert_array_equal(data.images[5], again.astype(np.float16))
    # plain NumPy reads it without matfit
    np.testing.assert_array_equal(np.load(reference / "images.npy", mmap_mode="r")[3], data.images[3])


def test_interrupted_run_resumes_to_identical_bytes(tmp_path, reference, settings):
    def stop_after_18(done, total, rate):
        if done >= 18:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        make(tmp_path, settings, 40, progress=stop_after_18)
    partial = dataset.open_dataset(str(tmp_path))
    assert 18 <= partial.finished < 40
    make(tmp_path, settings, 40)
    assert array_bytes(tmp_path) == array_bytes(reference)


def test_growing_a_dataset_matches_rendering_it_whole(tmp_path, reference, settings):
    make(tmp_path, settings, 25)
    make(tmp_path, settings, 40)
    assert array_bytes(tmp_path) == array_bytes(reference)


def test_two_workers_give_the_same_bytes(tmp_path, reference, settings):
    make(tmp_path, settings, 40, workers=2)
    assert array_bytes(tmp_path) == array_bytes(reference)


def test_two_runs_of_one_command_give_byte_identical_folders(tmp_path):
    """Every file, the scene without its sphere included: each run a process of its own, as a user's two runs are."""
    folders = [tmp_path / "first", tmp_path / "second"]
    for folder in folders:
        command = ["render-dataset", str(folder), "--count", "4", "--resolution", "16", "--spp", "2", "--workers", "1"]
        subprocess.run([sys.executable, "-m", "matfit", *command], check=True, capture_output=True)

    def contents(folder):
        return {path.relative_to(folder): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}

    first, second = (contents(folder) for folder in folders)
    assert dataset.SCENE_FILE in {str(path) for path in first} and first.keys() == second.keys()
    assert [path for path in first if first[path] != second[path]] == []


# Eight chunks (`dataset_workers.CHUNK`): a run is stopped once its first chunk is written, with at most one chunk per
# worker (two) in flight, so several chunks are still left to resume.
LONG_COUNT = 8 * dataset_workers.CHUNK


@pytest.fixture(scope="module")
def long_reference(tmp_path_factory, settings):
    """A `LONG_COUNT`-sample dataset: long enough to be stopped part-way by a signal."""
    path = tmp_path_factory.mktemp("long")
    make(path, Settings(16, 8, 3, settings.variant), LONG_COUNT)
    return path


@pytest.mark.slow
@pytest.mark.parametrize(
    ("stop", "code", "first", "again"),
    [
        pytest.param(signal.SIGKILL, -signal.SIGKILL, [], [], id="SIGKILL"),
        pytest.param(signal.SIGINT, 130, [], [], id="SIGINT"),
        # The driver killed, and the local Ray it started with it; the same command resumes.
        pytest.param(
            signal.SIGKILL, -signal.SIGKILL, ["--ray", "local"], ["--ray", "local"], marks=needs_ray, id="ray-SIGKILL"
        ),
        # Ctrl-C of a Ray run; the local pool may finish what Ray started.
        pytest.param(signal.SIGINT, 130, ["--ray", "local"], [], marks=needs_ray, id="ray-SIGINT"),
    ],
)
def test_stopped_command_resumes_to_identical_bytes(tmp_path, long_reference, stop, code, first, again):
    """kill -9 or Ctrl-C: nothing finished is lost, and the same command completes the dataset."""
    target = tmp_path / "data"
    settings = ["--count", str(LONG_COUNT), "--resolution", "16", "--spp", "8", "--seed", "3", "--workers", "2"]
    command = [sys.executable, "-m", "matfit", "render-dataset", str(target), *settings]
    process = subprocess.Popen([*command, *first], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        done = target / "done.npy"
        if done.exists() and (target / "meta.json").exists() and np.load(done, mmap_mode="r").sum() >= 16:
            break
        time.sleep(0.01)
    workers = descendants(process.pid)
    process.send_signal(stop)
    error = process.communicate()[1]  # read to its end: until the workers, which share it, have closed it too
    assert process.returncode == code, error
    if not first:  # matfit's own workers (Ray's processes are Ray's)
        assert workers, "the command had no rendering process when it was stopped"
        assert not [pid for pid in workers if running(pid)], "a rendering process outlived the command"
        # Only progress lines (and the interruption's): no worker's traceback, no resource tracker's warning.
        assert all(line.startswith(("rendering ", "interrupted: ")) for line in error.splitlines()), error
    if stop == signal.SIGINT:
        assert "run the same command to resume" in error
    finished = int(np.load(target / "done.npy").sum())
    assert finished < LONG_COUNT, "the run finished before it could be stopped; the test needs a slower render"
    result = subprocess.run([*command, *again], capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr
    assert array_bytes(target) == array_bytes(long_reference)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"resolution": 32}, "rendered with resolution 16, not 32: pass --resolution 16"),
        ({"spp": 4}, "rendered with spp 2, not 4: pass --spp 2"),
        ({"seed": 4}, "rendered with seed 3, not 4: pass --seed 3"),
    ],
)
def test_other_settings_are_refused(reference, settings, change, message):
    other = Settings(**{**settings.__dict__, **change})
    with pytest.raises(DatasetError, match=message):
        dataset_writing.prepare(str(reference), other, 40, VERSIONS)


def test_a_dataset_records_its_sampler_and_refuses_another(tmp_path, reference, settings):
    assert json.loads((reference / "meta.json").read_text())["sampler"] == "uniform"
    media = Settings(**{**settings.__dict__, "sampler": "dense-media"})
    data = dataset_writing.prepare(str(tmp_path / "media"), media, 6, VERSIONS)
    assert data.meta["sampler"] == "dense-media"
    expected = np.stack([params.from_unit(params.sample_index(3, i, "dense-media")) for i in range(6)])
    np.testing.assert_allclose(data.params, expected, rtol=1e-6)
    with pytest.raises(DatasetError, match="drawn with sampler uniform, not dense-media: pass --sampler uniform"):
        dataset_writing.prepare(str(reference), media, 40, VERSIONS)
    with pytest.raises(DatasetError, match="sampler 'milk' is unknown: use uniform or dense-media"):
        dataset_writing.prepare(
            str(tmp_path / "other"), Settings(**{**settings.__dict__, "sampler": "milk"}), 6, VERSIONS
        )
    assert not (tmp_path / "other").exists()


def test_other_parameter_table_is_refused(tmp_path, reference):
    for name in ("meta.json", *dataset.ARRAYS):
        (tmp_path / name).write_bytes((reference / name).read_bytes())
    meta = json.loads((tmp_path / "meta.json").read_text())
    meta["parameter_table"]["parameters"][0]["high"] = 2.0
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"another parameter table .*base_color_r"):
        dataset.open_dataset(str(tmp_path))


def test_shrinking_and_bad_counts_are_refused(reference, settings, tmp_path):
    with pytest.raises(DatasetError, match="already holds 40 samples: pass --count 40 or more"):
        dataset_writing.prepare(str(reference), settings, 10, VERSIONS)
    with pytest.raises(DatasetError, match="count 0 is out of range"):
        dataset_writing.prepare(str(tmp_path / "new"), settings, 0, VERSIONS)
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"resolution": 4}, "resolution 4 is out of range"),
        ({"resolution": 100000}, "resolution 100000"),
        ({"spp": 0}, "spp 0 is out of range"),
    ],
)
def test_absurd_settings_are_refused(tmp_path, settings, change, message):
    with pytest.raises(DatasetError, match=message):
        dataset_writing.prepare(str(tmp_path / "new"), Settings(**{**settings.__dict__, **change}), 10, VERSIONS)
    assert not (tmp_path / "new").exists()


def test_bad_directories_are_refused(tmp_path, settings):
    (tmp_path / "file").write_text("x")
    with pytest.raises(DatasetError, match="is a file"):
        dataset_writing.prepare(str(tmp_path / "file"), settings, 10, VERSIONS)
    with pytest.raises(DatasetError, match="does not exist"):
        dataset_writing.prepare(str(tmp_path / "missing" / "data"), settings, 10, VERSIONS)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("x")
    with pytest.raises(DatasetError, match="not a matfit dataset"):
        dataset_writing.prepare(str(tmp_path / "other"), settings, 10, VERSIONS)
    with pytest.raises(DatasetError, match="read-only"):
        dataset_writing.prepare("/proc/matfit-data", settings, 10, VERSIONS)


def test_a_dataset_too_large_for_the_disk_is_refused_before_its_folder_is_made(tmp_path, settings):
    with pytest.raises(DatasetError, match="GiB are free: lower --count or --resolution"):
        dataset_writing.prepare(
            str(tmp_path / "huge"), Settings(1024, 1, 0, settings.variant), dataset.MAX_COUNT, VERSIONS
        )
    assert not (tmp_path / "huge").exists()


def test_sizes_in_the_disk_message_read_true_when_small():
    # A nearly full disk read "need 0.0 GiB, only 0.0 GiB are free".
    sizes = [3 * 2**30 // 2, 2**30, 2**30 - 1, 40 * 2**20 + 2**19, 2**20, 400 * 2**10, 0]
    shown = ["1.5 GiB", "1.0 GiB", "1024.0 MiB", "40.5 MiB", "1.0 MiB", "400.0 KiB", "0.0 KiB"]
    assert [dataset_writing.byte_size(size) for size in sizes] == shown


def test_a_nearly_full_disk_says_its_free_space_in_a_unit_that_shows_it(tmp_path, settings):
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(disk)], capture_output=True)
    if mounted.returncode:
        pytest.skip("a small file system to fill needs mount (root)")
    try:
        with pytest.raises(DatasetError) as raised:
            dataset_writing.prepare(str(disk / "data"), Settings(64, 1, 0, settings.variant), 100, VERSIONS)
        assert str(raised.value) == (
            "100 images at 64 px need 2.4 MiB, only 2.0 MiB are free: lower --count or --resolution"
        )
    finally:
        subprocess.run(["umount", str(disk)], check=True)


def test_corrupt_datasets_name_the_fix(tmp_path, reference):
    with pytest.raises(DatasetError, match=r"no meta\.json"):
        dataset.open_dataset(str(tmp_path))
    (tmp_path / "meta.json").write_text("{broken")
    with pytest.raises(DatasetError, match=r"meta\.json is not valid JSON \(.*\): delete .* and render the dataset"):
        dataset.open_dataset(str(tmp_path))
    for name in ("meta.json", *dataset.ARRAYS):
        (tmp_path / name).write_bytes((reference / name).read_bytes())
    os.truncate(tmp_path / "images.npy", 1000)
    with pytest.raises(DatasetError, match=r"images\.npy is missing or corrupt"):
        dataset.open_dataset(str(tmp_path))
    (tmp_path / "images.npy").write_bytes((reference / "images.npy").read_bytes())
    (tmp_path / "done.npy").unlink()
    os.mkfifo(tmp_path / "done.npy")  # opened by name, a FIFO that no one writes blocked the reader for ever
    with pytest.raises(DatasetError, match=r"done\.npy is missing or corrupt \(.*FIFO.*\)"):
        dataset.open_dataset(str(tmp_path))


@pytest.fixture(scope="module")
def local_ray():
    """A Ray of 2 CPUs in this process, which `render_missing(ray_address=...)` then uses."""
    import ray

    with warnings.catch_warnings():
        # Ray starts its processes with fork + exec; JAX, running in this test process, warns
        # about any fork (the child here executes another program at once).
        warnings.filterwarnings("ignore", "os.fork", RuntimeWarning)
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    yield ray
    ray.shutdown()


def descendants(pid):
    """Returns the ids of every process below `pid`, from /proc."""
    parents = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as file:
                    parents[int(entry)] = int(file.read().rsplit(")", 1)[1].split()[1])
            except OSError:
                continue
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def running(pid):
    """Whether process `pid` is alive (a zombie, dead but not yet reaped by whoever adopted it, is not)."""
    try:
        with open(f"/proc/{pid}/stat") as file:
            return file.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def command_line(pid):
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as file:
            return file.read()
    except OSError:
        return b""


@needs_ray
def test_ray_gives_the_same_bytes(tmp_path, reference, settings, local_ray):
    make(tmp_path, settings, 40, ray_address="local")
    assert array_bytes(tmp_path) == array_bytes(reference)


@needs_ray
def test_killed_ray_worker_loses_nothing(tmp_path, long_reference, settings, local_ray):
    """kill -9 of a Ray worker in the middle of a chunk: Ray renders the chunk again, same bytes."""
    killed = []

    def kill_a_busy_worker(done, total, rate):
        if done >= 32 and not killed:
            busy = [pid for pid in descendants(os.getpid()) if command_line(pid).startswith(b"ray::_render_task")]
            if busy:
                os.kill(busy[0], signal.SIGKILL)
                killed.append(busy[0])

    long_settings = Settings(16, 8, 3, settings.variant)
    data = dataset_writing.prepare(str(tmp_path), long_settings, LONG_COUNT, VERSIONS)
    try:
        dataset_writing.render_missing(data, 2, kill_a_busy_worker, ray_address="local")
    except DatasetError as error:
        assert "run the same command to resume" in str(error)
    assert killed, "no Ray worker was busy rendering when the test looked for one"
    dataset_writing.render_missing(dataset.open_dataset(str(tmp_path), writable=True), 2, ray_address="local")
    assert array_bytes(tmp_path) == array_bytes(long_reference)


@pytest.mark.parametrize(
    ("change", "shown"),
    [
        pytest.param({"count": "abc"}, "'count' is \"abc\", not a whole number from 1 to", id="count-text"),
        pytest.param({"count": None}, "'count' is missing", id="no-count"),
        pytest.param({"resolution": 16.5}, "'resolution' is 16.5, not a whole number from 8 to 1024", id="resolution"),
        pytest.param({"spp": True}, "'spp' is true, not a whole number", id="spp-bool"),
        pytest.param({"seed": -1}, "'seed' is -1, not a whole number from 0 to", id="seed"),
        pytest.param({"variant": 5}, "'variant' is 5, not one of cuda_ad_rgb, llvm_ad_rgb, scalar_rgb", id="variant"),
        pytest.param({"sampler": "milk"}, "'sampler' is \"milk\", not one of uniform", id="sampler"),
        pytest.param({"parameter_table": []}, "'parameter_table' is [], not a parameter table", id="table"),
    ],
)
def test_every_meta_field_is_checked_by_every_command(tmp_path, reference, change, shown):
    """render-dataset, train and evaluate refuse a damaged meta.json in one line naming the file, the field, the fix."""
    from typer.testing import CliRunner

    from matfit.app.cli import app

    for name in ("meta.json", *dataset.ARRAYS):
        (tmp_path / name).write_bytes((reference / name).read_bytes())
    meta = json.loads((tmp_path / "meta.json").read_text())
    meta.update(change)
    meta = {key: value for key, value in meta.items() if value is not None}
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    commands = [
        ["render-dataset", tmp_path, "--count", 40, "--resolution", 16, "--spp", 2, "--seed", 3],
        ["train", "--arch", "8", "--dataset", tmp_path, "--out", tmp_path / "model"],
        ["evaluate", "--references", tmp_path],
    ]
    for command in commands:
        result = CliRunner().invoke(app, [str(part) for part in command])
        assert result.exit_code == 2, result.output
        lines = result.output.splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: {tmp_path / 'meta.json'}: field {shown}"), lines
        assert lines[0].endswith(f": delete {tmp_path} and render it again with `matfit render-dataset`"), lines
    assert not (tmp_path / "model").exists()
