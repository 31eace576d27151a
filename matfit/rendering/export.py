"""Exports of a fitted material: Mitsuba 3 XML and a Blender 4.x Python script.

Mitsuba: the same `principled` BSDF and `homogeneous` medium the test scene renders (scene.py),
with ids `matfit-material` and `matfit-interior`, inside a `<scene>` so that another scene can
`<include filename="mat.xml"/>` it and use `<ref id="matfit-material"/>` on a shape, plus
`<ref name="interior" id="matfit-interior"/>` for glass with a medium. Every principled parameter
is written, even at 0: Mitsuba switches a lobe on when its parameter is present, and the fit was
made with every lobe present. (`mi.parser.write_string` drops the ids of top-level objects, so
the XML is written here from the same plain data.)

Blender (Principled BSDF of 4.x, made for 4.5; checked in Cycles by `matfit blender-check`):

- base_color_r/g/b -> Base Color: the same linear RGB.
- metallic, roughness, anisotropic -> Metallic, Roughness, Anisotropic (Diffuse Roughness 0): the same (alpha =
  roughness^2 and the same anisotropic aspect in both); distribution GGX, not Blender's default multiscatter GGX
  (rough gold: RMSE 2.9 against 25.7).
- specular -> IOR: Mitsuba's eta from specular, F0 = 0.08 specular (0.5 -> 1.5), for reflection and refraction;
  Specular IOR Level 0.5.
- spec_tint -> Specular Tint: Disney's tint, white + spec_tint x (base / luminance(base) - white), mixed to white
  by metallic (Blender also tints metal edges with it).
- sheen, sheen_tint -> Sheen Weight, Sheen Tint, Sheen Roughness: SHEEN_WEIGHT_SCALE x sheen x (1 - metallic), none
  when spec_trans is 1; Disney's tint; roughness SHEEN_ROUGHNESS.
- clearcoat, clearcoat_gloss -> Coat Weight, Coat Roughness: COAT_WEIGHT_SCALE x clearcoat; the square root of
  Disney's alpha 0.1 + (0.001 - 0.1) x gloss; Coat IOR 1.5.
- spec_trans -> Transmission Weight: the same (both tint by sqrt(base colour) per crossing).
- medium (6 values) -> Volume Absorption + Volume Scatter: sigma_a = (1 - albedo) sigma_t, sigma_s = albedo sigma_t
  per unit of the sphere's radius; the script's OBJECT_RADIUS rescales them.

The sheen and coat constants were measured: the lobe's own contribution (image with the lobe
minus image without, 64 px, 512 spp, over the sphere) in Cycles against Mitsuba, on calibration
materials that are not presets (grey and blue diffuse with sheen; two coated diffuse materials,
gloss 1 and 0.3). Mitsuba's Disney sheen is faint (0.4-0.6 of 255 on average over the sphere);
Blender's microfibre sheen at weight 1 and roughness 0.5 gives 9 times as much light: weight 0.1
at roughness 0.5 gives 0.9 times and the smallest error (0.47 and 0.35, against 0.86 and 0.55 with
no sheen at all; weights 0.2-1 and roughness 0.1-0.8 were tried). For the coat, weight 0.5 x
clearcoat gives the smallest error (1.98 and 1.86, against 2.61 and 1.94 at 0.25 and 4.17 and 3.84
at 1): Blender's coat at weight 1 adds as much light as Disney's, but in a sharper highlight, since
Disney's GTR1 lobe has long tails.

Blender's Diffuse Roughness (Oren-Nayar) does not stand in for Disney's rough diffuse: set to the
roughness it made the sphere worse (RMSE 9.1 against 4.5 with Lambert on a grey of roughness
0.9, 6.2 against 4.5 at 0.4), so it stays 0.

What Blender's Principled BSDF does differently by design is listed in the script's own header
(`blender_material`): Lambertian diffuse, microfibre sheen, a layered coat, the metal edge tint,
and the tangent that anisotropy follows.
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree

import numpy as np

from matfit import params, shipped
from matfit.rendering import blender_mapping, scene

MATERIAL_ID = "matfit-material"
MEDIUM_ID = "matfit-interior"


def _value_element(parent: ElementTree.Element, name: str, value: dict | float) -> None:
    if isinstance(value, dict) and value.get("type") == "rgb":
        ElementTree.SubElement(parent, "rgb", name=name, value=" ".join(repr(float(v)) for v in value["value"]))
    elif isinstance(value, dict):
        child = ElementTree.SubElement(parent, "phase", type=value["type"], name=name)
        for key, item in value.items():
            if key != "type":
                _value_element(child, key, item)
    else:
        ElementTree.SubElement(parent, "float", name=name, value=repr(float(value)))


def element(tag: str, description: dict, **attributes: str) -> ElementTree.Element:
    """Returns a Mitsuba XML element of plain `mi.load_dict` data (`scene.bsdf`, `scene.medium`): its type and
    `attributes` (an id, a name), then each value as a float, rgb or nested phase element. The export and a scene
    file's fitted shape (`scene_file.xml`) write the material alike."""
    made = ElementTree.Element(tag, {"type": description["type"], **attributes})
    for key, value in description.items():
        if key != "type":
            _value_element(made, key, value)
    return made


def mitsuba_xml(values: np.ndarray) -> str:
    """Returns a Mitsuba 3 XML scene fragment holding the material's BSDF and interior medium."""
    root = ElementTree.Element("scene", version="3.0.0")
    root.append(
        ElementTree.Comment(
            ' matfit: use with <ref id="matfit-material"/>, '
            'and <ref name="interior" id="matfit-interior"/> for a medium '
        )
    )
    root.append(element("bsdf", scene.bsdf(values), id=MATERIAL_ID))
    root.append(element("medium", scene.medium(values), id=MEDIUM_ID))
    ElementTree.indent(root)
    return ElementTree.tostring(root, encoding="unicode") + "\n"


# The mapping's constants and formulas live in blender_mapping (the import reads the same table);
# named here too, since the script's header and the tests speak of them as the export's.
SHEEN_WEIGHT_SCALE = blender_mapping.SHEEN_WEIGHT_SCALE
SHEEN_ROUGHNESS = blender_mapping.SHEEN_ROUGHNESS
COAT_WEIGHT_SCALE = blender_mapping.COAT_WEIGHT_SCALE
eta_from_specular = blender_mapping.eta_from_specular


def blender_inputs(values: np.ndarray) -> tuple[dict, dict]:
    """Returns (Principled BSDF inputs, volume settings) for Blender 4.x, as plain data (blender_mapping.to_blender)."""
    sigma_t, albedo = params.medium_coefficients(values)
    named = dict(zip(params.NAMES, map(float, values), strict=True))
    return blender_mapping.to_blender(named, list(map(float, sigma_t)), list(map(float, albedo)))


def from_blender_inputs(principled: dict, volume: dict | None) -> tuple[np.ndarray, dict[str, str], list[str]]:
    """Returns (physical vector (19,), missing, notes) of Blender inputs: the import, defaults filled."""
    bounds = {p.name: (p.low, p.high) for p in params.PARAMETERS}
    values, missing, notes = blender_mapping.from_blender(principled, volume, bounds)
    return params.from_mapping(values), missing, notes


SCRIPT = shipped.PACKAGE / "rendering" / "blender_material.py"  # filled in per material


def blender_script(values: np.ndarray, name: str = "matfit") -> str:
    """Returns a Python script that builds the material in Blender 4.x: `blender_material.py`, filled in."""
    principled, volume = blender_inputs(values)
    if not name.isprintable() or '"' in name or "\\" in name:
        raise ValueError(f"material name {name!r} must be printable, without quotes or backslashes")
    replacements = {  # the constants first: a name cannot hide one
        "PRINCIPLED = {}": f"PRINCIPLED = {principled!r}",
        "VOLUME = {}": f"VOLUME = {volume!r}",
        "__SHEEN_SCALE__": f"{SHEEN_WEIGHT_SCALE:g}",
        "__SHEEN_ROUGHNESS__": f"{SHEEN_ROUGHNESS:g}",
        "__COAT_SCALE__": f"{COAT_WEIGHT_SCALE:g}",
        "__NAME__": name,
    }
    with open(SCRIPT) as file:
        source = file.read()
    script = source[source.index('"""') :]  # from the script's own header: the comments above it are matfit's
    for marker, text in replacements.items():
        script = script.replace(marker, text)
    return script
