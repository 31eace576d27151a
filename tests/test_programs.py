import os
import pickle
import stat

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from matfit import files, programs
from matfit.errors import OutputError

TRACES = []


def scaled(x, y, factor):
    TRACES.append(factor)  # runs once per trace: the tests count traces with it
    return {"sum": factor * jnp.sum(x * y), "y": y}


@pytest.fixture
def store(tmp_path):
    """Returns a fresh store of programs, enabled for the test; the store is disabled again after it."""
    previous = programs._directory, programs._key
    programs.enable(str(tmp_path / "programs"))
    TRACES.clear()
    yield str(tmp_path / "programs")
    programs._directory, programs._key = previous


def arguments(n: int = 3):
    return np.arange(n, dtype=np.float32), np.full(n, 2.0, np.float32)


def test_a_new_process_reads_the_stored_program_back_instead_of_tracing(store):
    first = programs.jit(scaled, static_argnames=("factor",))
    out = first(*arguments(), factor=3.0)
    assert float(out["sum"]) == pytest.approx(3.0 * 2.0 * (0 + 1 + 2))
    traced = len(TRACES)
    assert traced >= 1 and len(programs.stored()) == 1
    again = programs.jit(scaled, static_argnames=("factor",))  # what a new process holds: nothing in memory
    out = again(*arguments(), factor=3.0)
    assert len(TRACES) == traced  # read back, not traced
    assert float(out["sum"]) == pytest.approx(18.0)
    np.testing.assert_array_equal(np.asarray(out["y"]), arguments()[1])
    assert again._cache_size() == 1


def slowly_scaled(x, y, factor):
    import time

    time.sleep(1.0)  # a long compilation: the other caller arrives while it runs
    return scaled(x, y, factor)


def test_a_program_another_caller_is_compiling_is_waited_for_and_read_back(store):
    import threading

    # Two Programs of one function are what two processes sharing the store hold (the page and `matfit fit`, the
    # suite's workers); each opens the lock file itself, as a second process would.
    holders = [programs.jit(slowly_scaled, static_argnames=("factor",)) for _ in range(2)]
    results = [None, None]

    def call(k: int) -> None:
        results[k] = holders[k](*arguments(), factor=2.0)

    threads = [threading.Thread(target=call, args=(k,)) for k in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(TRACES) == 1  # compiled once; the other read it back
    assert [float(r["sum"]) for r in results] == [12.0, 12.0]
    assert len(programs.stored()) == 1 and all(h._cache_size() == 1 for h in holders)


def test_new_statics_shapes_or_source_make_new_programs(store, monkeypatch):
    function = programs.jit(scaled, static_argnames=("factor",))
    function(*arguments(), factor=3.0)
    function(*arguments(), factor=5.0)
    function(*arguments(4), factor=5.0)
    assert len(programs.stored()) == 3
    traced = len(TRACES)
    monkeypatch.setattr(programs, "source_digest", lambda: "another matfit")
    out = programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
    assert len(TRACES) > traced and len(programs.stored()) == 4  # a changed matfit never reads a stale program
    assert float(out["sum"]) == pytest.approx(18.0)


def test_a_damaged_program_is_traced_again_and_rewritten(store):
    programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
    (name,) = programs.stored()
    with open(os.path.join(store, name), "wb") as file:
        file.write(b"not a program")
    traced = len(TRACES)
    out = programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
    assert float(out["sum"]) == pytest.approx(18.0) and len(TRACES) > traced
    assert os.path.getsize(os.path.join(store, name)) > 100
    TRACES.clear()
    programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
    assert TRACES == []


def test_transformations_and_unkeyable_statics_trace_as_jax_jit_does(store):
    function = programs.jit(scaled, static_argnames=("factor",))
    x, y = arguments()
    gradient = jax.grad(lambda x: function(x, y, factor=3.0)["sum"])(x)
    np.testing.assert_allclose(np.asarray(gradient), 3.0 * y)
    batched = jax.vmap(lambda x: function(x, y, factor=1.0)["sum"])(np.stack([x, 2 * x]))
    np.testing.assert_allclose(np.asarray(batched), [6.0, 12.0])
    assert programs.stored() == []  # under a transformation nothing is exported

    class Opaque:  # the default repr names an address: no key outlives the process
        def __mul__(self, other):
            return 4.0 * other

    out = function(x, y, factor=Opaque())
    assert float(out["sum"]) == pytest.approx(24.0) and programs.stored() == []


def test_without_a_store_it_is_jax_jit():
    previous = programs._directory, programs._key
    programs.disable()
    try:
        function = programs.jit(scaled, static_argnames=("factor",))
        assert float(function(*arguments(), factor=2.0)["sum"]) == pytest.approx(12.0)
        assert function._cache_size() == 1 and programs.stored() == []
        assert programs.remembered("value", 1, lambda: [1, 2]) == [1, 2]
    finally:
        programs._directory, programs._key = previous  # the store's state is both: a directory without its key fails


def test_remembered_values_are_computed_once_per_key(store):
    calls = []

    def compute():
        calls.append(1)
        return {"shape": (2, 3)}

    assert programs.remembered("shapes", {"kind": "a"}, compute) == {"shape": [2, 3]}
    assert programs.remembered("shapes", {"kind": "a"}, compute) == {"shape": [2, 3]}
    assert len(calls) == 1
    programs.remembered("shapes", {"kind": "b"}, compute)
    assert len(calls) == 2
    for name in programs.stored():
        with open(os.path.join(store, name), "w") as file:
            file.write("{damaged")
    assert programs.remembered("shapes", {"kind": "a"}, compute) == {"shape": [2, 3]} and len(calls) == 3


def test_a_full_disk_leaves_the_fit_working_and_nothing_stored(store, monkeypatch):
    def full(path, data):
        raise OutputError(f"cannot write {path}: No space left on device")

    monkeypatch.setattr(files, "write_bytes", full)
    monkeypatch.setattr(files, "write_text", full)
    out = programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
    assert float(out["sum"]) == pytest.approx(18.0) and programs.stored() == []
    assert programs.remembered("shapes", 1, lambda: [4]) == [4]


def entry(label: str, suffix: str = programs.SUFFIX) -> str:
    """Returns the name the store gives a program of function `label` (`_stored_path`)."""
    return f"matfit.{label}-{'0' * 32}{suffix}"


def test_prune_removes_the_least_recently_used_until_the_rest_fit(tmp_path):
    for age, label in enumerate(["newest", "middle", "oldest"]):
        path = tmp_path / entry(label)
        path.write_bytes(b"x" * 1000)
        os.utime(path, (1e9 - 100 * age, 1e9 - 100 * age))
    assert programs.prune(str(tmp_path), 2500) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == [entry("middle"), entry("newest")]
    programs.touch(str(tmp_path / entry("middle")))  # read back now: the newest use
    assert programs.prune(str(tmp_path), 1000) == 1
    assert [p.name for p in tmp_path.iterdir()] == [entry("middle")]
    assert programs.prune(str(tmp_path), 1000) == 0
    assert programs.prune(str(tmp_path / "absent"), 0) == 0  # no cache: nothing to do, no error


def test_prune_removes_the_lock_files_of_programs_gone_but_not_one_held(tmp_path):
    import fcntl

    program = tmp_path / entry("kept")
    program.write_bytes(b"x" * 100)
    for label in ("kept", "gone", "compiling"):
        (tmp_path / f"{entry(label)}{programs.LOCK}").touch()
    held = os.open(tmp_path / f"{entry('compiling')}{programs.LOCK}", os.O_RDWR)
    fcntl.flock(held, fcntl.LOCK_EX)  # another process compiling that program now
    try:
        assert programs.prune(str(tmp_path), 1000) == 1
    finally:
        os.close(held)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == [f"{entry('compiling')}{programs.LOCK}", program.name, f"{program.name}{programs.LOCK}"]
    assert programs.prune(str(tmp_path), 0) == 3  # the program by its size, then both locks, no longer held
    assert list(tmp_path.iterdir()) == []


def test_prune_removes_only_the_cache_s_own_files_and_never_through_a_link(tmp_path):
    elsewhere = tmp_path / "someone"
    elsewhere.mkdir()
    theirs = [entry("a"), entry("b", ".json"), f"{entry('c')}{programs.LOCK}", "notes.txt"]
    for name in theirs:
        (elsewhere / name).write_bytes(b"x" * 100)
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "notes.txt").write_bytes(b"x" * 100)  # not a name the store gives: not the cache's
    (cache / entry("linked")).symlink_to(elsewhere / entry("a"))  # a link, not a file the cache wrote
    os.mkfifo(cache / f"{entry('fifo')}{programs.LOCK}")  # not a regular file: left, and opening it blocks nothing
    (tmp_path / "link").symlink_to(elsewhere)
    assert programs.prune(str(tmp_path / "link"), 0) == 0  # the folder itself a link: not followed
    assert programs.prune(str(cache), 0) == 0
    assert sorted(p.name for p in elsewhere.iterdir()) == sorted(theirs)
    assert all((elsewhere / name).read_bytes() == b"x" * 100 for name in theirs)
    assert sorted(p.name for p in cache.iterdir()) == sorted(
        ["notes.txt", entry("linked"), f"{entry('fifo')}{programs.LOCK}"]
    )


def test_the_old_jax_cache_linked_elsewhere_costs_no_file_when_the_store_is_enabled(tmp_path, monkeypatch):
    # `ln -s <scratch>/v <cache>/matfit/jax`: the clean-up of the old folder followed the link and emptied <scratch>/v.
    scratch = tmp_path / "v"
    scratch.mkdir()
    jax_named = f"jit_f-{'0' * 64}-cache"
    for name in ("thesis.tex", jax_named, ".lockfile"):
        (scratch / name).write_text("keep me")
    (tmp_path / "cache" / "matfit").mkdir(parents=True)
    (tmp_path / "cache" / "matfit" / "jax").symlink_to(scratch)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(programs, "_directory", programs._directory)  # restored after the test, with its key
    monkeypatch.setattr(programs, "_key", programs._key)
    programs.enable_compilation_cache()
    assert sorted(p.name for p in scratch.iterdir()) == sorted(["thesis.tex", jax_named, ".lockfile"])
    assert (tmp_path / "cache" / "matfit" / "jax").is_symlink()


def test_a_program_read_back_counts_as_used(store, tmp_path):
    programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
    (path,) = [os.path.join(store, name) for name in programs.stored()]
    os.utime(path, (1e9, 1e9))
    programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)  # a new process reads it back
    assert TRACES == [3.0] and os.path.getmtime(path) > 1e9


def test_with_jax_s_persistent_cache_on_nothing_is_stored(store, tmp_path, monkeypatch):
    # An executable XLA read from JAX's cache fails after being stored again: the store stays out of the way.
    monkeypatch.setattr(programs, "jax_cache_enabled", lambda: True)
    out = programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
    assert float(out["sum"]) == pytest.approx(18.0) and programs.stored() == []


def test_the_key_names_the_processor_and_the_devices():
    described = repr(programs.environment())
    assert programs.processor() in described and len(programs.processor()) == 16
    assert str(len(jax.devices())) in described


def test_a_stored_executable_file_holds_its_trees_and_refuses_damage():
    in_tree = jax.tree_util.tree_structure(((1, {"a": 2, "b": (3, 4)}), {}))
    out_tree = jax.tree_util.tree_structure({"sum": 0, "y": 0})
    data = programs.pack(b"machine code", in_tree, out_tree)
    assert data.startswith(programs.MAGIC)
    payload, arguments, results = programs.unpack(data)
    assert (payload, arguments, results) == (b"machine code", in_tree, out_tree)
    for damaged in (data[:-1], data + b"x", b"not a program", data[: len(programs.MAGIC) + 4]):
        with pytest.raises(ValueError):
            programs.unpack(damaged)


def test_the_source_digest_covers_modules_in_subpackages(tmp_path):
    (tmp_path / "fit").mkdir()
    (tmp_path / "errors.py").write_text("A = 1\n")
    (tmp_path / "fit" / "search.py").write_text("B = 2\n")
    (tmp_path / "fit" / "notes.txt").write_text("not source")
    first = programs.tree_digest(str(tmp_path))
    (tmp_path / "fit" / "notes.txt").write_text("other notes")
    assert programs.tree_digest(str(tmp_path)) == first  # only Python source keys the programs
    (tmp_path / "fit" / "search.py").write_text("B = 3\n")
    assert programs.tree_digest(str(tmp_path)) != first  # an edit in a subpackage makes new programs
    (tmp_path / "fit" / "search.py").write_text("B = 2\n")
    assert programs.tree_digest(str(tmp_path)) == first
    (tmp_path / "fit" / "search.py").rename(tmp_path / "fit" / "other.py")
    assert programs.tree_digest(str(tmp_path)) != first  # a moved module too
    package = os.path.dirname(os.path.abspath(programs.__file__))
    assert programs.source_digest() == programs.tree_digest(package)


class Planted:
    """What a planted pickle does when it is loaded: creates the file `marker`."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return open, (self.marker, "w")


def test_a_planted_pickle_is_never_loaded_and_the_program_is_compiled_again(store, tmp_path):
    programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
    (name,) = programs.stored()
    marker = tmp_path / "planted-code-ran"
    trees = jax.tree_util.tree_structure(((0, 0), {})), jax.tree_util.tree_structure({"sum": 0, "y": 0})
    planted = programs.pack(pickle.dumps(Planted(str(marker))), *trees)
    for data in (planted, bytes(32) + planted, os.urandom(32) + planted):  # bare, or behind a made-up HMAC
        with open(os.path.join(store, name), "wb") as file:
            file.write(data)
        traced = len(TRACES)
        out = programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
        assert not marker.exists()
        assert float(out["sum"]) == pytest.approx(18.0) and len(TRACES) > traced  # compiled again, not loaded
    TRACES.clear()  # the rewritten entry is authentic: read back without tracing
    assert float(programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)["sum"]) == 18.0
    assert TRACES == []


def test_a_fifo_planted_where_a_program_is_stored_is_ignored_with_a_notice(store, capsys):
    # Opening it blocked `matfit fit` for ever: nothing writes to it.
    programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
    programs.remembered("answer", (1,), lambda: {"value": 1})
    planted = [os.path.join(store, name) for name in programs.stored()]
    for path in planted:
        os.unlink(path)
        os.mkfifo(path)
    TRACES.clear()
    assert float(programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)["sum"]) == 18.0
    assert programs.remembered("answer", (1,), lambda: {"value": 2}) == {"value": 2}
    assert TRACES == [3.0]  # compiled again, and stored over the FIFO
    notices = sorted(capsys.readouterr().err.splitlines())
    assert notices == sorted(
        f"notice: ignored {path} in the compiled-program store: it is a FIFO (named pipe), not a regular file"
        for path in planted
    )
    assert all(stat.S_ISREG(os.stat(path).st_mode) for path in planted)


def test_a_remembered_value_is_read_only_when_authentic(store):
    assert programs.remembered("answer", (1,), lambda: {"value": 1}) == {"value": 1}
    (name,) = programs.stored()
    with open(os.path.join(store, name), "w") as file:
        file.write('{"value": 666}')
    assert programs.remembered("answer", (1,), lambda: {"value": 2}) == {"value": 2}
    assert programs.remembered("answer", (1,), lambda: {"value": 3}) == {"value": 2}  # the rewritten one


def test_the_key_is_private_and_a_store_others_can_write_is_not_used(tmp_path):
    previous = programs._directory, programs._key
    try:
        programs.enable(str(tmp_path / "private"))
        key = tmp_path / "programs.key"
        assert stat.S_IMODE(key.stat().st_mode) == 0o600 and key.stat().st_size == 32
        assert stat.S_IMODE((tmp_path / "private").stat().st_mode) & 0o077 == 0
        shared = tmp_path / "shared"
        shared.mkdir()
        shared.chmod(0o777)
        with pytest.raises(OutputError, match=f"{shared} can be written by others: chmod 700"):
            programs.enable(str(shared))
        assert programs._directory is None and programs.stored() == []
        programs.jit(scaled, static_argnames=("factor",))(*arguments(), factor=3.0)
        assert os.listdir(shared) == []  # nothing stored there, so nothing is ever read from there
        key.chmod(0o644)
        with pytest.raises(OutputError, match=r"key .* can be read by others"):
            programs.enable(str(tmp_path / "private"))
    finally:
        programs._directory, programs._key = previous


def test_the_program_store_is_pruned_to_its_cap_and_the_old_jax_cache_removed_when_enabled(tmp_path, monkeypatch):
    old = tmp_path / "matfit" / "jax"  # what earlier versions kept in JAX's own cache: removed, and its folder
    old.mkdir(parents=True)
    for name in (f"jit_f-{'0' * 64}-cache", f"jit_f-{'0' * 64}-atime", f"jit_g-{'1' * 64}", ".lockfile"):
        (old / name).write_bytes(b"x")
    store = tmp_path / "matfit" / "programs"
    store.mkdir(mode=0o700)
    for age, label in enumerate(["newer", "older"]):
        with open(store / entry(label), "wb") as file:  # sparse: its size counts, no disk is written
            file.truncate(programs.CACHE_BYTES["programs"] // 2 + 1)
        os.utime(store / entry(label), (1e9 - 100 * age, 1e9 - 100 * age))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(programs, "_directory", programs._directory)  # restored after the test, with its key
    monkeypatch.setattr(programs, "_key", programs._key)
    programs.enable_compilation_cache()
    assert not old.exists()
    assert [p.name for p in store.iterdir()] == [entry("newer")]  # the store pruned to its cap
    assert programs._directory == str(tmp_path / "matfit" / "programs")
    assert not programs.jax_cache_enabled()  # JAX's persistent cache stays off
