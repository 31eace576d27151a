# The script that `matfit fit --blender` writes is this file, filled in by `export.blender_script`:
# the __MARKERS__ replaced and NAME, PRINCIPLED and VOLUME set, these comment lines left out. It runs
# inside Blender (bpy 4.x). `blender_scene` builds the test scene's own materials with `node_tree`, so
# Blender's copy of the scene and the exported material share one way of building a node tree.
"""The matfit material "__NAME__" for Blender 4.x (made for 4.5): a Principled BSDF, and Volume
Absorption + Volume Scatter for the interior medium.

Run it from Blender's Text Editor (Text > Run Script) with the meshes to shade selected, or from a
shell: `blender scene.blend --background --python this.py` (the objects selected in scene.blend).
It creates (or rebuilds) the material "__NAME__" and puts it in every material slot of the selected
meshes, linked to the object (slot link "Object"), so that other objects sharing a mesh keep their
materials; a selected mesh without slots gets one. Nothing else is changed.

How matfit's parameters (Mitsuba 3's Disney-style `principled` BSDF) were mapped:
- base colour, metallic, roughness, anisotropic, spec_trans: the same values (roughness squared is
  the GGX alpha in both); distribution GGX, since Mitsuba's is single-scattering GGX.
- IOR: Mitsuba's index of refraction from `specular` (F0 = 0.08 specular, 0.5 -> 1.5), for the
  reflection and the refraction alike; Specular IOR Level stays at 0.5.
- Specular Tint, Sheen Tint: Disney's tints, white mixed towards base colour / luminance.
- Sheen Weight = __SHEEN_SCALE__ x sheen x (1 - metallic) (Mitsuba's sheen belongs to its diffuse
  lobe), Sheen Roughness __SHEEN_ROUGHNESS__; Coat Weight = __COAT_SCALE__ x clearcoat, Coat Roughness =
  the square root of Disney's clearcoat alpha (0.1 at gloss 0 to 0.001 at gloss 1), Coat IOR 1.5.
- Medium: absorption and scattering coefficients as in Mitsuba, per unit of matfit's sphere radius;
  set OBJECT_RADIUS to your object's radius (scene units) to keep the look on a larger object.

Where Blender's Principled BSDF differs by design (no mapping can fix it):
- diffuse: Blender's is Lambertian; Disney's brightens rough surfaces at grazing angles
  (retro-reflection) and darkens smooth ones;
- sheen: Blender's is a microfibre layer, Disney's a Schlick-weighted term added to the diffuse;
- coat: Blender's is a dielectric layer that also dims the base beneath it, Disney's an added
  GTR1 lobe with longer tails;
- Specular Tint also tints a metal's edges (F82) in Blender: Mitsuba's metals are plain Schlick, so
  metals get white; a partly metallic material gets a mixture;
- anisotropic highlights follow the tangent: Blender's default runs around the object's local Z
  axis, matfit's sphere's around the axis pointing at the camera.
How close it comes: `matfit blender-check` renders both (docs/blender.md#the-check).
"""

import bpy

NAME = "__NAME__"
# The Principled BSDF's inputs, mapped from matfit's parameters as the header says, and the interior
# medium: densities and colours of Volume Absorption and Volume Scatter.
PRINCIPLED = {}
VOLUME = {}
OBJECT_RADIUS = 1.0  # the medium's densities are per unit of matfit's sphere radius


def node_tree(owner):
    """Returns the (nodes, links) of the node tree of `owner` (a material or a world), emptied."""
    owner.use_nodes = True
    owner.node_tree.nodes.clear()
    return owner.node_tree.nodes, owner.node_tree.links


def build_material():
    """Returns the material NAME with its node tree rebuilt."""
    material = bpy.data.materials.get(NAME) or bpy.data.materials.new(NAME)
    nodes, links = node_tree(material)
    output = nodes.new("ShaderNodeOutputMaterial")
    bsdf = nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.distribution = "GGX"
    for key, value in PRINCIPLED.items():
        bsdf.inputs[key].default_value = value
    links.new(bsdf.outputs["BSDF"], output.inputs["Surface"])
    if PRINCIPLED["Transmission Weight"] > 0 and max(VOLUME["absorption_density"], VOLUME["scatter_density"]) > 1e-6:
        absorption = nodes.new("ShaderNodeVolumeAbsorption")
        absorption.inputs["Color"].default_value = VOLUME["absorption_color"]
        absorption.inputs["Density"].default_value = VOLUME["absorption_density"] / OBJECT_RADIUS
        scatter = nodes.new("ShaderNodeVolumeScatter")
        scatter.inputs["Color"].default_value = VOLUME["scatter_color"]
        scatter.inputs["Density"].default_value = VOLUME["scatter_density"] / OBJECT_RADIUS
        scatter.inputs["Anisotropy"].default_value = VOLUME["anisotropy"]
        both = nodes.new("ShaderNodeAddShader")
        links.new(absorption.outputs["Volume"], both.inputs[0])
        links.new(scatter.outputs["Volume"], both.inputs[1])
        links.new(both.outputs["Shader"], output.inputs["Volume"])
        material.cycles.homogeneous_volume = True
    return material


def assign(material):
    """Puts `material` in every slot of the selected meshes, linked to the object; returns them."""
    meshes = [obj for obj in bpy.context.selected_objects if obj.type == "MESH"]
    for obj in meshes:
        if not obj.material_slots:
            obj.data.materials.append(None)
        for slot in obj.material_slots:
            slot.link = "OBJECT"
            slot.material = material
    return meshes


if __name__ == "__main__":
    meshes = assign(build_material())
    hint = "" if meshes else "; select meshes and run again to assign it"
    print(f"matfit: material {NAME!r} on {len(meshes)} selected mesh(es){hint}")
