import io
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from matfit import images, params
from matfit.rendering import engine, presets, process, scene
from matfit.rendering.engine import RenderError


def srgb(renderer, seed=0, **values):
    return images.srgb_encode(renderer.render(params.from_mapping(values), seed=seed))


def sphere_mask(renderer):
    black = srgb(renderer, base_color_r=0, base_color_g=0, base_color_b=0, roughness=1, specular=0)
    white = srgb(renderer, base_color_r=1, base_color_g=1, base_color_b=1, roughness=1, specular=0)
    return (white - black).mean(axis=2) > 0.3


def test_images_are_linear_float_of_the_requested_size(renderer):
    image = renderer.render(params.DEFAULTS)
    assert image.dtype == np.float32 and image.shape == (16, 16, 3)
    assert np.all(np.isfinite(image)) and image.min() >= 0.0


def test_the_sphere_covers_the_centre_of_the_frame(renderer):
    mask = sphere_mask(renderer)
    assert 0.25 < mask.mean() < 0.6
    assert mask[8, 8] and not mask[0, 0] and not mask[15, 15]


def test_red_base_colour_is_redder_than_blue(renderer):
    mask = sphere_mask(renderer)
    red = srgb(renderer, base_color_r=0.8, base_color_g=0.05, base_color_b=0.05)[mask].mean(axis=0)
    blue = srgb(renderer, base_color_r=0.05, base_color_g=0.05, base_color_b=0.8)[mask].mean(axis=0)
    assert red[0] > red[2] + 0.25
    assert blue[2] > blue[0] + 0.25


def test_metal_differs_from_diffuse(renderer):
    diffuse = srgb(renderer, base_color_r=0.9, base_color_g=0.6, base_color_b=0.2, roughness=0.7)
    metal = srgb(renderer, base_color_r=0.9, base_color_g=0.6, base_color_b=0.2, roughness=0.1, metallic=1.0)
    assert images.rmse(diffuse, metal) > 15.0


def test_glass_shows_the_checker_through_the_object(renderer):
    """Darkening the checkers' light squares changes a glass sphere a lot and an opaque one little."""
    mask = sphere_mask(renderer)
    keys = ("floor.bsdf.reflectance.color1.value", "backdrop.bsdf.reflectance.color1.value")
    glass = params.from_mapping(
        {"roughness": 0.0, "spec_trans": 1.0, "base_color_r": 1, "base_color_g": 1, "base_color_b": 1}
    )
    opaque = params.from_mapping({"roughness": 0.6, "base_color_r": 0.8, "base_color_g": 0.8, "base_color_b": 0.8})
    before = {key: renderer.mi.Color3f(renderer.parameters[key]) for key in keys}  # a copy: the scene updates in place
    lit = [images.srgb_encode(renderer.render(v)) for v in (glass, opaque)]
    try:
        for key in keys:
            renderer.parameters[key] = renderer.mi.Color3f(0.0, 0.0, 0.0)
        dark = [images.srgb_encode(renderer.render(v)) for v in (glass, opaque)]
    finally:
        for key, value in before.items():
            renderer.parameters[key] = value
        renderer.parameters.update()
    weights = mask.astype(np.float32)
    glass_change = images.rmse(lit[0], dark[0], weights)
    opaque_change = images.rmse(lit[1], dark[1], weights)
    assert glass_change > 40.0
    assert glass_change > 2.5 * opaque_change


def test_interior_medium_colours_transmissive_spheres_only(renderer):
    mask = sphere_mask(renderer)
    glass = {"roughness": 0.0, "spec_trans": 1.0, "base_color_r": 1, "base_color_g": 1, "base_color_b": 1}
    amber = {"medium_color_r": 0.9, "medium_color_g": 0.3, "medium_color_b": 0.05, "density": 1.0}
    clear = srgb(renderer, **glass)[mask].mean(axis=0)
    tinted = srgb(renderer, **glass, **amber)[mask].mean(axis=0)
    assert clear[0] - clear[2] < 0.05
    assert tinted[0] - tinted[2] > 0.15
    opaque = {"roughness": 0.5, "base_color_r": 0.5, "base_color_g": 0.5, "base_color_b": 0.5}
    assert images.rmse(srgb(renderer, **opaque), srgb(renderer, **opaque, **amber)) < 1e-3


def test_scattering_medium_turns_glass_milky(renderer):
    mask = sphere_mask(renderer)
    glass = {"roughness": 0.0, "spec_trans": 1.0, "base_color_r": 1, "base_color_g": 1, "base_color_b": 1}
    grey = {"medium_color_r": 0.3, "medium_color_g": 0.3, "medium_color_b": 0.3, "density": 3.0}
    smoky = srgb(renderer, **glass, **grey, scattering=0.0)[mask].mean()
    milky = srgb(renderer, **glass, **grey, scattering=1.0)[mask].mean()
    assert milky > smoky + 0.2


def test_renders_are_reproducible_whatever_came_before(renderer):
    a = params.from_unit(params.sample_index(0, 1))
    b = params.from_unit(params.sample_index(0, 2))
    first = renderer.render(a, seed=5)
    renderer.render(b, seed=9)
    # the same picture up to the last bit, which Dr.Jit's threads may add in another order (README)
    np.testing.assert_allclose(renderer.render(a, seed=5), first, rtol=0, atol=1e-5)
    assert not np.allclose(renderer.render(a, seed=6), first, rtol=0, atol=1e-3)


def test_rejects_malformed_materials(renderer):
    with pytest.raises(RenderError, match="19 finite values"):
        renderer.render(np.zeros(5))
    bad = params.DEFAULTS.copy()
    bad[0] = np.nan
    with pytest.raises(RenderError, match="19 finite values"):
        renderer.render(bad)


@pytest.mark.parametrize(
    ("name", "major"),
    [
        ("libLLVM-19.so", 19),
        ("libLLVM.so.19.1", 19),
        ("libLLVM-15.so.1", 15),
        ("libLLVM.so.20.1", 20),
        ("libLLVM.so", None),
    ],
)
def test_llvm_version_is_read_from_the_file_name(name, major):
    assert engine.llvm_major(f"/usr/lib/x86_64-linux-gnu/{name}") == major


# What `decide_variant` gives for every request and every finding (GPU usable by Mitsuba, libLLVM >= 19):
# a variant, or the start of the one-line refusal.
CHOICES = {
    (None, True, True): "cuda_ad_rgb",
    (None, True, False): "cuda_ad_rgb",
    (None, False, True): "llvm_ad_rgb",
    (None, False, False): "scalar_rgb",
    ("cuda_ad_rgb", True, True): "cuda_ad_rgb",
    ("cuda_ad_rgb", True, False): "cuda_ad_rgb",
    ("cuda_ad_rgb", False, True): "variant cuda_ad_rgb is not usable here (no GPU): use --variant llvm_ad_rgb or "
    "--variant scalar_rgb, or leave --variant out",
    ("cuda_ad_rgb", False, False): "variant cuda_ad_rgb is not usable here (no GPU): use --variant scalar_rgb, or "
    "leave --variant out",
    ("llvm_ad_rgb", True, True): "llvm_ad_rgb",
    ("llvm_ad_rgb", True, False): "variant llvm_ad_rgb needs libLLVM >= 19",
    ("llvm_ad_rgb", False, True): "llvm_ad_rgb",
    ("llvm_ad_rgb", False, False): "variant llvm_ad_rgb needs libLLVM >= 19",
    ("scalar_rgb", True, True): "scalar_rgb",
    ("scalar_rgb", True, False): "scalar_rgb",
    ("scalar_rgb", False, True): "scalar_rgb",
    ("scalar_rgb", False, False): "scalar_rgb",
    ("cuda_rgb", True, True): "unknown variant 'cuda_rgb': use one of cuda_ad_rgb, llvm_ad_rgb, scalar_rgb",
    ("cuda_rgb", True, False): "unknown variant 'cuda_rgb': use one of cuda_ad_rgb, llvm_ad_rgb, scalar_rgb",
    ("cuda_rgb", False, True): "unknown variant 'cuda_rgb': use one of cuda_ad_rgb, llvm_ad_rgb, scalar_rgb",
    ("cuda_rgb", False, False): "unknown variant 'cuda_rgb': use one of cuda_ad_rgb, llvm_ad_rgb, scalar_rgb",
}


@pytest.mark.parametrize(("requested", "cuda", "llvm"), list(CHOICES))
def test_the_variant_is_decided_by_what_was_found(requested, cuda, llvm):
    expected = CHOICES[requested, cuda, llvm]
    if expected not in engine.VARIANTS:
        with pytest.raises(RenderError) as refused:
            engine.decide_variant(requested, cuda, llvm, why_not_cuda="no GPU")
        assert str(refused.value).startswith(expected)
        return
    variant, notice = engine.decide_variant(requested, cuda, llvm)
    assert variant == expected
    # only the fallback nobody asked for says why
    assert (notice is not None) == (requested is None and variant == "scalar_rgb")


ELF_SHARED_OBJECT = b"\x7fELF\x02\x01\x01" + bytes(9) + (3).to_bytes(2, "little") + bytes(46)  # a 64-bit .so's header


def test_variant_choice_on_a_machine_without_a_gpu(monkeypatch, tmp_path):
    library = tmp_path / "libLLVM-19.so"
    library.write_bytes(ELF_SHARED_OBJECT)
    monkeypatch.setattr(engine, "cuda_devices", lambda: 0)
    assert engine.choose_variant("scalar_rgb") == ("scalar_rgb", None)
    with pytest.raises(RenderError, match="use one of cuda_ad_rgb, llvm_ad_rgb, scalar_rgb"):
        engine.choose_variant("cuda_rgb")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "")  # unset, as far as Dr.Jit is concerned; restored afterwards
    monkeypatch.setattr(engine, "find_libllvm", lambda: str(library))
    assert engine.choose_variant(None) == ("llvm_ad_rgb", None)
    assert os.environ["DRJIT_LIBLLVM_PATH"] == str(library)
    with pytest.raises(RenderError, match=r"no NVIDIA GPU answers libcuda.so.1\): use --variant llvm_ad_rgb or"):
        engine.check_request("cuda_ad_rgb")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "")
    monkeypatch.setattr(engine, "find_libllvm", lambda: None)
    variant, notice = engine.choose_variant(None)
    assert variant == "scalar_rgb" and "scalar_rgb" in notice
    with pytest.raises(RenderError, match="--variant scalar_rgb"):
        engine.choose_variant("llvm_ad_rgb")
    with pytest.raises(RenderError, match=r"use --variant scalar_rgb, or leave --variant out"):
        engine.choose_variant("cuda_ad_rgb")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "/nonexistent/libLLVM.so")
    with pytest.raises(RenderError, match="does not exist"):
        engine.choose_variant(None)


def test_a_libllvm_path_that_names_no_library_is_ignored_with_a_notice(monkeypatch, tmp_path):
    text, executable = tmp_path / "notes.txt", tmp_path / "libLLVM-19.so"
    text.write_text("not a library")
    executable.write_bytes(ELF_SHARED_OBJECT[:16] + (2).to_bytes(2, "little") + ELF_SHARED_OBJECT[18:])  # ET_EXEC
    assert engine.not_a_library(str(text)) == "it is no shared library"
    assert engine.not_a_library(str(executable)) == "it is an ELF file but no shared library"
    assert engine.not_a_library(str(tmp_path / "libLLVM-19.so")) is not None
    monkeypatch.setattr(engine, "cuda_devices", lambda: 0)
    monkeypatch.setattr(engine, "find_libllvm", lambda: None)
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(text))
    variant, notice = engine.choose_variant(None)  # as without it: scalar_rgb here, saying why
    assert variant == "scalar_rgb" and notice.startswith(f"notice: DRJIT_LIBLLVM_PATH={text} is not a libLLVM (")
    assert "scalar_rgb" in notice and "DRJIT_LIBLLVM_PATH" not in os.environ  # Dr.Jit no longer reads it
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(text))
    with pytest.raises(RenderError, match=r"is not a libLLVM .*; variant llvm_ad_rgb needs libLLVM >= 19"):
        engine.choose_variant("llvm_ad_rgb")
    # the command line, in a process of its own: a notice and the render, not Mitsuba's ImportError
    out = tmp_path / "gold.png"
    command = [sys.executable, "-m", "matfit", "render", "--preset", "gold", "--size", "16", "--spp", "4", "-o", out]
    environment = {**os.environ, "DRJIT_LIBLLVM_PATH": str(text)}
    done = subprocess.run(command, env=environment, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert f"notice: DRJIT_LIBLLVM_PATH={text} is not a libLLVM" in done.stderr and "Traceback" not in done.stderr
    assert images.read(str(out)).shape == (16, 16, 3)


def test_a_gpu_is_looked_for_only_when_the_choice_needs_it(monkeypatch, renderer):
    def no_look(*_):
        raise AssertionError("looked for a GPU")

    monkeypatch.setattr(engine, "cuda_devices", no_look)
    assert engine.choose_variant("scalar_rgb")[0] == "scalar_rgb"
    if renderer.variant == "llvm_ad_rgb":
        assert engine.choose_variant("llvm_ad_rgb")[0] == "llvm_ad_rgb"
    engine.check_request(None)
    # a GPU the driver reports, in a process whose Mitsuba already renders with another variant, is not taken
    monkeypatch.setattr(engine, "cuda_devices", lambda: 1)
    assert engine.cuda_problem() == f"this process already renders with {renderer.variant}"
    assert engine.choose_variant(None)[0] == renderer.variant


def test_a_background_renderer_renders_what_one_loaded_in_front_does_and_answers_prefetches(renderer):
    background = process.Background(renderer.resolution, renderer.spp)
    material = params.from_unit(params.sample_index(0, 3))
    other = params.from_unit(params.sample_index(0, 4))
    background.prefetch(material, seed=4)
    loaded = background.renderer()
    assert isinstance(loaded, engine.Renderer) and loaded.variant == renderer.variant
    expected = renderer.render(material, seed=4)
    np.testing.assert_allclose(background.render(material, seed=4), expected, atol=1e-5)
    # the prefetched picture is answered, not rendered again: the scene now holds nothing of it
    loaded.render(other, seed=1)
    np.testing.assert_allclose(background.render(material, seed=4), expected, atol=1e-5)
    # anything not prefetched is rendered now, with its own seed and spp
    np.testing.assert_allclose(
        background.render(other, seed=2, spp=8), renderer.render(other, seed=2, spp=8), atol=1e-5
    )
    assert not np.allclose(background.render(material, seed=5), expected, atol=1e-3)


def test_a_renderer_that_fails_in_the_background_raises_for_whoever_waits():
    background = process.Background(16, 4, "no_such_variant")
    background.prefetch(params.DEFAULTS, seed=1)
    with pytest.raises(RenderError, match="unknown variant 'no_such_variant'"):
        background.renderer()
    with pytest.raises(RenderError, match="unknown variant 'no_such_variant'"):
        background.render(params.DEFAULTS, seed=1)


def test_a_render_process_renders_what_one_in_this_process_does_and_answers_prefetches(renderer):
    material = params.from_unit(params.sample_index(0, 3))
    other = params.from_unit(params.sample_index(0, 4))
    with process.Process() as child:
        assert child.variant == renderer.variant and child.renderer() is child
        with pytest.raises(RenderError, match="load"):
            child.render(material, seed=4)
        child.load(renderer.resolution, renderer.spp)
        child.prefetch(material, seed=4)
        child.prefetch(other, seed=2, spp=8)
        expected = renderer.render(material, seed=4)
        np.testing.assert_allclose(child.render(material, seed=4), expected, atol=1e-5)
        np.testing.assert_allclose(child.render(other, seed=2, spp=8), renderer.render(other, seed=2, spp=8), atol=1e-5)
        assert not np.allclose(child.render(material, seed=5), expected, atol=1e-3)
        bad = params.DEFAULTS.copy()
        bad[0] = np.nan
        with pytest.raises(RenderError, match="19 finite values"):  # the child's error, raised here
            child.render(bad)
        assert child.render(material, seed=4).shape == (renderer.resolution,) * 2 + (3,)  # it goes on
    assert child._child.wait(timeout=10) == 0  # it ends by itself once its requests do


def test_two_render_processes_render_a_material_to_the_same_bits():
    # several Dr.Jit threads add their samples into the film in no fixed order: the renders that decide use one
    material = presets.preset("jade")
    pictures = []
    for _ in range(2):
        with process.Process() as child:
            child.load(64, 64)  # verification's renders
            pictures.append(child.render(material, seed=7))
    np.testing.assert_array_equal(pictures[0], pictures[1])


def test_a_render_pool_renders_each_picture_to_the_bits_of_one_child_whatever_the_number_of_children():
    # the renders that decide run on every core, one render a child, and the answer does not depend on how many
    materials = [presets.preset("jade"), presets.preset("gold"), params.from_unit(params.sample_index(0, 3))]
    requests = [(material, seed) for material in materials for seed in (7, 8)]
    with process.Process() as child:
        child.load(32, 16)
        expected = [child.render(material, seed=seed) for material, seed in requests]
    for count in (1, 2, 3):
        with process.Pool(children=count) as pool:
            assert pool.children == count and pool.renderer() is pool
            pool.load(32, 16)
            deadline = time.monotonic() + 120
            while any(each.outstanding() for each in pool._children) and time.monotonic() < deadline:
                time.sleep(0.01)  # the scenes loaded: a load still in hand would count as work
            for material, seed in requests:
                pool.prefetch(material, seed)
            shares = [sum(owner is each for owner in pool._owners.values()) for each in pool._children]
            assert max(shares) - min(shares) <= 1 and sum(shares) == len(requests)  # the renders shared out
            for (material, seed), picture in zip(requests, expected, strict=True):
                np.testing.assert_array_equal(pool.render(material, seed=seed), picture)
            np.testing.assert_array_equal(pool.render(*requests[0]), expected[0])  # read once, rendered again


def test_a_render_pool_sends_a_request_to_a_child_that_finished_though_its_picture_was_not_read_yet():
    # A finished render waits in its pipe until `render` asks for it: that child is idle, and gets the next request,
    # not the one still rendering.
    material = presets.preset("jade")
    with process.Pool(children=2) as pool:
        pool.load(16, 4)
        first, second = pool._children
        deadline = time.monotonic() + 120
        while (first.outstanding() or second.outstanding()) and time.monotonic() < deadline:
            time.sleep(0.01)  # both scenes loaded: otherwise a load still in hand counts as work and may decide
        assert (first.outstanding(), second.outstanding()) == (0, 0)
        pool.prefetch(material, seed=1, spp=4000)  # about a second of work for the first child
        pool.prefetch(material, seed=2, spp=1)  # a moment's for the second
        deadline = time.monotonic() + 60
        while second.outstanding() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert second.outstanding() == 0 and first.outstanding() == 1  # its picture arrived, unread; the first renders
        pool.prefetch(material, seed=3, spp=1)
        assert (first.outstanding(), second.outstanding()) == (1, 1)
        assert pool.render(material, seed=2, spp=1).shape == (16, 16, 3)  # read from what arrived


def test_a_render_pool_needs_a_child_and_has_one_a_core_or_one_for_a_gpu(monkeypatch):
    with pytest.raises(ValueError, match="at least one child"):
        process.Pool(children=0)
    monkeypatch.setattr(process, "cores", lambda: 3)
    with process.Pool("scalar_rgb") as pool:
        assert pool.children == 3
    monkeypatch.setattr(process, "cuda_devices", lambda: 1)  # the GPU takes every render: one child, one CUDA context
    for variant in (None, engine.CUDA_VARIANT):
        with process.Pool(variant) as pool:
            assert pool.children == 1
    with process.Pool(engine.LLVM_VARIANT) as pool:
        assert pool.children == 3


def test_a_render_process_that_cannot_start_raises_its_reason():
    with process.Process("no_such_variant") as child:
        child.load(16, 4)
        for _ in range(2):  # the reason, every time it is asked, not a pipe's end
            with pytest.raises(RenderError, match="unknown variant 'no_such_variant'"):
                child.render(params.DEFAULTS, seed=1)
        with pytest.raises(RenderError, match="unknown variant 'no_such_variant'"):
            child.renderer()
    assert child._child.wait(timeout=10) == 0


def running(pid: int) -> bool:
    """Returns whether a process exists and has not ended (a zombie waiting for its parent has ended)."""
    try:
        with open(f"/proc/{pid}/stat") as file:
            return file.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_a_child_that_cannot_start_leaves_no_pipe_open(monkeypatch):
    # Both the fit's render process and a dataset's workers start through `start_child`: a failed start closes all
    # four pipe ends, so a caller that retries does not run out of file descriptors.
    before = sorted(os.listdir("/proc/self/fd"))
    monkeypatch.setattr(sys, "executable", "/nonexistent/python")
    with pytest.raises(FileNotFoundError):
        process.Process()
    with pytest.raises(FileNotFoundError):
        process.start_child("matfit.model.dataset_workers", "serve_chunks", 16, 1, "scalar_rgb")
    assert sorted(os.listdir("/proc/self/fd")) == before


def test_a_started_child_runs_the_named_function_with_its_pipes_and_arguments():
    child, requests, replies = process.start_child("matfit.rendering.process", "serve_requests", "no_such_variant")
    header, array = process.read_message(replies)
    requests.close()
    replies.close()
    assert child.wait(timeout=60) == 0
    assert array is None and "no_such_variant" in header["failed"]


def test_a_render_process_ends_with_its_caller_even_a_killed_one():
    script = (
        "import time\n"
        "from matfit import params; from matfit.rendering import process\n"
        "child = process.Process()\n"
        "child.load(16, 4)\n"
        "child.render(params.DEFAULTS, seed=1)\n"
        "print(child._child.pid, flush=True)\n"
        "time.sleep(60)\n"
    )
    caller = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    pid = int(caller.stdout.readline())
    assert running(pid)
    caller.send_signal(signal.SIGKILL)
    caller.wait()
    caller.stdout.close()
    deadline = time.monotonic() + 10
    while running(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    if running(pid):
        os.kill(pid, signal.SIGKILL)
        pytest.fail("the render process outlived its killed caller")


def test_render_process_messages_round_trip_and_a_cut_one_is_the_pipes_end():
    image = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    pipe = io.BytesIO()
    process.write_message(pipe, {"done": True}, image)
    process.write_message(pipe, {"error": "a material is 19 finite values"})
    whole = pipe.getvalue()
    pipe.seek(0)
    header, array = process.read_message(pipe)
    assert header["done"] is True and array.dtype == np.float32
    np.testing.assert_array_equal(array, image)
    array[0, 0, 0] = -1  # the caller's own copy
    assert process.read_message(pipe) == ({"error": "a material is 19 finite values"}, None)
    with pytest.raises(EOFError, match="ended"):
        process.read_message(pipe)
    for cut in (3, 12, len(whole) // 2):
        with pytest.raises(EOFError, match="inside a message"):
            process.read_message(io.BytesIO(whole[:cut]))


def test_a_message_that_does_not_come_whole_by_its_deadline_is_a_timeout():
    # A render process stopped (SIGSTOP) or stuck: its reply was waited for for ever.
    pipe = io.BytesIO()
    process.write_message(pipe, {"done": True}, np.zeros((2, 2, 3), np.float32))
    whole = pipe.getvalue()
    for sent, said in ((b"", "no message came in time"), (whole[:5], "part-way"), (whole[:-1], "part-way")):
        read, write = os.pipe()
        with os.fdopen(read, "rb", buffering=0) as replies, os.fdopen(write, "wb") as requests:
            requests.write(sent)
            requests.flush()
            started = time.monotonic()
            with pytest.raises(TimeoutError, match=said):
                process.read_message(replies, started + 0.2)
            assert 0.2 <= time.monotonic() - started < 5
    read, write = os.pipe()
    with os.fdopen(read, "rb", buffering=0) as replies, os.fdopen(write, "wb") as requests:
        requests.write(whole)
        requests.flush()
        assert process.read_message(replies, time.monotonic() + 5)[0]["done"] is True  # in time


def test_a_render_process_that_ended_is_said_with_its_exit_code_or_signal():
    assert process.ending(3) == "exit code 3"
    assert process.ending(-signal.SIGKILL) == "killed by signal 9 (SIGKILL)"
    assert process.ending(-signal.SIGSEGV) == "killed by signal 11 (SIGSEGV)"
    # a reply is given what its render may take: START_SECONDS, and SAMPLE_SECONDS a pixel sample
    assert process.reply_seconds(64, 64) == pytest.approx(process.START_SECONDS + 64 * 64 * 64 * process.SAMPLE_SECONDS)


def test_a_render_process_whose_caller_left_ends_without_a_word():
    # The caller's end of the replies is closed before the child's first message (Ctrl-C or kill -9 while it starts).
    requests_read, requests_write = os.pipe()
    replies_read, replies_write = os.pipe()
    code = (
        f"from matfit.rendering import process; process.serve_requests({requests_read}, {replies_write}, 'scalar_rgb')"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", code], pass_fds=(requests_read, replies_write), stderr=subprocess.PIPE, text=True
    )
    os.close(requests_read)
    os.close(replies_write)
    os.close(replies_read)
    try:
        assert child.wait(timeout=60) == 0
        assert child.stderr.read() == ""
    finally:
        os.close(requests_write)
        child.stderr.close()


def test_a_renderer_with_a_thread_count_renders_on_it_whatever_another_renderer_set():
    import drjit

    original = drjit.thread_count()
    jade = presets.preset("jade")
    try:
        deciding = engine.Renderer(16, 16, threads=1)  # the page verifies on one thread ...
        large = engine.Renderer(24, 4, threads=2)  # ... and renders large pictures on every core
        assert drjit.thread_count() == 2
        first = deciding.render(jade, seed=3)
        assert drjit.thread_count() == 1
        large.render(jade, seed=3)
        assert drjit.thread_count() == 2
        np.testing.assert_array_equal(deciding.render(jade, seed=3), first)
    finally:
        drjit.set_thread_count(original)


def test_sphere_mask_covers_the_silhouette():
    mask = scene.sphere_mask(64, margin=0.0)
    assert mask[32, 32] and not mask[0, 0] and not mask[63, 63]
    # the unit sphere seen from 5.57 units subtends asin(1 / d); its image is close to a disc of
    # radius tan(asin(1 / d)) on an image plane 2 tan(15 degrees) wide
    distance = np.sqrt(0.9**2 + 5.5**2)
    disc = np.pi * np.tan(np.arcsin(1 / distance)) ** 2 / (2 * np.tan(np.radians(15.0))) ** 2 * 64 * 64
    assert mask.sum() == pytest.approx(disc, rel=0.03)
    assert scene.sphere_mask(64).sum() > mask.sum()
