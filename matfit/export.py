"""Exports of a fitted material: Mitsuba 3 XML and a Blender 4.x Python script.

Mitsuba: the same `principled` BSDF and `homogeneous` medium the test scene renders (scene.py),
with ids `matfit-material` and `matfit-interior`, inside a `<scene>` so that another scene can
`<include filename="mat.xml"/>` it and use `<ref id="matfit-material"/>` on a shape, plus
`<ref name="interior" id="matfit-interior"/>` for glass with a medium. Every principled parameter
is written, even at 0: Mitsuba switches a lobe on when its parameter is present, and the fit was
made with every lobe present. (`mi.parser.write_string` drops the ids of top-level objects, so
the XML is written here from the same plain data.)

Blender (Principled BSDF of 4.x, whose inputs differ from the Disney/Mitsuba names):

| matfit | Blender 4.x | how |
|---|---|---|
| base_color_r/g/b | Base Color | same linear RGB |
| metallic, roughness | Metallic, Roughness | same |
| anisotropic | Anisotropic | same |
| specular | Specular IOR Level | same value (0.5 = IOR 1.5, Blender's default) |
| spec_tint | Specular Tint | colour white + spec_tint x (base colour - white) |
| sheen | Sheen Weight | same |
| sheen_tint | Sheen Tint | colour white + sheen_tint x (base colour - white) |
| clearcoat | Coat Weight | same |
| clearcoat_gloss | Coat Roughness | 0.1 + (0.001 - 0.1) x gloss, Disney's clearcoat roughness |
| spec_trans | Transmission Weight | same, IOR 1.5 |
| medium (6 values) | Volume Absorption + Volume Scatter | sigma_a = (1 - albedo) sigma_t, sigma_s = albedo sigma_t, densities per scene unit (the test sphere has radius 1) |

What does not map exactly: Blender's principled model is not Disney's (its sheen and coat lobes
differ, its Specular Tint is a colour), Blender's anisotropy direction follows the tangent of
the mesh, and a coloured extinction is approximated by one density and a colour per node.
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree

import numpy as np

from matfit import params, scene

MATERIAL_ID = "matfit-material"
MEDIUM_ID = "matfit-interior"


def _value_element(parent: ElementTree.Element, name: str, value: object) -> None:
    if isinstance(value, dict) and value.get("type") == "rgb":
        ElementTree.SubElement(parent, "rgb", name=name, value=" ".join(repr(float(v)) for v in value["value"]))
    elif isinstance(value, dict):
        child = ElementTree.SubElement(parent, "phase", type=value["type"], name=name)
        for key, item in value.items():
            if key != "type":
                _value_element(child, key, item)
    else:
        ElementTree.SubElement(parent, "float", name=name, value=repr(float(value)))


def _object(root: ElementTree.Element, tag: str, identifier: str, description: dict) -> None:
    element = ElementTree.SubElement(root, tag, type=description["type"], id=identifier)
    for key, value in description.items():
        if key != "type":
            _value_element(element, key, value)


def mitsuba_xml(values: np.ndarray) -> str:
    """Returns a Mitsuba 3 XML scene fragment holding the material's BSDF and interior medium."""
    root = ElementTree.Element("scene", version="3.0.0")
    root.append(
        ElementTree.Comment(' matfit: use with <ref id="matfit-material"/>, and <ref name="interior" id="matfit-interior"/> for a medium ')
    )
    _object(root, "bsdf", MATERIAL_ID, scene.bsdf(values))
    _object(root, "medium", MEDIUM_ID, scene.medium(values))
    ElementTree.indent(root)
    return ElementTree.tostring(root, encoding="unicode") + "\n"


def blender_inputs(values: np.ndarray) -> tuple[dict, dict]:
    """Returns (Principled BSDF inputs, volume settings) for Blender 4.x, as plain data."""
    v = dict(zip(params.NAMES, (float(x) for x in values), strict=True))
    base = np.array([v["base_color_r"], v["base_color_g"], v["base_color_b"]])

    def tint(amount: float) -> list[float]:
        return [*map(float, 1.0 + amount * (base - 1.0)), 1.0]

    principled = {
        "Base Color": [*map(float, base), 1.0],
        "Metallic": v["metallic"],
        "Roughness": v["roughness"],
        "Anisotropic": v["anisotropic"],
        "Specular IOR Level": v["specular"],
        "Specular Tint": tint(v["spec_tint"]),
        "Sheen Weight": v["sheen"],
        "Sheen Tint": tint(v["sheen_tint"]),
        "Coat Weight": v["clearcoat"],
        "Coat Roughness": 0.1 + (0.001 - 0.1) * v["clearcoat_gloss"],
        "Transmission Weight": v["spec_trans"],
        "IOR": 1.5,
    }
    sigma_t, albedo = params.medium_coefficients(values)
    sigma_s, sigma_a = albedo * sigma_t, (1.0 - albedo) * sigma_t
    scatter_density, absorb_density = float(sigma_s.max()), float(sigma_a.max())
    volume = {
        "absorption_density": absorb_density,
        "absorption_color": [float(1.0 - a / absorb_density) if absorb_density > 0 else 1.0 for a in sigma_a] + [1.0],
        "scatter_density": scatter_density,
        "scatter_color": [float(s / scatter_density) if scatter_density > 0 else 0.0 for s in sigma_s] + [1.0],
        "anisotropy": v["phase_g"],
    }
    return principled, volume


BLENDER_TEMPLATE = '''"""Builds the matfit material in Blender 4.x: run in Blender's Text Editor or `blender -P this.py`.

Creates (or replaces) the material "{name}" and assigns it to the selected objects.
"""

import bpy

PRINCIPLED = {principled}
VOLUME = {volume}

material = bpy.data.materials.get("{name}") or bpy.data.materials.new("{name}")
material.use_nodes = True
nodes, links = material.node_tree.nodes, material.node_tree.links
nodes.clear()
output = nodes.new("ShaderNodeOutputMaterial")
bsdf = nodes.new("ShaderNodeBsdfPrincipled")
for key, value in PRINCIPLED.items():
    bsdf.inputs[key].default_value = value
links.new(bsdf.outputs["BSDF"], output.inputs["Surface"])
if PRINCIPLED["Transmission Weight"] > 0 and (VOLUME["absorption_density"] > 1e-6 or VOLUME["scatter_density"] > 1e-6):
    absorption = nodes.new("ShaderNodeVolumeAbsorption")
    absorption.inputs["Color"].default_value = VOLUME["absorption_color"]
    absorption.inputs["Density"].default_value = VOLUME["absorption_density"]
    scatter = nodes.new("ShaderNodeVolumeScatter")
    scatter.inputs["Color"].default_value = VOLUME["scatter_color"]
    scatter.inputs["Density"].default_value = VOLUME["scatter_density"]
    scatter.inputs["Anisotropy"].default_value = VOLUME["anisotropy"]
    mix = nodes.new("ShaderNodeAddShader")
    links.new(absorption.outputs["Volume"], mix.inputs[0])
    links.new(scatter.outputs["Volume"], mix.inputs[1])
    links.new(mix.outputs["Shader"], output.inputs["Volume"])
for obj in bpy.context.selected_objects:
    if obj.type == "MESH":
        obj.data.materials.clear()
        obj.data.materials.append(material)
'''


def blender_script(values: np.ndarray, name: str = "matfit") -> str:
    """Returns a Python script that builds the material in Blender 4.x."""
    principled, volume = blender_inputs(values)
    return BLENDER_TEMPLATE.format(name=name, principled=repr(principled), volume=repr(volume))
