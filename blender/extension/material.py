"""A Blender material's node tree as the plain data blender_mapping reads and writes: Principled BSDF inputs, a volume.

`write` builds the fitted material from blender_mapping.to_blender's inputs with the node tree of the
exported script (matfit/rendering/blender_material.py), and `assign` puts it on the selected meshes as
that script does; the extension runs no script. `slots` saves what `assign` changes and `restore` puts
it back (a fit that fails or is cancelled after its first answer was shown).

What matfit's shader can hold: a Principled BSDF on the Material Output's Surface, and on its Volume
Volume Absorption, Volume Scatter (alone or added) or a Principled Volume. Another shader on the
Surface (Glass, Emission, a Mix, a node group) is refused with one line that says what to use. An
input driven by a link (a texture, a node group) is read at the value it shows when unlinked, and
said so; so is a volume that cannot be read.
"""

import bpy

PRINCIPLED = "ShaderNodeBsdfPrincipled"
VOLUME_SHADERS = ("ShaderNodeVolumeAbsorption", "ShaderNodeVolumeScatter", "ShaderNodeVolumePrincipled")


class MaterialError(Exception):
    """The material cannot be read as matfit's shader; the message is one line for Blender's report."""


def _source(socket):
    """Returns the node feeding `socket` through any reroutes, or None."""
    while socket.is_linked:
        node = socket.links[0].from_node
        if node.bl_idname != "NodeReroute":
            return node
        socket = node.inputs[0]
    return None


def _describe(node):
    """Returns how the report names a node: its kind, and its own name where the artist gave one."""
    if node.bl_idname == "ShaderNodeGroup":
        return f"the node group {node.node_tree.name if node.node_tree else node.name!r}"
    named = f" {node.name!r}" if node.name != node.bl_label else ""
    return f"{node.bl_label}{named}"


def _value(socket):
    value = socket.default_value
    return [float(v) for v in value] if hasattr(value, "__len__") else float(value)


def read(material, radius):
    """Returns (principled inputs, volume per unit of `radius` or None, notes), or raises MaterialError."""
    if material is None:
        raise MaterialError("matfit: the active object has no material: add one with a Principled BSDF")
    where = f"matfit: material {material.name!r}"
    if not material.use_nodes or material.node_tree is None:
        raise MaterialError(f"{where} does not use nodes: turn on Use Nodes (a Principled BSDF)")
    output = material.node_tree.get_output_node("CYCLES")
    surface = _source(output.inputs["Surface"]) if output is not None else None
    if surface is None:
        raise MaterialError(f"{where} has no shader on its Material Output's Surface: connect a Principled BSDF")
    if surface.bl_idname != PRINCIPLED:
        raise MaterialError(
            f"{where}: its Surface is {_describe(surface)}, which matfit cannot represent; "
            "use a Principled BSDF there (for glass: Transmission Weight 1)"
        )
    principled, notes = {}, []
    linked = []
    for socket in surface.inputs:
        if not hasattr(socket, "default_value") or socket.name in principled:
            continue
        principled[socket.name] = _value(socket)
        source = _source(socket)
        if source is not None and socket.name not in ("Normal", "Tangent", "Coat Normal"):
            linked.append(f"{socket.name} ({_describe(source)})")
    if linked:
        notes.append(f"{', '.join(linked)} read at their unlinked values")
    if surface.inputs["Normal"].is_linked or surface.inputs["Coat Normal"].is_linked:
        notes.append("the normal map ignored")
    if surface.distribution != "GGX":
        notes.append(f"distribution {surface.distribution} shown as GGX")
    volume = _volume(_source(output.inputs["Volume"]), radius, notes)
    return principled, volume, notes


def _volume(node, radius, notes):
    """Returns the volume settings of blender_mapping per unit of `radius`, or None without a readable volume."""
    if node is None:
        return None
    sigma_a, sigma_s, anisotropy = [0.0] * 3, [0.0] * 3, []
    pending = [node]
    while pending:
        node = pending.pop()
        kind = node.bl_idname
        if kind == "ShaderNodeAddShader":
            pending += [source for source in map(_source, node.inputs) if source is not None]
            continue
        if kind not in VOLUME_SHADERS:
            notes.append(f"the Volume's {_describe(node)} ignored: no medium")
            return None
        density = node.inputs["Density"].default_value * radius
        colour = list(node.inputs["Color"].default_value)[:3]
        if kind == "ShaderNodeVolumeAbsorption":
            sigma_a = [a + density * (1.0 - c) for a, c in zip(sigma_a, colour, strict=True)]
        elif kind == "ShaderNodeVolumeScatter":
            sigma_s = [s + density * c for s, c in zip(sigma_s, colour, strict=True)]
            anisotropy.append(node.inputs["Anisotropy"].default_value)
        else:
            # Cycles' Principled Volume: scattering Color x Density, absorption
            # max(1 - Color, 0) x max(1 - Absorption Color, 0) x Density.
            absorption = list(node.inputs["Absorption Color"].default_value)[:3]
            sigma_s = [s + density * c for s, c in zip(sigma_s, colour, strict=True)]
            sigma_a = [
                a + density * max(1 - c, 0) * max(1 - b, 0) for a, c, b in zip(sigma_a, colour, absorption, strict=True)
            ]
            anisotropy.append(node.inputs["Anisotropy"].default_value)
            if (
                node.inputs["Emission Strength"].default_value > 0
                or node.inputs["Blackbody Intensity"].default_value > 0
            ):
                notes.append("the Principled Volume's emission ignored")
    absorb_density, scatter_density = max(sigma_a), max(sigma_s)
    return {
        "absorption_density": absorb_density,
        "absorption_color": [1.0 - a / absorb_density if absorb_density > 0 else 1.0 for a in sigma_a],
        "scatter_density": scatter_density,
        "scatter_color": [s / scatter_density if scatter_density > 0 else 0.0 for s in sigma_s],
        "anisotropy": sum(anisotropy) / len(anisotropy) if anisotropy else 0.0,
    }


def write(materials, name, principled, volume, with_volume):
    """Returns the material `name` of `materials` (bpy.data.materials), its node tree rebuilt as the script builds it.

    `with_volume` is blender_mapping.has_volume: Volume Absorption + Volume Scatter behind the
    transmission, per unit of matfit's sphere radius (the script's OBJECT_RADIUS 1).
    """
    material = materials.get(name) or materials.new(name)
    material.use_nodes = True
    nodes, links = material.node_tree.nodes, material.node_tree.links
    nodes.clear()
    output = nodes.new("ShaderNodeOutputMaterial")
    bsdf = nodes.new(PRINCIPLED)
    bsdf.distribution = "GGX"
    for key, value in principled.items():
        bsdf.inputs[key].default_value = value
    links.new(bsdf.outputs["BSDF"], output.inputs["Surface"])
    if with_volume:
        absorption = nodes.new("ShaderNodeVolumeAbsorption")
        absorption.inputs["Color"].default_value = volume["absorption_color"]
        absorption.inputs["Density"].default_value = volume["absorption_density"]
        scatter = nodes.new("ShaderNodeVolumeScatter")
        scatter.inputs["Color"].default_value = volume["scatter_color"]
        scatter.inputs["Density"].default_value = volume["scatter_density"]
        scatter.inputs["Anisotropy"].default_value = volume["anisotropy"]
        both = nodes.new("ShaderNodeAddShader")
        links.new(absorption.outputs["Volume"], both.inputs[0])
        links.new(scatter.outputs["Volume"], both.inputs[1])
        links.new(both.outputs["Shader"], output.inputs["Volume"])
        material.cycles.homogeneous_volume = True
    return material


def assign(material, objects):
    """Puts `material` in every slot of the meshes among `objects`, linked to the object; returns those meshes."""
    meshes = [obj for obj in objects if obj.type == "MESH"]
    for obj in meshes:
        if not obj.material_slots:
            obj.data.materials.append(None)
        for slot in obj.material_slots:
            slot.link = "OBJECT"
            slot.material = material
    return meshes


def slots(objects):
    """Returns what `assign` changes on the meshes among `objects`, for `restore`: by object name, its active slot and,
    slot by slot, the slot's link and the name of the object's own material there (or None)."""
    saved = {}
    for obj in objects:
        if obj.type != "MESH":
            continue
        own = []
        for slot in obj.material_slots:
            link = slot.link
            slot.link = "OBJECT"  # the object's own material, also where the slot shows the mesh's
            own.append((link, slot.material.name if slot.material is not None else None))
            slot.link = link
        saved[obj.name] = (obj.active_material_index, own)
    return saved


def restore(saved):
    """Puts back on the objects still there what `slots` saved: each slot's own material and link, and the slots
    `assign` added removed (in Edit Mode, where Blender removes none, left empty)."""
    for name, (active, own) in saved.items():
        obj = bpy.data.objects.get(name)
        if obj is None or obj.type != "MESH":
            continue
        for index, slot in enumerate(obj.material_slots):
            link, material = own[index] if index < len(own) else ("DATA", None)  # an added slot: the mesh's holds None
            slot.link = "OBJECT"
            slot.material = bpy.data.materials.get(material) if material is not None else None
            slot.link = link
        # the mesh's slot and the object's both: removing the mesh's alone (materials.pop) keeps the object's
        while len(obj.material_slots) > len(own):
            obj.active_material_index = len(obj.material_slots) - 1
            try:
                with bpy.context.temp_override(object=obj):
                    bpy.ops.object.material_slot_remove()
            except RuntimeError:  # "Unable to remove material slot in edit mode"
                break
        obj.active_material_index = active
