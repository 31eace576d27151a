"""Physically based rendering of the test scene: the only module that imports Mitsuba to render.

The scene is loaded once per `Renderer`; each material is applied through `mi.traverse` +
`update()` (no reload, no recompilation) and rendered with an explicit seed, so that image i is the
same whatever was rendered before it. Images come back as linear (HDR) float32 (H, W, 3) arrays.

Variant choice: Mitsuba's fast CPU variant `llvm_ad_rgb` needs libLLVM. With an LLVM older than
19 (Debian 12 ships 15) the first render aborts the whole process (`LLVM ERROR: Cannot select
... fminimum`), which no Python code can catch, so the library is looked for on disk *before*
Mitsuba is asked for the variant, and `DRJIT_LIBLLVM_PATH` is pointed at it.
"""

from __future__ import annotations

import glob
import os
import re
import time
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass

import numpy as np

from matfit import params, scene
from matfit.errors import RenderError

LLVM_VARIANT = "llvm_ad_rgb"
SCALAR_VARIANT = "scalar_rgb"
VARIANTS = (LLVM_VARIANT, SCALAR_VARIANT)
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


def choose_variant(requested: str | None = None) -> tuple[str, str | None]:
    """Returns (variant, notice): the Mitsuba variant to use and a one-line notice, if any.

    `requested` forces a variant; None picks llvm_ad_rgb when a usable libLLVM is found (or
    `DRJIT_LIBLLVM_PATH` names one), else scalar_rgb.
    """
    if requested is not None and requested not in VARIANTS:
        raise RenderError(f"unknown variant {requested!r}: use one of {', '.join(VARIANTS)}")
    if requested == SCALAR_VARIANT:
        return SCALAR_VARIANT, None
    configured = os.environ.get("DRJIT_LIBLLVM_PATH")
    if configured:
        if not os.path.isfile(configured):
            raise RenderError(
                f"DRJIT_LIBLLVM_PATH={configured} does not exist: point it at libLLVM >= {MINIMUM_LLVM} or unset it"
            )
        return LLVM_VARIANT, None
    found = find_libllvm()
    if found is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = found
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

    return {"mitsuba": mi.__version__, "drjit": drjit.__version__}


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
    """Where each part of the material lives in `mi.traverse(scene)`."""

    base_color: str = "object.bsdf.base_color.value"
    sigma_t: str = "object.interior_medium.sigma_t.value.value"
    albedo: str = "object.interior_medium.albedo.value.value"
    phase_g: str = "object.interior_medium.phase_function.g"

    @staticmethod
    def scalar(name: str) -> str:
        """Returns the key of a scalar principled parameter."""
        return f"object.bsdf.{name}" if name == "specular" else f"object.bsdf.{name}.value"


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


class Renderer:
    """The test scene loaded once, rendering any material at a fixed resolution."""

    def __init__(self, resolution: int = 64, spp: int = 16, variant: str | None = None):
        self.variant, self.notice = choose_variant(variant)
        self.resolution = resolution
        self.spp = spp
        self.mi = mitsuba(self.variant)
        import drjit

        self.drjit = drjit
        self.scene = self.mi.load_dict(to_mitsuba(self.mi, scene.scene(resolution, spp)))
        self.parameters = self.mi.traverse(self.scene)

    def set_material(self, values: np.ndarray) -> None:
        """Applies a physical parameter vector (19,) to the loaded scene."""
        mi, p, keys = self.mi, self.parameters, Keys()
        v = np.asarray(values, dtype=np.float64)
        if v.shape != (params.COUNT,) or not np.all(np.isfinite(v)):
            raise RenderError(f"a material is {params.COUNT} finite values, got shape {v.shape}")
        index = params.INDEX
        p[keys.base_color] = mi.Color3f(*(float(x) for x in v[index["base_color_r"] : index["base_color_b"] + 1]))
        for name in SCALAR_BSDF_PARAMETERS:
            p[Keys.scalar(name)] = mi.Float(float(v[index[name]]))
        sigma_t, albedo = scene.medium_textures(v)
        p[keys.sigma_t] = mi.Color3f(*(float(x) for x in sigma_t))
        p[keys.albedo] = mi.Color3f(*(float(x) for x in albedo))
        # The phase function does not make its `g` opaque itself: as a literal, every new value
        # would compile a new kernel (~0.5 s).
        p[keys.phase_g] = self.drjit.opaque(mi.Float, float(v[index["phase_g"]]))
        p.update()

    def render(self, values: np.ndarray, seed: int = 0, spp: int | None = None) -> np.ndarray:
        """Returns the linear float32 (H, W, 3) image of a material rendered with `seed`."""
        self.set_material(values)
        return self.render_current(seed, spp)

    def render_current(self, seed: int = 0, spp: int | None = None) -> np.ndarray:
        """Returns the image of whatever material is loaded, without touching the scene."""
        image = self.mi.render(self.scene, seed=int(seed) & 0xFFFFFFFF, spp=int(spp or self.spp))
        return np.array(image, dtype=np.float32)


class Background:
    """A `Renderer` loaded, and renders made, on one background thread while the caller computes.

    Importing Mitsuba, loading the scene, the first `update()` of its parameters and the first
    render's kernels take ~0.4 s that a fit need not wait for (XLA releases the interpreter), and a
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
        renderer = Renderer(resolution, spp, variant)
        renderer.render(params.DEFAULTS, spp=1)  # warms the kernels; changes no later (seeded) render
        return renderer

    @staticmethod
    def _key(values: np.ndarray, seed: int, spp: int | None) -> tuple:
        return np.asarray(values, np.float64).tobytes(), int(seed), spp

    def prefetch(self, values: np.ndarray, seed: int = 0, spp: int | None = None) -> None:
        """Starts rendering a material in the background, for a later `render` of the same arguments."""
        key = self._key(values, seed, spp)
        if key not in self._prefetched:
            self._prefetched[key] = self._executor.submit(lambda: self._loaded.result().render(values, seed, spp))

    def renderer(self) -> Renderer:
        """Returns the loaded renderer once every background render is done (raises a failure to load)."""
        wait(self._prefetched.values())
        return self._loaded.result()

    def render(self, values: np.ndarray, seed: int = 0, spp: int | None = None) -> np.ndarray:
        """Returns what `Renderer.render` returns: the prefetched image of these arguments, or a new render."""
        renderer = self.renderer()
        job = self._prefetched.get(self._key(values, seed, spp))
        return job.result() if job is not None else renderer.render(values, seed, spp)


@dataclass
class Rendered:
    """What `render_file` did: the variant it rendered with, notices (such as the scalar fallback), seconds."""

    variant: str
    notices: list[str]
    seconds: float


def render_file(
    values: np.ndarray, path: str, size: int, spp: int, seed: int = 0, variant: str | None = None
) -> Rendered:
    """Renders a material (19 physical values) at size x size and writes it to an image file; checks the path first."""
    from matfit import images

    images.check_output(path)
    started = time.perf_counter()
    renderer = Renderer(size, spp, variant)
    images.write(path, renderer.render(values, seed=seed))
    return Rendered(renderer.variant, [renderer.notice] if renderer.notice else [], time.perf_counter() - started)


def render_without_sphere(resolution: int, spp: int, variant: str | None = None, seed: int = 0) -> np.ndarray:
    """Returns the linear float32 (H, W, 3) image of the test scene without its sphere.

    Datasets keep it (clean) as the picture of what lies behind the sphere.
    """
    chosen, _ = choose_variant(variant)
    mi = mitsuba(chosen)
    empty = mi.load_dict(to_mitsuba(mi, scene.scene(resolution, spp, sphere=False)))
    return np.array(mi.render(empty, seed=int(seed), spp=int(spp)), dtype=np.float32)
