"""The 19 shader parameters: the single source of truth for names, ranges and meanings.

Everything that needs to know what a material is (the renderer, the dataset, the networks, the
optimiser, params.json) reads it from `PARAMETERS`. Networks and optimisers only ever see the unit
cube [0, 1]^19; `to_unit` and `from_unit` are the one place where physical values meet it.

The shader is Mitsuba's `principled` BSDF (13 values) with a homogeneous medium inside the object
(6 values). The medium is only reached by light that the BSDF transmits (`spec_trans` > 0):
- the *absorption colour* c is the colour that white light keeps after one unit of travel (the
  sphere's radius) through the medium at density 1; the extinction per colour channel is
  sigma_t = density * (-ln c), so the transmittance over a path of length L is c ** (density * L);
- the *scattering fraction* is the single-scattering albedo: the share of the extinction that
  scatters rather than absorbs (0: clear coloured glass, 1: milky, wax-like interiors);
- the phase anisotropy g is the Henyey-Greenstein mean cosine (g > 0 scatters forward).
Colour and density trade off against each other (c ** 2 at density 1 looks like c at density 2):
that redundancy is deliberate, it is how artists think of coloured glass ("what colour, how thick").
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from matfit import documents
from matfit.errors import ParameterError

if TYPE_CHECKING:
    from jaxtyping import Float


@dataclass(frozen=True)
class Parameter:
    """One bounded shader parameter.

    `low_corner` and `high_corner` are the probabilities with which `sample_unit` draws the value
    from the bottom or top 5% of the range (the "corners" that uniform sampling would rarely
    visit: perfectly opaque or perfectly transmissive, non-metal or metal); the rest of the mass is
    spread over the whole range, warped by `power` (u ** power; > 1 favours low values).
    """

    name: str
    low: float
    high: float
    default: float
    unit: str
    meaning: str
    low_corner: float = 0.0
    high_corner: float = 0.0
    power: float = 1.0


PARAMETERS: tuple[Parameter, ...] = (
    Parameter("base_color_r", 0.0, 1.0, 0.8, "reflectance", "base colour, red channel (linear)"),
    Parameter("base_color_g", 0.0, 1.0, 0.8, "reflectance", "base colour, green channel (linear)"),
    Parameter("base_color_b", 0.0, 1.0, 0.8, "reflectance", "base colour, blue channel (linear)"),
    Parameter(
        "metallic", 0.0, 1.0, 0.0, "fraction", "0 dielectric, 1 metal (base colour tints the reflection)", 0.45, 0.2
    ),
    Parameter("roughness", 0.0, 1.0, 0.5, "fraction", "microfacet roughness: 0 mirror-like, 1 matte", 0.15, 0.0, 2.0),
    Parameter("anisotropic", 0.0, 1.0, 0.0, "fraction", "stretches highlights along the tangent direction", 0.5, 0.0),
    Parameter(
        "specular", 0.0, 1.0, 0.5, "fraction", "Fresnel reflectance; sets the index of refraction eta (0.5 -> 1.5)"
    ),
    Parameter(
        "spec_tint", 0.0, 1.0, 0.0, "fraction", "tints dielectric specular reflection towards the base colour", 0.4, 0.0
    ),
    Parameter("sheen", 0.0, 1.0, 0.0, "fraction", "soft grazing-angle reflection, as on cloth", 0.5, 0.0),
    Parameter("sheen_tint", 0.0, 1.0, 0.5, "fraction", "tints the sheen towards the base colour"),
    Parameter(
        "clearcoat", 0.0, 1.0, 0.0, "fraction", "strength of a second, clear varnish-like specular layer", 0.5, 0.0
    ),
    Parameter("clearcoat_gloss", 0.0, 1.0, 1.0, "fraction", "glossiness of the clearcoat: 0 satin, 1 gloss"),
    Parameter("spec_trans", 0.0, 1.0, 0.0, "fraction", "specular transmission: 0 opaque, 1 glass-like", 0.4, 0.3),
    Parameter(
        "medium_color_r",
        0.01,
        1.0,
        1.0,
        "transmittance",
        "absorption colour, red: light kept after one radius at density 1",
        0.0,
        0.2,
    ),
    Parameter(
        "medium_color_g",
        0.01,
        1.0,
        1.0,
        "transmittance",
        "absorption colour, green: light kept after one radius at density 1",
        0.0,
        0.2,
    ),
    Parameter(
        "medium_color_b",
        0.01,
        1.0,
        1.0,
        "transmittance",
        "absorption colour, blue: light kept after one radius at density 1",
        0.0,
        0.2,
    ),
    Parameter(
        "density",
        0.0,
        4.0,
        0.0,
        "multiplier",
        "thickness of the interior medium: extinction = density * -ln(colour)",
        0.3,
        0.0,
        1.5,
    ),
    Parameter(
        "scattering",
        0.0,
        1.0,
        0.0,
        "albedo",
        "share of the medium's extinction that scatters (milky) rather than absorbs",
        0.3,
        0.2,
    ),
    Parameter(
        "phase_g",
        -0.9,
        0.9,
        0.0,
        "mean cosine",
        "Henyey-Greenstein anisotropy of the medium: < 0 back-, > 0 forward-scattering",
    ),
)

# The shader's optional features and the values that turn each one off (with the parameters that only matter while it
# is on at their defaults): the clean answer sets a feature the picture does not decide to these values
# (docs/fitting.md#what-the-picture-decides). The first parameter of each is the one whose verdict decides.
FEATURES: dict[str, dict[str, float]] = {
    "anisotropy": {"anisotropic": 0.0},
    "sheen": {"sheen": 0.0, "sheen_tint": 0.5},
    "clearcoat": {"clearcoat": 0.0, "clearcoat_gloss": 1.0},
    "medium": {
        "density": 0.0,
        "medium_color_r": 1.0,
        "medium_color_g": 1.0,
        "medium_color_b": 1.0,
        "scattering": 0.0,
        "phase_g": 0.0,
    },
    "transmission": {"spec_trans": 0.0},
}

NAMES: tuple[str, ...] = tuple(p.name for p in PARAMETERS)
COUNT = len(PARAMETERS)
LOW = np.array([p.low for p in PARAMETERS], dtype=np.float64)
HIGH = np.array([p.high for p in PARAMETERS], dtype=np.float64)
DEFAULTS = np.array([p.default for p in PARAMETERS], dtype=np.float64)
INDEX = {name: i for i, name in enumerate(NAMES)}

# Width of the corner bands that `sample_unit` favours, as a fraction of each range.
CORNER_WIDTH = 0.05
MINIMUM_EXTINCTION = 1e-4
# Bumped whenever `PARAMETERS` or the sampling changes, so that datasets and models made with
# another table are recognised as such.
TABLE_VERSION = 1
MAX_SEED = 2**32 - 1  # every seed of matfit (sampling, renders, training, fits) is in [0, MAX_SEED]

assert COUNT == 19, "the paper's shader has m = 19 parameters"


def to_unit(values: Float[np.ndarray, "*batch 19"]) -> Float[np.ndarray, "*batch 19"]:
    """Returns physical values (..., 19) mapped affinely onto the unit cube [0, 1]^19."""
    values = np.asarray(values, dtype=np.float64)
    return (values - LOW) / (HIGH - LOW)


def from_unit(unit: Float[np.ndarray, "*batch 19"]) -> Float[np.ndarray, "*batch 19"]:
    """Returns unit-cube coordinates (..., 19) mapped back onto the physical ranges."""
    unit = np.asarray(unit, dtype=np.float64)
    return LOW + unit * (HIGH - LOW)


def table() -> list[dict]:
    """Returns the parameter table as plain data, for dataset and model metadata."""
    return [{"name": p.name, "low": p.low, "high": p.high, "default": p.default, "unit": p.unit} for p in PARAMETERS]


def table_fingerprint() -> dict:
    """Returns what identifies this parameter table: compared when a dataset or model is reused."""
    return {"version": TABLE_VERSION, "parameters": table()}


def describe_table_difference(stored: Mapping) -> str | None:
    """Returns a one-line description of how a stored table differs from ours, or None if equal."""
    ours = table_fingerprint()
    if stored == ours:
        return None
    stored_names = [p.get("name") for p in stored.get("parameters", [])]
    if stored_names != list(NAMES):
        missing = sorted(set(NAMES) - set(stored_names))
        extra = sorted(set(stored_names) - set(NAMES))
        if not missing and not extra:
            return "the parameters are in another order"
        return f"parameters missing: {missing or 'none'}, unexpected: {extra or 'none'}"
    for theirs, mine in zip(stored["parameters"], ours["parameters"], strict=True):
        if theirs != mine:
            return f"parameter {mine['name']!r} is {theirs}, expected {mine}"
    return f"parameter table version {stored.get('version')} (this matfit uses {TABLE_VERSION})"


def sample_unit(rng: np.random.Generator) -> Float[np.ndarray, " 19"]:
    """Returns one unit-cube vector from the training distribution.

    Per parameter: with probability `low_corner` the value lies uniformly in [0, 0.05], with
    probability `high_corner` in [0.95, 1], otherwise it is u ** power for u uniform in [0, 1].
    So a quarter to a half of the samples are exact-looking non-metals, metals, opaque or fully
    transmissive materials, and roughness leans towards glossy, while every interior point
    stays reachable.
    """
    choice = rng.random(COUNT)
    band = rng.random(COUNT) * CORNER_WIDTH
    interior = rng.random(COUNT)
    out = np.empty(COUNT)
    for i, p in enumerate(PARAMETERS):
        if choice[i] < p.low_corner:
            out[i] = band[i]
        elif choice[i] < p.low_corner + p.high_corner:
            out[i] = 1.0 - band[i]
        else:
            out[i] = interior[i] ** p.power
    return out


def sample_dense_media_unit(rng: np.random.Generator) -> Float[np.ndarray, " 19"]:
    """Returns one unit-cube vector from the dense-media corner of the training distribution.

    The other parameters as `sample_unit` draws them, then: spec_trans in its top 5% (a dielectric
    sphere), density uniform in [0.5, 4] and the scattering albedo 1 - 0.15 u^3 (u uniform), so
    that 40% of the albedos lie in [0.99, 1]. Milk- and jade-like materials (dense, nearly
    lossless scattering: a white medium turns grey steeply as the albedo falls below 1) are a
    fraction of a percent of `sample_unit`'s draws; a supplement drawn from here teaches the
    decoder that corner (docs/training.md#datasets).
    """
    out = sample_unit(rng)
    u = rng.random(3)
    out[INDEX["spec_trans"]] = 1.0 - CORNER_WIDTH * u[0]
    density = PARAMETERS[INDEX["density"]]
    out[INDEX["density"]] = (0.5 + 3.5 * u[1] - density.low) / (density.high - density.low)
    out[INDEX["scattering"]] = 1.0 - 0.15 * u[2] ** 3
    return out


def sample_glass_unit(rng: np.random.Generator) -> Float[np.ndarray, " 19"]:
    """Returns one unit-cube vector from the white-glass corner of the training distribution.

    Glass is what artists make with spec_trans = 1 and a white or grey base colour (every
    transmissive preset has base colour (1, 1, 1)), but `sample_unit` draws the three channels
    independently, so all three lie above 0.9 once in a thousand draws, and the decoder's error
    on glass, frosted glass, amber, jade and milk grew steadily as their base colour went from
    grey 0.5 to white (docs/training.md#datasets). Here: the other parameters as `sample_unit` draws
    them, then a dielectric (metallic in its bottom 5%, spec_trans in its top 5%) whose base
    colour is grey v (in the top 5% half of the time, else sqrt(u): mostly bright), exactly grey
    half of the time, else with each channel up to 0.05 below v, and half of the time the dense medium of
    `sample_dense_media_unit` (otherwise the medium as drawn: clear, tinted or milky).
    """
    out = sample_unit(rng)
    u = rng.random(9)
    out[INDEX["metallic"]] = CORNER_WIDTH * u[0]
    out[INDEX["spec_trans"]] = 1.0 - CORNER_WIDTH * u[1]
    grey = 1.0 - CORNER_WIDTH * u[2] if u[3] < 0.5 else np.sqrt(u[2])
    for k, channel in enumerate(("base_color_r", "base_color_g", "base_color_b")):
        out[INDEX[channel]] = max(0.0, grey - CORNER_WIDTH * u[4 + k] * (u[8] < 0.5))
    if u[7] < 0.5:
        dense = sample_dense_media_unit(rng)
        for name in ("density", "scattering"):
            out[INDEX[name]] = dense[INDEX[name]]
    return out


def sample_tinted_glass_unit(rng: np.random.Generator) -> Float[np.ndarray, " 19"]:
    """Returns one unit-cube vector from the tinted-glass corner: amber-like dielectrics that absorb but do not scatter.

    The white or grey dielectric of `sample_glass_unit`, then a medium that colours the light it
    keeps: scattering in its bottom 5% (absorption only), density uniform in [0.25, 2.5] and each
    channel of the absorption colour uniform over its range, independently (saturated tints such
    as amber's (0.85, 0.45, 0.08) as often as pale ones). `sample_glass_unit` draws such media for
    a fraction of its half of media as drawn; amber glass stayed the decoder's worst preset after it
    (docs/training.md#datasets).
    """
    out = sample_glass_unit(rng)
    u = rng.random(5)
    out[INDEX["scattering"]] = CORNER_WIDTH * u[0]
    density = PARAMETERS[INDEX["density"]]
    out[INDEX["density"]] = (0.25 + 2.25 * u[1] - density.low) / (density.high - density.low)
    for k, channel in enumerate(("medium_color_r", "medium_color_g", "medium_color_b")):
        out[INDEX[channel]] = u[2 + k]
    return out


# How a dataset's parameters are drawn: `uniform` is the training distribution (and the references'),
# `dense-media`, `glass` and `tinted-glass` corners of it, rendered as supplements for the decoder.
SAMPLERS = {
    "uniform": sample_unit,
    "dense-media": sample_dense_media_unit,
    "glass": sample_glass_unit,
    "tinted-glass": sample_tinted_glass_unit,
}


def sample_index(seed: int, index: int, sampler: str = "uniform") -> Float[np.ndarray, " 19"]:
    """Returns the unit-cube vector number `index` of the dataset drawn with `seed` and `sampler`.

    Each index has its own random stream, so sample i is the same whatever order, chunking or
    number of workers produced it.
    """
    if sampler not in SAMPLERS:
        raise ParameterError(f"unknown sampler {sampler!r}: use {' or '.join(SAMPLERS)}", field="sampler")
    return SAMPLERS[sampler](np.random.default_rng([seed, index]))


def closest_name(name: str) -> str | None:
    """Returns the parameter name closest to a misspelt one, if any is close."""
    matches = difflib.get_close_matches(name, NAMES, n=1, cutoff=0.5)
    return matches[0] if matches else None


def check_value(name: str, value: object) -> float:
    """Returns `value` as a float after checking that `name` exists and the value is in range."""
    if name not in INDEX:
        suggestion = closest_name(name)
        hint = f"did you mean {suggestion!r}?" if suggestion else "see `matfit params` for the list"
        raise ParameterError(f"unknown parameter {name!r}: {hint}")
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ParameterError(f"parameter {name!r} must be a number, got {value!r}")
    p = PARAMETERS[INDEX[name]]
    try:
        value = float(value)
    except OverflowError:  # an int too large for a float
        raise ParameterError(f"parameter {name!r} is out of range: use a value in [{p.low}, {p.high}]") from None
    if math.isnan(value) or math.isinf(value):
        raise ParameterError(f"parameter {name!r} is {value}: give a number in [{p.low}, {p.high}]")
    if not p.low <= value <= p.high:
        raise ParameterError(f"parameter {name!r} = {value} is out of range: use a value in [{p.low}, {p.high}]")
    return value


def from_mapping(values: Mapping[str, object]) -> Float[np.ndarray, " 19"]:
    """Returns the physical vector (19,) for named values; missing names take their defaults."""
    out = DEFAULTS.copy()
    for name, value in values.items():
        checked = check_value(name, value)
        out[INDEX[name]] = checked
    return out


def to_mapping(values: Float[np.ndarray, " 19"]) -> dict[str, float]:
    """Returns the named values of a physical vector (19,), rounded to 6 decimals for humans."""
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (COUNT,):
        raise ParameterError(f"expected {COUNT} parameter values, got shape {values.shape}")
    if not np.all(np.isfinite(values)):  # a params.json never holds NaN (not JSON) nor a value the shader cannot take
        bad = ", ".join(f"{name} {value}" for name, value in zip(NAMES, values, strict=True) if not np.isfinite(value))
        raise ParameterError(
            f"the parameters are not finite ({bad}): nothing is written; check the model and its weights"
        )
    return {name: round(float(v), 6) for name, v in zip(NAMES, values, strict=True)}


def parse_params_json(text: str | bytes, source: str = "params.json") -> Float[np.ndarray, " 19"]:
    """Returns the physical vector described by a params.json text (or its bytes, UTF-8).

    The file is a JSON object, either {"params": {name: value, ...}, ...other fields} (what matfit
    writes) or a flat {name: value, ...}, not both at once. Names left out take their defaults; a
    name given twice is refused (JSON would silently keep the last), and so is an integer too
    long for a float.
    """
    data = documents.parse(text, source, PARAMS_FIX, ParameterError, object_pairs_hook=_unique_keys, parse_int=float)
    return from_document(data, source)


PARAMS_FIX = 'give a params.json that matfit wrote, or a JSON object like {"roughness": 0.2}'


def from_document(data: object, source: str) -> Float[np.ndarray, " 19"]:
    """Returns the physical vector of a parsed params.json document (see `parse_params_json`)."""
    if not isinstance(data, dict):
        raise ParameterError(
            f'{source} must hold a JSON object of parameter names and values, like {{"roughness": 0.2}}'
        )
    if "params" in data:
        if not isinstance(data["params"], dict):
            raise ParameterError(
                f'{source}: "params" must be a JSON object of names and values, like {{"params": {{"roughness": 0.2}}}}'
            )
        outside = [name for name in data if name in INDEX]
        if outside:
            raise ParameterError(
                f'{source} names {", ".join(outside)} outside "params" as well: put every parameter inside "params"'
            )
        data = data["params"]
    try:
        return from_mapping(data)
    except ParameterError as error:
        raise ParameterError(f"{source}: {error}") from None


def _unique_keys(pairs: list[tuple[str, object]]) -> dict:
    """Returns the object of `pairs`; ParameterError naming every key given more than once (linear: 40 000 keys of an
    `--init` took minutes with a count per key)."""
    document = dict(pairs)
    if len(document) < len(pairs):
        seen: set[str] = set()
        repeated: set[str] = set()
        for name, _ in pairs:
            (repeated if name in seen else seen).add(name)
        raise ParameterError(f"{', '.join(map(repr, sorted(repeated)))} given more than once: keep one value")
    return document


def read_file(path: str) -> Float[np.ndarray, " 19"]:
    """Returns the physical parameter vector of a params.json file."""
    data = documents.read(path, PARAMS_FIX, ParameterError, object_pairs_hook=_unique_keys, parse_int=float)
    return from_document(data, path)


def params_document(values: Float[np.ndarray, " 19"], **extra: object) -> dict:
    """Returns the params.json document for a physical vector, with units and extra fields."""
    return {
        "params": to_mapping(values),
        "units": {p.name: p.unit for p in PARAMETERS},
        **extra,
    }


def medium_coefficients(values: Float[np.ndarray, " 19"]) -> tuple[Float[np.ndarray, " 3"], Float[np.ndarray, " 3"]]:
    """Returns (sigma_t rgb, albedo rgb) of the interior medium for a physical vector (19,).

    sigma_t = density * -ln(absorption colour), albedo = scattering fraction (grey).
    """
    colour = np.asarray(values[INDEX["medium_color_r"] : INDEX["medium_color_b"] + 1], dtype=np.float64)
    # A medium with zero extinction makes Mitsuba's distance sampling divide by zero; 1e-4 per
    # radius is invisible (the sphere then keeps 99.98% of the light).
    sigma_t = np.maximum(values[INDEX["density"]] * -np.log(colour), MINIMUM_EXTINCTION)
    albedo = np.full(3, values[INDEX["scattering"]])
    return sigma_t, albedo


def shows_medium(values: Float[np.ndarray, " 19"]) -> bool:
    """Returns whether a material's interior medium shows: some transmission and some density."""
    return bool(values[INDEX["spec_trans"]] > 0.01 and values[INDEX["density"]] > 0)
