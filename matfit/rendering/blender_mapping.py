"""matfit's 19 parameters <-> Blender 4.x's Principled BSDF and volume nodes: the one table both ways read.

`to_blender` is what the exported script sets (export.blender_inputs); `from_blender` is its inverse,
what the Blender extension reads off an artist's material (docs/blender.md#the-extension). Pure
Python on plain data (no numpy, no matfit import): `make blender-extension` copies this file into the
extension's zip, where it runs in Blender's own Python.

The table (why each constant: export.py's docstring), matfit -> Blender -> back:
- base_color_r/g/b, metallic, roughness, anisotropic, spec_trans -> Base Color, `DIRECT` inputs: the same.
- specular -> IOR: F0 = 0.08 specular = ((eta - 1) / (eta + 1))^2; back: F0 / 0.08.
- spec_tint -> Specular Tint: Disney's tint, mixed to white by metallic; back: least squares over r, g, b.
- sheen -> Sheen Weight: SHEEN_WEIGHT_SCALE x sheen x (1 - metallic), 0 through full transmission; back: divided.
- sheen_tint -> Sheen Tint: Disney's tint; back: least squares.
- clearcoat -> Coat Weight: COAT_WEIGHT_SCALE x clearcoat; back: divided.
- clearcoat_gloss -> Coat Roughness: sqrt(0.1 + (0.001 - 0.1) gloss); back: solved for gloss.
- medium (sigma_t, albedo, phase_g) -> Volume Absorption + Volume Scatter per unit of radius; back: see below.
- `FIXED` inputs are written at one value; back: a note when the material's differ, as for the `NEUTRAL` ones.

What cannot come back (`from_blender` names it in `missing` and leaves the parameter out, so that
matfit's default fills it): spec_tint of a full metal or a grey base (the tint is white whatever its
value), sheen of a metal or through full transmission, sheen_tint of a grey base, the medium of an
opaque material or of one without volume nodes, scattering of a medium that does not attenuate. The
medium's colour and density come back as one product: matfit's extinction density x -ln(colour) is
what Blender holds, so the import chooses density 1 (colour = the light kept after one radius) unless
a channel would keep less than the lowest colour, then the smallest density that fits.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

# Rec. 709 luminance, as Mitsuba's `luminance` of an RGB colour: the Disney tints divide by it.
LUMINANCE = (0.212671, 0.715160, 0.072169)
# Measured mapping constants (Cycles against Mitsuba on calibration materials that are not presets;
# see export.py's docstring).
SHEEN_WEIGHT_SCALE = 0.1
SHEEN_ROUGHNESS = 0.5
COAT_WEIGHT_SCALE = 0.5
# Parameters that are the same number on both sides, and inputs the export always writes at one value.
DIRECT = {
    "metallic": "Metallic",
    "roughness": "Roughness",
    "anisotropic": "Anisotropic",
    "spec_trans": "Transmission Weight",
}
FIXED = {
    "Diffuse Roughness": 0.0,
    "Specular IOR Level": 0.5,
    "Sheen Roughness": SHEEN_ROUGHNESS,
    "Coat IOR": 1.5,
}
# Inputs matfit's shader has no counterpart for, with the value at which they do nothing.
NEUTRAL: dict[str, float | tuple[float, float, float]] = {
    "Subsurface Weight": 0.0,
    "Emission Strength": 0.0,
    "Alpha": 1.0,
    "Thin Film Thickness": 0.0,
    "Coat Tint": (1.0, 1.0, 1.0),
}
BASE = ("base_color_r", "base_color_g", "base_color_b")
MEDIUM_COLOUR = ("medium_color_r", "medium_color_g", "medium_color_b")
MEDIUM = (*MEDIUM_COLOUR, "density", "scattering", "phase_g")
CLIP_TOLERANCE = 1e-5  # Blender keeps its inputs in float32: a value at its bound may come back just past it
TINY = 1e-6  # below it a weight, a density or a hue difference is taken as none


def eta_from_specular(specular: float) -> float:
    """Returns Mitsuba's index of refraction for `specular`: F0 = 0.08 specular = ((eta - 1) / (eta + 1))^2."""
    return 2.0 / (1.0 - math.sqrt(0.08 * max(specular, 1e-3))) - 1.0


def specular_from_eta(eta: float) -> float:
    """Returns `specular` of an index of refraction: the inverse of `eta_from_specular`."""
    return ((eta - 1.0) / (eta + 1.0)) ** 2 / 0.08


def _hue(base: Sequence[float]) -> tuple[float, ...]:
    luminance = sum(w * c for w, c in zip(LUMINANCE, base, strict=True))
    return tuple(c / luminance for c in base) if luminance > 0 else (1.0, 1.0, 1.0)


def disney_tint(base: Sequence[float], amount: float) -> tuple[float, ...]:
    """Returns 1 + amount x (base / luminance(base) - 1): the Disney tint of Mitsuba's spec_tint and sheen_tint."""
    return tuple(1.0 + amount * (h - 1.0) for h in _hue(base))


def tint_amount(base: Sequence[float], tint: Sequence[float]) -> float | None:
    """Returns the amount whose `disney_tint` of `base` is closest to `tint` (least squares), None for a grey base."""
    away = [h - 1.0 for h in _hue(base)]
    spread = sum(a * a for a in away)
    if spread < TINY:
        return None
    return sum(a * (t - 1.0) for a, t in zip(away, tint, strict=True)) / spread


def to_blender(values: dict[str, float], sigma_t: list[float], albedo: list[float]) -> tuple[dict, dict]:
    """Returns (Principled BSDF inputs, volume settings) of named parameter values, as plain data.

    `sigma_t` and `albedo` are the medium's coefficients (params.medium_coefficients).
    """
    base = tuple(values[name] for name in BASE)
    metallic = values["metallic"]

    def colour(rgb: tuple[float, ...]) -> list[float]:
        return [*map(float, rgb), 1.0]

    # One Specular Tint serves Blender's dielectric F0 and its metal edge (F82) tint; Mitsuba's
    # metal is plain Schlick on the base colour (edge tint white).
    specular_tint = tuple(t * (1.0 - metallic) + metallic for t in disney_tint(base, values["spec_tint"]))
    # Mitsuba's sheen belongs to its diffuse lobe: weighted by 1 - metallic, absent once spec_trans is 1.
    sheen = values["sheen"] * (1.0 - metallic) if values["spec_trans"] < 1.0 else 0.0
    principled = {
        "Base Color": colour(base),
        **{blender: values[name] for name, blender in DIRECT.items()},
        **FIXED,
        "IOR": eta_from_specular(values["specular"]),
        "Specular Tint": colour(specular_tint),
        "Sheen Weight": SHEEN_WEIGHT_SCALE * sheen,
        "Sheen Tint": colour(disney_tint(base, values["sheen_tint"])),
        "Coat Weight": COAT_WEIGHT_SCALE * values["clearcoat"],
        "Coat Roughness": math.sqrt(0.1 + (0.001 - 0.1) * values["clearcoat_gloss"]),
    }
    sigma_s = [a * t for a, t in zip(albedo, sigma_t, strict=True)]
    sigma_a = [(1.0 - a) * t for a, t in zip(albedo, sigma_t, strict=True)]
    scatter_density, absorb_density = max(sigma_s), max(sigma_a)
    volume = {
        "absorption_density": absorb_density,
        "absorption_color": [1.0 - a / absorb_density if absorb_density > 0 else 1.0 for a in sigma_a] + [1.0],
        "scatter_density": scatter_density,
        "scatter_color": [s / scatter_density if scatter_density > 0 else 0.0 for s in sigma_s] + [1.0],
        "anisotropy": values["phase_g"],
    }
    return principled, volume


def has_volume(principled: dict, volume: dict) -> bool:
    """Returns whether the exported material carries its medium: transmission and a medium that attenuates."""
    return principled["Transmission Weight"] > 0 and max(volume["absorption_density"], volume["scatter_density"]) > TINY


def _clip(name: str, value: float, bounds: dict, notes: list[str]) -> float:
    low, high = bounds[name]
    if value < low - CLIP_TOLERANCE or value > high + CLIP_TOLERANCE:
        notes.append(f"{name} {value:.3g} clipped to [{low:g}, {high:g}]")
    return min(max(value, low), high)


def from_blender(
    principled: dict, volume: dict | None, bounds: dict[str, tuple[float, float]]
) -> tuple[dict[str, float], dict[str, str], list[str]]:
    """Returns (values, missing, notes): the named parameters a Blender material carries, the inverse of `to_blender`.

    `principled` maps the Principled BSDF's input names to values (colours as 3 or 4 numbers);
    `volume` is `to_blender`'s volume settings per unit of the object's radius, or None without a
    medium; `bounds` maps each parameter to its (low, high) (params.PARAMETERS). `missing` names each
    parameter the material cannot determine and why (left out of `values`); `notes` says what was
    clipped into range or differs from what matfit's shader can show.
    """
    values: dict[str, float] = {}
    missing: dict[str, str] = {}
    notes: list[str] = []
    base = tuple(float(c) for c in principled["Base Color"][:3])
    for name, channel in zip(BASE, base, strict=True):
        values[name] = _clip(name, channel, bounds, notes)
    for name, blender in DIRECT.items():
        values[name] = _clip(name, float(principled[blender]), bounds, notes)
    metallic, spec_trans = values["metallic"], values["spec_trans"]
    values["specular"] = _clip("specular", specular_from_eta(float(principled["IOR"])), bounds, notes)
    clipped_base = tuple(values[name] for name in BASE)
    if metallic > 1.0 - TINY:
        missing["spec_tint"] = "a full metal's Specular Tint is white"
    else:
        tint = [(t - metallic) / (1.0 - metallic) for t in principled["Specular Tint"][:3]]
        amount = tint_amount(clipped_base, tint)
        if amount is None:
            missing["spec_tint"] = "a grey base colour's tint is white"
        else:
            values["spec_tint"] = _clip("spec_tint", amount, bounds, notes)
    if metallic > 1.0 - TINY or spec_trans >= 1.0:
        missing["sheen"] = "no sheen on a full metal or through full transmission"
    else:
        sheen = float(principled["Sheen Weight"]) / SHEEN_WEIGHT_SCALE / (1.0 - metallic)
        values["sheen"] = _clip("sheen", sheen, bounds, notes)
    amount = tint_amount(clipped_base, principled["Sheen Tint"][:3])
    if amount is None:
        missing["sheen_tint"] = "a grey base colour's tint is white"
    else:
        values["sheen_tint"] = _clip("sheen_tint", amount, bounds, notes)
    values["clearcoat"] = _clip("clearcoat", float(principled["Coat Weight"]) / COAT_WEIGHT_SCALE, bounds, notes)
    gloss = (0.1 - float(principled["Coat Roughness"]) ** 2) / (0.1 - 0.001)
    # Blender's default Coat Roughness (0.03) is sharper than Disney's glossiest coat: said only where a coat shows.
    values["clearcoat_gloss"] = _clip("clearcoat_gloss", gloss, bounds, notes if values["clearcoat"] > 0 else [])
    notes += _unshown(principled)
    _medium_from_blender(volume, spec_trans, bounds, values, missing, notes)
    return values, missing, notes


def _unshown(principled: dict) -> list[str]:
    """Returns a note for each input matfit's shader holds at another value (`FIXED`) or has no counterpart for."""
    notes = []
    for blender, fixed in FIXED.items():
        if blender in principled and abs(float(principled[blender]) - fixed) > 1e-4:
            notes.append(f"{blender} {float(principled[blender]):.3g} shown as {fixed:g}")
    for blender, neutral in NEUTRAL.items():
        value = principled.get(blender)
        if value is None:
            continue
        if isinstance(neutral, tuple):
            differs = any(abs(float(v) - n) > 1e-4 for v, n in zip(value[:3], neutral, strict=True))
        else:
            differs = abs(float(value) - neutral) > 1e-4
        if differs:
            notes.append(f"{blender} ignored (matfit's shader has none)")
    return notes


def _medium_from_blender(
    volume: dict | None, spec_trans: float, bounds: dict, values: dict, missing: dict, notes: list[str]
) -> None:
    if spec_trans <= 0.0 or volume is None:
        reason = "an opaque material shows no medium" if spec_trans <= 0.0 else "the material has no volume nodes"
        missing.update({name: reason for name in MEDIUM})
        if volume is not None:
            notes.append("the volume is hidden behind Transmission Weight 0")
        return
    sigma_a = [volume["absorption_density"] * (1.0 - c) for c in volume["absorption_color"][:3]]
    sigma_s = [volume["scatter_density"] * c for c in volume["scatter_color"][:3]]
    sigma_t = [a + s for a, s in zip(sigma_a, sigma_s, strict=True)]
    if max(sigma_t) <= TINY:
        missing.update({name: "the volume does not attenuate" for name in MEDIUM})
        return
    values["phase_g"] = _clip("phase_g", float(volume["anisotropy"]), bounds, notes)
    albedo = sum(sigma_s) / sum(sigma_t)
    per_channel = [s / t if t > TINY else albedo for s, t in zip(sigma_s, sigma_t, strict=True)]
    if max(per_channel) - min(per_channel) > 1e-3:
        notes.append("the scattering colour's hue ignored (matfit's medium scatters grey)")
    values["scattering"] = _clip("scattering", albedo, bounds, notes)
    lowest_colour = bounds[MEDIUM_COLOUR[0]][0]
    density = max(1.0, max(sigma_t) / -math.log(lowest_colour))
    values["density"] = _clip("density", density, bounds, notes)
    for name, extinction in zip(MEDIUM_COLOUR, sigma_t, strict=True):
        values[name] = _clip(name, math.exp(-extinction / values["density"]), bounds, notes)
