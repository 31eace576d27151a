"""Physically based rendering of the test scene: the only module that imports Mitsuba to render.

The scene is loaded once per `Renderer`; each material is applied through `mi.traverse` +
`update()` (no reload, no recompilation) and rendered with an explicit seed, so that image i is the
same whatever was rendered before it. Images come back as linear (HDR) float32 (H, W, 3) arrays.

Variant choice: Mitsuba's fast CPU variant `llvm_ad_rgb` needs libLLVM. With an LLVM older than
19 (Debian 12 ships 15) the first render aborts the whole process (`LLVM ERROR: Cannot select
... fminimum`), which no Python code can catch, so the library is looked for on disk *before*
Mitsuba is asked for the variant, and `DRJIT_LIBLLVM_PATH` is pointed at it. Where an NVIDIA GPU
answers the CUDA driver (`cuda_devices`, through ctypes: no JAX) and Mitsuba starts its CUDA backend,
`cuda_ad_rgb` comes first. What was found decides alone (`decide_variant`), so every combination is
testable on any machine.
"""

from __future__ import annotations

import ctypes
import glob
import os
import re
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from matfit import files, params
from matfit.errors import RenderError
from matfit.rendering import scene

if TYPE_CHECKING:
    from jaxtyping import Float

CUDA_VARIANT = "cuda_ad_rgb"
LLVM_VARIANT = "llvm_ad_rgb"
SCALAR_VARIANT = "scalar_rgb"
VARIANTS = (CUDA_VARIANT, LLVM_VARIANT, SCALAR_VARIANT)  # in the order of preference
CUDA_DRIVER = "libcuda.so.1"
MINIMUM_LLVM = 19
LLVM_SEARCH = (
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)


def llvm_major(path: str) -> int | None:
    """Returns the LLVM major version encoded in a libLLVM file name, or None."""
    match = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
    return int(match.group(1)) if match else None


def find_libllvm() -> str | None:
    """Returns the path of the newest libLLVM >= 19 on this machine, or None."""
    candidates = []
    for pattern in LLVM_SEARCH:
        for path in glob.glob(pattern):
            major = llvm_major(path)
            if major is not None and major >= MINIMUM_LLVM and os.path.isfile(path):
                candidates.append((major, len(path), path))
    return max(candidates)[2] if candidates else None


def cuda_devices() -> int:
    """Returns how many GPUs the NVIDIA CUDA driver reports: 0 without the driver, a GPU, or a driver that starts."""
    try:
        driver = ctypes.CDLL(CUDA_DRIVER)
    except OSError:
        return 0
    count = ctypes.c_int(0)
    if driver.cuInit(0) != 0 or driver.cuDeviceGetCount(ctypes.byref(count)) != 0:
        return 0
    return count.value


def cuda_problem() -> str | None:
    """Returns why Mitsuba cannot render with cuda_ad_rgb in this process, or None when it can.

    On success this process's Mitsuba variant is cuda_ad_rgb (the one use of what was just checked).
    """
    if cuda_devices() == 0:
        return f"no NVIDIA GPU answers {CUDA_DRIVER}"
    try:
        import drjit
        import mitsuba as mi
    except ImportError as error:
        return f"Mitsuba cannot be imported: {error}"
    current = mi.variant()
    if current is not None:
        return None if current == CUDA_VARIANT else f"this process already renders with {current}"
    try:
        if not drjit.has_backend(drjit.JitBackend.CUDA):
            return "Dr.Jit cannot start its CUDA backend"
        mi.set_variant(CUDA_VARIANT)
    except Exception as error:  # an ImportError of a variant left out of the wheel, a RuntimeError of the driver
        return f"Mitsuba cannot set {CUDA_VARIANT}: {error}"
    return None


# The first bytes of a shared library: ELF (Linux; its type, bytes 16-17, says a shared object), Mach-O (macOS, 32
# and 64 bits, either byte order, and the universal binary's), PE (Windows' DLLs).
ELF_MAGIC = b"\x7fELF"
ELF_SHARED = 3  # e_type ET_DYN
MACH_O_MAGICS = (
    b"\xfe\xed\xfa\xce",
    b"\xce\xfa\xed\xfe",
    b"\xfe\xed\xfa\xcf",
    b"\xcf\xfa\xed\xfe",
    b"\xca\xfe\xba\xbe",
)
PE_MAGIC = b"MZ"


def not_a_library(path: str) -> str | None:
    """Returns why the file `path` cannot be a libLLVM, from its first bytes (not a shared library: a text file, an
    executable), or None when it looks like one. Dr.Jit would fail on it only once Mitsuba starts, with an ImportError
    from deep inside."""
    try:
        head = files.read_input(path, 32)[:32]
    except OSError as error:
        return f"it cannot be read: {error.strerror or error}"
    if head.startswith(ELF_MAGIC):
        big = head[5:6] == b"\x02"  # EI_DATA: 1 little-endian, 2 big-endian
        shared = len(head) >= 18 and int.from_bytes(head[16:18], "big" if big else "little") == ELF_SHARED
        return None if shared else "it is an ELF file but no shared library"
    if head.startswith(MACH_O_MAGICS) or head.startswith(PE_MAGIC):
        return None
    return "it is no shared library"


def libllvm_usable() -> tuple[bool, str | None]:
    """Returns (whether llvm_ad_rgb can run, a notice or None): it can when `DRJIT_LIBLLVM_PATH` names a shared
    library, or a libLLVM >= 19 is found on disk (then `DRJIT_LIBLLVM_PATH` is pointed at it). Raises RenderError for
    a `DRJIT_LIBLLVM_PATH` that does not exist. One that names a file that is no shared library (`not_a_library`) is
    dropped from the environment, with a notice, and the choice goes on as without it."""
    configured = os.environ.get("DRJIT_LIBLLVM_PATH")
    notice = None
    if configured:
        if not os.path.isfile(configured):
            raise RenderError(
                f"DRJIT_LIBLLVM_PATH={configured} does not exist: point it at libLLVM >= {MINIMUM_LLVM} or unset it"
            )
        why = not_a_library(configured)
        if why is None:
            return True, None
        del os.environ["DRJIT_LIBLLVM_PATH"]  # Dr.Jit, here and in the render processes started later, reads it
        notice = f"notice: DRJIT_LIBLLVM_PATH={configured} is not a libLLVM ({why}), so it is ignored"
    found = find_libllvm()
    if found is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = found
        return True, None if notice is None else f"{notice}: rendering with {found}"
    return False, notice


NO_CUDA = "no NVIDIA GPU with its CUDA driver and Mitsuba's CUDA backend"


def decide_variant(
    requested: str | None, cuda: bool, llvm: bool, why_not_cuda: str = NO_CUDA
) -> tuple[str, str | None]:
    """Returns (variant, notice) for what was found: `cuda` (cuda_ad_rgb runs), `llvm` (a usable libLLVM).

    `requested` None picks the first usable of VARIANTS; a requested variant that is unusable raises
    RenderError naming the fix and the variants usable here (`why_not_cuda`: what the CUDA check found).
    """
    if requested is not None and requested not in VARIANTS:
        raise RenderError(f"unknown variant {requested!r}: use one of {', '.join(VARIANTS)}")
    if requested == SCALAR_VARIANT:
        return SCALAR_VARIANT, None
    if cuda and requested in (None, CUDA_VARIANT):
        return CUDA_VARIANT, None
    if requested == CUDA_VARIANT:
        usable = " or ".join(
            f"--variant {name}" for name in (LLVM_VARIANT, SCALAR_VARIANT) if llvm or name != LLVM_VARIANT
        )
        raise RenderError(
            f"variant {CUDA_VARIANT} is not usable here ({why_not_cuda}): use {usable}, or leave --variant out"
        )
    if llvm:
        return LLVM_VARIANT, None
    if requested == LLVM_VARIANT:
        raise RenderError(
            f"variant llvm_ad_rgb needs libLLVM >= {MINIMUM_LLVM}: run `make install` as root "
            "(installs Debian's libllvm19), set DRJIT_LIBLLVM_PATH, or use --variant scalar_rgb"
        )
    notice = (
        f"notice: no libLLVM >= {MINIMUM_LLVM} found, rendering with the slower scalar_rgb variant "
        "(install Debian's libllvm19 or set DRJIT_LIBLLVM_PATH for llvm_ad_rgb)"
    )
    return SCALAR_VARIANT, notice


def choose_variant(requested: str | None = None, *, start_mitsuba: bool = True) -> tuple[str, str | None]:
    """Returns (variant, notice): the Mitsuba variant to use and a one-line notice, if any.

    `requested` forces a variant; None picks cuda_ad_rgb where an NVIDIA GPU and Mitsuba's CUDA
    backend are usable, else llvm_ad_rgb when a usable libLLVM is found (or `DRJIT_LIBLLVM_PATH`
    names one), else scalar_rgb (`decide_variant`). Only what the choice needs is looked for: the GPU
    unless llvm_ad_rgb or scalar_rgb is requested, libLLVM unless cuda_ad_rgb is usable.
    `start_mitsuba` False checks the GPU through its driver alone (no Mitsuba import: a quick check of
    a request before other work; the variant may still fail to start later).
    """
    if requested not in (None, CUDA_VARIANT, LLVM_VARIANT):  # scalar_rgb, or a name to refuse: nothing to look for
        return decide_variant(requested, cuda=False, llvm=False)
    problem = None
    if requested in (None, CUDA_VARIANT):
        problem = (
            cuda_problem() if start_mitsuba else None if cuda_devices() else f"no NVIDIA GPU answers {CUDA_DRIVER}"
        )
    cuda = requested != LLVM_VARIANT and problem is None
    llvm, ignored = (False, None) if cuda else libllvm_usable()
    try:
        variant, notice = decide_variant(requested, cuda, llvm, problem or NO_CUDA)
    except RenderError as error:
        if ignored is None:
            raise
        raise RenderError(f"{ignored.removeprefix('notice: ')}; {error}") from None
    if ignored is None or (notice is None and variant != LLVM_VARIANT):  # quiet where the fallback needed none
        return variant, notice
    return variant, f"{ignored}; {notice.removeprefix('notice: ')}" if notice else ignored


def check_request(requested: str | None) -> None:
    """Raises RenderError for a requested variant that this machine cannot use, without importing Mitsuba: a command
    that works before it renders refuses the request first."""
    if requested is not None:
        choose_variant(requested, start_mitsuba=False)


def mitsuba(variant: str):
    """Returns the mitsuba module set to `variant`; a process can hold only one variant."""
    import mitsuba as mi

    current = mi.variant()
    if current is None:
        mi.set_variant(variant)
    elif current != variant:
        raise RenderError(f"this process already renders with {current}; it cannot switch to {variant}")
    return mi


def versions() -> dict[str, str]:
    """Returns the Mitsuba and Dr.Jit versions, for dataset metadata."""
    import drjit
    import mitsuba as mi

    return {"mitsuba": str(mi.__version__), "drjit": drjit.__version__}  # type: ignore[attr-defined]  # not in the stubs


def _transform(mi, transform: scene.Transform):
    """Returns the Mitsuba transform for a `scene.Transform` (first operation innermost)."""
    result = mi.ScalarTransform4f()
    for name, *arguments in transform.operations:
        if name == "look_at":
            origin, target, up = arguments
            step = mi.ScalarTransform4f().look_at(origin=origin, target=target, up=up)
        elif name == "rotate":
            axis, angle = arguments
            step = mi.ScalarTransform4f().rotate(axis=axis, angle=angle)
        else:
            step = getattr(mi.ScalarTransform4f(), name)(arguments[0])
        result = step @ result
    return result


def to_mitsuba(mi, node: object) -> object:
    """Returns a scene dictionary with transforms and arrays turned into Mitsuba objects."""
    if isinstance(node, dict):
        return {key: to_mitsuba(mi, value) for key, value in node.items()}
    if isinstance(node, scene.Transform):
        return _transform(mi, node)
    if isinstance(node, np.ndarray):
        return mi.Bitmap(node)
    return node


@dataclass(frozen=True)
class Keys:
    """Where each part of the material lives in `mi.traverse(scene)`: under the fitted shape's id (`object`, the test
    scene's sphere; a scene file's shape, `scene_file`)."""

    shape: str = "object"

    @property
    def base_color(self) -> str:
        return f"{self.shape}.bsdf.base_color.value"

    @property
    def sigma_t(self) -> str:
        return f"{self.shape}.interior_medium.sigma_t.value.value"

    @property
    def albedo(self) -> str:
        return f"{self.shape}.interior_medium.albedo.value.value"

    @property
    def phase_g(self) -> str:
        return f"{self.shape}.interior_medium.phase_function.g"

    def scalar(self, name: str) -> str:
        """Returns the key of a scalar principled parameter."""
        return f"{self.shape}.bsdf.{name}" if name == "specular" else f"{self.shape}.bsdf.{name}.value"


SCALAR_BSDF_PARAMETERS = (
    "metallic",
    "roughness",
    "anisotropic",
    "specular",
    "spec_tint",
    "sheen",
    "sheen_tint",
    "clearcoat",
    "clearcoat_gloss",
    "spec_trans",
)


class Renders(Protocol):
    """What the stages of a fit ask of whatever renders for them: `Renderer` here, or `process.Background`,
    `process.Process` and `process.Pool` beside the caller. Every image depends only on its material, seed and
    samples, so which kind made it, and when, never changes an answer."""

    def prefetch(self, values: Float[np.ndarray, " 19"], seed: int = 0, spp: int | None = None) -> None:
        """Asks for a render now, for a later `render` of the same arguments (a kind that renders only when asked
        ignores it)."""

    def render(
        self, values: Float[np.ndarray, " 19"], seed: int = 0, spp: int | None = None
    ) -> Float[np.ndarray, "R R 3"]:
        """Returns the linear float32 (H, W, 3) image of a material (physical parameters) rendered with `seed`."""
        ...


def set_material(mi: Any, parameters: Any, values: Float[np.ndarray, " 19"], keys: Keys) -> None:
    """Writes a physical parameter vector (19,) into a loaded scene's traversed `parameters` at `keys`, and updates."""
    import drjit

    v = np.asarray(values, dtype=np.float64)
    if v.shape != (params.COUNT,) or not np.all(np.isfinite(v)):
        raise RenderError(f"a material is {params.COUNT} finite values, got shape {v.shape}")
    index = params.INDEX
    parameters[keys.base_color] = mi.Color3f(*(float(x) for x in v[index["base_color_r"] : index["base_color_b"] + 1]))
    for name in SCALAR_BSDF_PARAMETERS:
        parameters[keys.scalar(name)] = mi.Float(float(v[index[name]]))
    sigma_t, albedo = scene.medium_textures(v)
    parameters[keys.sigma_t] = mi.Color3f(*(float(x) for x in sigma_t))
    parameters[keys.albedo] = mi.Color3f(*(float(x) for x in albedo))
    # The phase function does not make its `g` opaque itself: as a literal, every new value would compile a new
    # kernel.
    parameters[keys.phase_g] = drjit.opaque(mi.Float, float(v[index["phase_g"]]))
    parameters.update()


class Renderer:
    """The test scene loaded once, rendering any material at a fixed resolution.

    `threads`: Dr.Jit's thread count, which is the whole process's (every renderer in it then uses
    it). Several threads add their samples into the film in no fixed order, so two renders of one
    material and seed differ in the last bits; one thread makes them bit-identical from run to run,
    which the renders that decide (verification, a dataset's scene image) need. It is set when the
    renderer is made, and again before each of its renders if another renderer changed it since
    (the page's one worker thread renders large pictures on every core and verifies on one); a
    renderer without `threads` renders on whatever count the process has. Use it where no other
    thread renders at the time (a render process, `Background`'s one thread, the page's worker).
    """

    def __init__(self, resolution: int = 64, spp: int = 16, variant: str | None = None, threads: int | None = None):
        self.variant, self.notice = choose_variant(variant)
        self.resolution = resolution
        self.spp = spp
        self.mi = mitsuba(self.variant)
        import drjit

        self.threads = threads
        if threads is not None:
            drjit.set_thread_count(threads)
        self.drjit = drjit
        self.scene = self.mi.load_dict(to_mitsuba(self.mi, scene.scene(resolution, spp)))
        self.parameters = self.mi.traverse(self.scene)

    def set_material(self, values: Float[np.ndarray, " 19"]) -> None:
        """Applies a physical parameter vector (19,) to the loaded scene."""
        set_material(self.mi, self.parameters, values, Keys())

    def prefetch(self, values: Float[np.ndarray, " 19"], seed: int = 0, spp: int | None = None) -> None:
        """Renders nothing ahead: `Background` and `Process` do (every renderer answers `prefetch`)."""

    def render(
        self, values: Float[np.ndarray, " 19"], seed: int = 0, spp: int | None = None
    ) -> Float[np.ndarray, "R R 3"]:
        """Returns the linear float32 (H, W, 3) image of a material rendered with `seed`."""
        self.set_material(values)
        return self.render_current(seed, spp)

    def render_current(self, seed: int = 0, spp: int | None = None) -> Float[np.ndarray, "R R 3"]:
        """Returns the image of whatever material is loaded, without touching the scene."""
        if self.threads is not None and self.drjit.thread_count() != self.threads:
            self.drjit.set_thread_count(self.threads)  # another renderer of this process changed it since
        image = self.mi.render(self.scene, seed=int(seed) & 0xFFFFFFFF, spp=int(spp or self.spp))
        return np.array(image, dtype=np.float32)


@dataclass
class Rendered:
    """What `render_file` did: the variant it rendered with, notices (such as the scalar fallback), seconds."""

    variant: str
    notices: list[str]
    seconds: float


def render_file(
    values: Float[np.ndarray, " 19"],
    path: str,
    size: int,
    spp: int,
    seed: int = 0,
    variant: str | None = None,
    inputs: dict[str, str | None] | None = None,
) -> Rendered:
    """Renders a material (19 physical values) at size x size and writes it to an image file; checks the path first.

    `inputs` ({"params_file": path}): files the material was read from, which the image must not overwrite.
    """
    from matfit import images

    images.check_output(path, inputs)
    started = time.perf_counter()
    renderer = Renderer(size, spp, variant)
    images.write(path, renderer.render(values, seed=seed))
    return Rendered(renderer.variant, [renderer.notice] if renderer.notice else [], time.perf_counter() - started)


def render_without_sphere(
    resolution: int, spp: int, variant: str | None = None, seed: int = 0
) -> Float[np.ndarray, "R R 3"]:
    """Returns the linear float32 (H, W, 3) image of the test scene without its sphere, rendered on one thread.

    Datasets keep it (clean) as the picture of what lies behind the sphere. Call it where no other thread renders.
    """
    chosen, _ = choose_variant(variant)
    mi = mitsuba(chosen)
    import drjit

    empty = mi.load_dict(to_mitsuba(mi, scene.scene(resolution, spp, sphere=False)))
    threads = drjit.thread_count()
    drjit.set_thread_count(1)  # bit-identical from run to run, as a dataset's files are (see `Renderer`)
    try:
        return np.array(mi.render(empty, seed=int(seed), spp=int(spp)), dtype=np.float32)
    finally:
        drjit.set_thread_count(threads)
