"""Named starting materials (partial parameter sets over the defaults), and choosing the material to render."""

from __future__ import annotations

import numpy as np

from matfit import params
from matfit.errors import ParameterError

PRESETS: dict[str, dict[str, float]] = {
    "gold": {"base_color_r": 1.0, "base_color_g": 0.71, "base_color_b": 0.29, "metallic": 1.0, "roughness": 0.25},
    "silver": {"base_color_r": 0.95, "base_color_g": 0.93, "base_color_b": 0.88, "metallic": 1.0, "roughness": 0.12},
    "copper": {
        "base_color_r": 0.95,
        "base_color_g": 0.64,
        "base_color_b": 0.54,
        "metallic": 1.0,
        "roughness": 0.35,
        "anisotropic": 0.6,
    },
    "red-plastic": {
        "base_color_r": 0.7,
        "base_color_g": 0.05,
        "base_color_b": 0.04,
        "roughness": 0.3,
        "clearcoat": 0.5,
    },
    "blue-rubber": {
        "base_color_r": 0.05,
        "base_color_g": 0.12,
        "base_color_b": 0.45,
        "roughness": 0.85,
        "specular": 0.3,
    },
    "velvet": {
        "base_color_r": 0.35,
        "base_color_g": 0.02,
        "base_color_b": 0.2,
        "roughness": 0.9,
        "sheen": 1.0,
        "sheen_tint": 0.6,
    },
    "glass": {"base_color_r": 1.0, "base_color_g": 1.0, "base_color_b": 1.0, "roughness": 0.0, "spec_trans": 1.0},
    "frosted-glass": {
        "base_color_r": 1.0,
        "base_color_g": 1.0,
        "base_color_b": 1.0,
        "roughness": 0.35,
        "spec_trans": 1.0,
    },
    "amber-glass": {
        "base_color_r": 1.0,
        "base_color_g": 1.0,
        "base_color_b": 1.0,
        "roughness": 0.0,
        "spec_trans": 1.0,
        "medium_color_r": 0.85,
        "medium_color_g": 0.45,
        "medium_color_b": 0.08,
        "density": 1.0,
    },
    "jade": {
        "base_color_r": 1.0,
        "base_color_g": 1.0,
        "base_color_b": 1.0,
        "roughness": 0.15,
        "spec_trans": 1.0,
        "medium_color_r": 0.25,
        "medium_color_g": 0.7,
        "medium_color_b": 0.4,
        "density": 2.0,
        "scattering": 0.9,
        "phase_g": 0.3,
    },
    "milk": {
        "base_color_r": 1.0,
        "base_color_g": 1.0,
        "base_color_b": 1.0,
        "roughness": 0.2,
        "spec_trans": 1.0,
        "specular": 0.25,
        "medium_color_r": 0.3,
        "medium_color_g": 0.3,
        "medium_color_b": 0.3,
        "density": 3.0,
        "scattering": 1.0,
    },
}


def preset(name: str) -> np.ndarray:
    """Returns the physical parameter vector (19,) of a named preset."""
    if name not in PRESETS:
        raise ParameterError(f"unknown preset {name!r}: choose one of {', '.join(PRESETS)}", field="preset")
    return params.from_mapping(PRESETS[name])


def material(
    params_file: str | None = None, preset_name: str | None = None, random_seed: int | None = None
) -> np.ndarray:
    """Returns the physical vector (19,) of exactly one source: a params.json file, a preset or a random draw."""
    if sum(source is not None for source in (params_file, preset_name, random_seed)) != 1:
        raise ParameterError("give exactly one material: a params.json file, --preset NAME or --random")
    if params_file is not None:
        return params.read_file(params_file)
    if preset_name is not None:
        return preset(preset_name)
    return params.from_unit(params.sample_unit(np.random.default_rng(random_seed)))


def sheet(size: int, spp: int, variant: str | None = None) -> np.ndarray:
    """Returns every preset rendered side by side with its name under it, as one linear image."""
    from matfit import images
    from matfit.rendering.engine import Renderer

    renderer = Renderer(size, spp, variant)
    tiles = [images.label(images.srgb_encode(renderer.render(preset(name))), name) for name in PRESETS]
    return images.srgb_decode(np.concatenate(tiles, axis=1))
