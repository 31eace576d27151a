"""Named starting materials for `matfit render --preset`: partial parameter sets over the defaults."""

from __future__ import annotations

import numpy as np

from matfit import params

PRESETS: dict[str, dict[str, float]] = {
    "gold": {"base_color_r": 1.0, "base_color_g": 0.71, "base_color_b": 0.29, "metallic": 1.0, "roughness": 0.25},
    "silver": {"base_color_r": 0.95, "base_color_g": 0.93, "base_color_b": 0.88, "metallic": 1.0, "roughness": 0.12},
    "copper": {"base_color_r": 0.95, "base_color_g": 0.64, "base_color_b": 0.54, "metallic": 1.0, "roughness": 0.35, "anisotropic": 0.6},
    "red-plastic": {"base_color_r": 0.7, "base_color_g": 0.05, "base_color_b": 0.04, "roughness": 0.3, "clearcoat": 0.5},
    "blue-rubber": {"base_color_r": 0.05, "base_color_g": 0.12, "base_color_b": 0.45, "roughness": 0.85, "specular": 0.3},
    "velvet": {"base_color_r": 0.35, "base_color_g": 0.02, "base_color_b": 0.2, "roughness": 0.9, "sheen": 1.0, "sheen_tint": 0.6},
    "glass": {"base_color_r": 1.0, "base_color_g": 1.0, "base_color_b": 1.0, "roughness": 0.0, "spec_trans": 1.0},
    "frosted-glass": {"base_color_r": 1.0, "base_color_g": 1.0, "base_color_b": 1.0, "roughness": 0.35, "spec_trans": 1.0},
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
        raise params.ParameterError(f"unknown preset {name!r}: choose one of {', '.join(PRESETS)}")
    return params.from_mapping(PRESETS[name])
