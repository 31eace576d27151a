"""The material test scene as plain data: camera, lights, floor, backdrop and the shaded sphere.

No Mitsuba import here: transforms are `Transform` records and the environment map is a NumPy
array; `engine.py` turns them into Mitsuba objects. Keeping the scene as data lets the exporters
write the same shader that the renderer uses, and lets tests inspect the scene without rendering.

Layout (units: the sphere's radius): a unit sphere at the origin resting on a checker floor at
y = -1, a lower-contrast checkered backdrop 4 units behind it, a camera 5.5 units in front looking slightly
down, a soft rectangular key light above-left, and a procedural sky-to-ground gradient as the
environment. The checkers show through transmissive spheres (refracted and upside down) and in
reflections, so that roughness, index of refraction and interior absorption are all visible.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from matfit import params

FIELD_OF_VIEW = 30.0
MAX_DEPTH = 64
# `volpathmis` (spectral MIS over the RGB channels of a chromatic medium) rather than `volpath`:
# far less noise at equal time in chromatic media (jade, amber glass), the same on opaque materials.
# A later Russian roulette (rr_depth 10 or 20) lowers milk's noise but costs as much time as the
# samples it saves (docs/method.md#the-scene; the figures: docs/decisions.md).
INTEGRATOR = {"type": "volpathmis", "max_depth": MAX_DEPTH}
# The largest extinction the parameter ranges allow: density 4 through colour 0.01.
MEDIUM_SCALE = float(params.HIGH[params.INDEX["density"]] * -np.log(params.LOW[params.INDEX["medium_color_r"]]))


@dataclass(frozen=True)
class Transform:
    """A to_world transform as a list of operations applied in order (first one innermost)."""

    operations: tuple[tuple, ...] = field(default_factory=tuple)

    def then(self, *operation: object) -> Transform:
        """Returns this transform followed by one more operation."""
        return Transform((*self.operations, tuple(operation)))


def identity() -> Transform:
    """Returns the identity transform."""
    return Transform()


def environment_map(height: int = 32, width: int = 64) -> np.ndarray:
    """Returns a (height, width, 3) linear-RGB latitude-longitude sky: bright above, dark below."""
    elevation = 0.5 - (np.arange(height) + 0.5) / height  # +0.5 at the zenith, -0.5 at the nadir
    sky = np.array([0.75, 0.85, 1.0])
    horizon = np.array([0.9, 0.9, 0.85])
    ground = np.array([0.15, 0.13, 0.12])
    up = np.clip(elevation * 2.0, 0.0, 1.0)[:, None]
    down = np.clip(-elevation * 6.0, 0.0, 1.0)[:, None]
    rows = horizon * (1 - up) + sky * up
    rows = rows * (1 - down) + ground * down
    return np.repeat(rows[:, None, :], width, axis=1).astype(np.float32)


def checker(dark: float, light: float, cells: float | tuple[float, float]) -> dict:
    """Returns a diffuse BSDF with a grey checkerboard of `cells` squares across its rectangle."""
    across, down = (cells, cells) if isinstance(cells, float) else cells
    return {
        "type": "diffuse",
        "reflectance": {
            "type": "checkerboard",
            "color0": {"type": "rgb", "value": [dark, dark, dark]},
            "color1": {"type": "rgb", "value": [light, light, light]},
            "to_uv": identity().then("scale", (across / 2.0, down / 2.0, 1.0)),
        },
    }


def bsdf(values: np.ndarray) -> dict:
    """Returns the Mitsuba `principled` BSDF dictionary for a physical parameter vector (19,)."""
    v = dict(zip(params.NAMES, (float(x) for x in values), strict=True))
    return {
        "type": "principled",
        "base_color": {"type": "rgb", "value": [v["base_color_r"], v["base_color_g"], v["base_color_b"]]},
        "metallic": v["metallic"],
        "roughness": v["roughness"],
        "anisotropic": v["anisotropic"],
        "specular": v["specular"],
        "spec_tint": v["spec_tint"],
        "sheen": v["sheen"],
        "sheen_tint": v["sheen_tint"],
        "clearcoat": v["clearcoat"],
        "clearcoat_gloss": v["clearcoat_gloss"],
        "spec_trans": v["spec_trans"],
    }


def medium_textures(values: np.ndarray) -> tuple[list[float], list[float]]:
    """Returns (sigma_t / MEDIUM_SCALE, albedo) as the medium's two RGB texture values.

    Mitsuba's RGB textures hold values in [0, 1] and the medium's `scale` is a plain float (each
    new value would recompile the renderer), so the extinction is stored divided by the fixed
    largest extinction the parameter ranges allow.
    """
    sigma_t, albedo = params.medium_coefficients(values)
    return [float(s) / MEDIUM_SCALE for s in sigma_t], [float(a) for a in albedo]


def medium(values: np.ndarray) -> dict:
    """Returns the Mitsuba homogeneous medium dictionary for a physical parameter vector (19,)."""
    sigma_t, albedo = medium_textures(values)
    return {
        "type": "homogeneous",
        "scale": MEDIUM_SCALE,
        "sigma_t": {"type": "rgb", "value": sigma_t},
        "albedo": {"type": "rgb", "value": albedo},
        "phase": {"type": "hg", "g": float(values[params.INDEX["phase_g"]])},
    }


# The clear-glass basis of the refracting decoder: the sphere as clear, colourless glass (white
# base colour, spec_trans 1, no medium) rendered on a grid of `specular` (which sets the index of
# refraction) and `roughness`. The decoder interpolates it at a material's specular and roughness and
# tints it per pixel, so refraction (the checkers bent and turned upside down through the sphere,
# blurred by roughness) is drawn by Mitsuba, not learned. Roughness is gridded uniformly in its
# square root: the microfacet alpha is roughness squared, so most of the change is near 0.
GLASS_GRID = (17, 6)


def glass_grid_values(shape: Sequence[int] = GLASS_GRID) -> tuple[np.ndarray, np.ndarray]:
    """Returns the (specular, roughness) values of the glass basis grid: (S,) and (G,)."""
    specular_count, roughness_count = shape
    if specular_count < 2 or roughness_count < 2:
        raise ValueError(f"a glass basis grid needs at least 2 x 2 points, got {specular_count} x {roughness_count}")
    return np.linspace(0.0, 1.0, specular_count), np.linspace(0.0, 1.0, roughness_count) ** 2


def clear_glass_grid(shape: tuple[int, int]) -> np.ndarray:
    """Returns clear, colourless glass (white base colour, spec_trans 1, every other lobe off, no medium) repeated
    on a grid, (K, L, 19) physical vectors: what both bases vary from."""
    clear = params.from_unit(np.zeros(params.COUNT))  # every lobe off, no medium (density 0)
    for name in ("base_color_r", "base_color_g", "base_color_b", "spec_trans"):
        clear[params.INDEX[name]] = 1.0
    return np.repeat(np.repeat(clear[None, None], shape[0], 0), shape[1], 1)


def glass_basis_materials(shape: Sequence[int] = GLASS_GRID) -> np.ndarray:
    """Returns the physical parameter vectors of the glass basis, (S, G, 19): clear glass at each grid point."""
    specular, roughness = glass_grid_values(shape)
    materials = clear_glass_grid((len(specular), len(roughness)))
    materials[..., params.INDEX["specular"]] = specular[:, None]
    materials[..., params.INDEX["roughness"]] = roughness[None, :]
    return materials


# The scattering basis of the refracting decoder: the light a medium scatters, which a clear-glass
# render tinted per pixel cannot draw (milk: white, lit from inside). In Mitsuba's RGB mode every
# colour channel is transported independently, so a medium whose extinction differs per channel
# shows in channel k what a grey medium of channel k's optical thickness shows there: one basis of
# grey media serves every colour. It is gridded in the optical thickness of a radius, tau = density
# x -ln(colour), uniformly in log2(1 + 8 tau) up to the largest the parameters allow, and in the
# similarity parameter sqrt(1 - albedo) (van de Hulst), along which a white medium's brightness
# changes evenly; the surface is clear glass of the default specular and MEDIUM_ROUGHNESS. The
# basis keeps only the scattered light: each render less the render of the same medium that only
# absorbs (albedo 0), which is clear glass dimmed along each path, the glass basis's job.
MEDIUM_GRID = (9, 6)
MEDIUM_ROUGHNESS = 0.15
THICKNESS_SCALE = 8.0  # the grid is uniform in log2(1 + THICKNESS_SCALE x tau), from 0 to the largest tau:
LARGEST_COORDINATE = float(np.log2(1.0 + THICKNESS_SCALE * MEDIUM_SCALE))


def medium_grid_values(shape: Sequence[int] = MEDIUM_GRID) -> tuple[np.ndarray, np.ndarray]:
    """Returns the (thickness tau, albedo) values of the scattering basis grid: (T,) from 0, (A,) from 1 down to 0."""
    thickness_count, albedo_count = shape
    if thickness_count < 2 or albedo_count < 2:
        raise ValueError(f"a scattering basis grid needs at least 2 x 2 points, got {thickness_count} x {albedo_count}")
    coordinate = np.linspace(0.0, LARGEST_COORDINATE, thickness_count)
    similarity = np.linspace(0.0, 1.0, albedo_count)
    return (2.0**coordinate - 1.0) / THICKNESS_SCALE, 1.0 - similarity**2


def medium_basis_materials(shape: Sequence[int] = MEDIUM_GRID) -> np.ndarray:
    """Returns the physical parameter vectors of the scattering basis, (T, A, 19): a grey medium at each grid point.

    The thickness comes from the colour at the largest density (colour = exp(-tau / density)), so
    every grid point lies inside the parameter ranges.
    """
    thickness, albedo = medium_grid_values(shape)
    density = params.HIGH[params.INDEX["density"]]
    low = params.LOW[params.INDEX["medium_color_r"]]
    colour = np.clip(np.exp(-thickness / density), low, 1.0)
    materials = clear_glass_grid((len(thickness), len(albedo)))
    materials[..., params.INDEX["specular"]] = params.DEFAULTS[params.INDEX["specular"]]
    materials[..., params.INDEX["roughness"]] = MEDIUM_ROUGHNESS
    materials[..., params.INDEX["density"]] = density
    for name in ("medium_color_r", "medium_color_g", "medium_color_b"):
        materials[..., params.INDEX[name]] = colour[:, None]
    materials[..., params.INDEX["scattering"]] = albedo[None, :]
    return materials


def all_lobes_values() -> np.ndarray:
    """Returns a vector with every principled lobe and the medium switched on.

    Mitsuba switches a principled lobe on when it is present at load time and never off again, so
    the scene is loaded with all of them present: every image is then rendered with the same lobe
    set, whatever material was rendered before it.
    """
    return params.from_unit(np.full(params.COUNT, 0.5))


def scene(resolution: int, spp: int, values: np.ndarray | None = None, sphere: bool = True) -> dict:
    """Returns the whole test scene as a plain dictionary for `render.load` (`sphere` False: what lies behind it)."""
    values = all_lobes_values() if values is None else values
    whole = {
        "type": "scene",
        "integrator": dict(INTEGRATOR),
        "sensor": {
            "type": "perspective",
            "fov": FIELD_OF_VIEW,
            "to_world": identity().then("look_at", (0.0, 0.9, 5.5), (0.0, -0.1, 0.0), (0.0, 1.0, 0.0)),
            "film": {"type": "hdrfilm", "width": resolution, "height": resolution, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "sky": {
            "type": "envmap",
            "bitmap": environment_map(),
            "scale": 0.6,
        },
        "key_light": {
            "type": "rectangle",
            "to_world": identity()
            .then("scale", (1.2, 1.2, 1.0))
            .then("look_at", (-3.0, 4.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [6.0, 6.0, 6.0]}},
        },
        "floor": {
            "type": "rectangle",
            "to_world": identity()
            .then("scale", (12.0, 12.0, 1.0))
            .then("rotate", (1.0, 0.0, 0.0), -90.0)
            .then("translate", (0.0, -1.0, 0.0)),
            "bsdf": checker(0.08, 0.7, 24.0),
        },
        "backdrop": {
            "type": "rectangle",
            "to_world": identity().then("scale", (12.0, 6.0, 1.0)).then("translate", (0.0, 5.0, -4.0)),
            "bsdf": checker(0.25, 0.6, (24.0, 12.0)),
        },
        "object": {
            "type": "sphere",
            "bsdf": bsdf(values),
            "interior": medium(values),
        },
    }
    if not sphere:
        del whole["object"]
    return whole


def sphere_mask(resolution: int, margin: float = 1.5) -> np.ndarray:
    """Returns a boolean (H, W) mask of the pixels within `margin` pixels of the sphere's silhouette.

    Rays through pixel centres of the test scene's camera, tested against the unit sphere; the
    margin covers the reconstruction filter's reach.
    """
    camera = scene(resolution, 1)["sensor"]
    (_, origin, target, up) = camera["to_world"].operations[0]
    origin, target, up = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    forward = (target - origin) / np.linalg.norm(target - origin)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    half = np.tan(np.radians(camera["fov"]) / 2.0)
    coordinates = ((np.arange(resolution) + 0.5) / resolution * 2.0 - 1.0) * half
    x, y = np.meshgrid(coordinates, -coordinates)
    directions = forward + x[..., None] * right + y[..., None] * true_up
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    # distance from the sphere's centre to each ray, against the radius grown by the margin in angle
    along = directions @ -origin
    closest = np.linalg.norm(-origin - along[..., None] * directions, axis=-1)
    pixel_angle = 2.0 * half / resolution
    return closest <= 1.0 + margin * pixel_angle * np.linalg.norm(origin)
