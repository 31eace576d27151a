"""The current Blender scene as a Mitsuba 3 scene folder, for `matfit render --scene` and `matfit fit --scene`.

Pure bpy and NumPy (no add-on, no Mitsuba): `export` writes scene.xml, one binary PLY per evaluated mesh
(per material slot) in meshes/, the world's image as PFM where it has one, and matfit-export.json (each
object's shape id, the notes). Everything is in Blender's world space (z up); Mitsuba has no up axis.
Each shape's id is its object's name made safe (letters, digits, _ and -; a letter first; made unique
with -2, -3 ...), so that one export serves a fit of any of its objects; `Export.ids` maps names to ids.

The conversions, each measured against Cycles in a test (tests/test_blender_scene_export.py,
docs/blender.md, "Your own scene"):
- meshes: evaluated (modifiers as the viewport shows them), triangulated, world-space positions, the
  corner (split) normals, so flat and sharp edges stay sharp, and the active UV map (v turned: Mitsuba's
  bitmaps put v = 0 at the top row, Blender's at the bottom), vertices split where a corner's normal or UV
  differs, winding reversed under a mirroring transform;
- camera: `perspective`, the field of view along the axis the sensor fit chooses, `to_world` the camera's
  matrix without its scale times diag(-1, 1, -1) (Blender's camera looks down -z with +y up, Mitsuba's
  down +z with +y up and +x to the left), the film the render resolution x its percentage;
- lights (power P = Power x 2^Exposure, times the light's colour): area light radiance P / (pi A) with A
  its world area (P / pi with Normalize off), a one-sided rectangle or disk facing the light's -z, black,
  so it reflects nothing; point intensity P / (4 pi); spot the same intensity, `cutoff_angle` half the
  Spot Size, `beam_width` where the blend's smoothstep reaches full; sun (`directional`) irradiance =
  Strength;
- world: the Background's Color x Strength as a `constant` emitter, or an Environment Texture's image
  (equirectangular, unmapped) as an `envmap` turned from Blender's z-up longitude to Mitsuba's y-up one;
- materials: a Principled BSDF through blender_mapping.from_blender, the extension's own reading
  (`material.read`), to matfit's 19 values, written as Mitsuba's `principled` with the keys matfit's
  scene.bsdf writes (parameters the material cannot decide take matfit's defaults); with Specular IOR
  Level 0 (no specular) as `diffuse` of its base colour (measured: such a ground as principled reads
  10-13% brighter than Cycles); a volume behind transmission as a homogeneous interior medium, per
  world unit; no material as Cycles' default grey (diffuse 0.8); any other shader as that grey, said.

What the export cannot carry is a list of one-line notes (`Export.notes`): textures and node groups on
inputs (read at their unlinked values), Multiscatter GGX (shown as GGX), more than one material on the
fitted object (its active one is fitted), modifiers that fail to evaluate or differ between viewport and render,
point/spot radius (a point), a sun's angle (a direction), light nodes and colour temperature, square
spots, area spread, a camera's shift or depth of field, a world shader other than Background.
"""

import json
import math
import os
import re
import xml.etree.ElementTree as ElementTree

import numpy as np

from . import blender_mapping, material

MESHES = "meshes"
CONVERTIBLE = ("MESH", "CURVE", "SURFACE", "META", "FONT", "CURVES", "POINTCLOUD")
DEFAULT_GREY = 0.8  # Cycles' surface without a material: diffuse of this albedo
SPOT_BLEND_FLOOR = 1e-3  # degrees between Mitsuba's cutoff and beam width at Spot Blend 0 (it divides by it)
# Mitsuba's envmap looks up direction (x, y, z) of its local frame at u = atan2(x, -z) / 2 pi, v = acos(y) / pi;
# Blender's world image at u = 1/2 - atan2(y, x) / 2 pi, v = acos(z) / pi from the top: the local frame's x, y, z
# are Blender's y, z, x.
ENVMAP_TO_WORLD = np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
CAMERA_AXES = np.diag([-1.0, 1.0, -1.0, 1.0])  # Blender's camera frame -> Mitsuba's
FACING_MINUS_Z = np.diag([1.0, -1.0, -1.0, 1.0])  # a rotation: Mitsuba's +z (rectangle normal, spot axis) to -z


class ExportError(Exception):
    """The scene cannot be exported; the message is one line for Blender's report."""


class Export:
    """What `export` wrote: the XML file's path, each object's shape id, the fitted one's, the notes, and the fitted
    object's material as matfit's 19 named values (its shape's BSDF in the file, the picture's source)."""

    def __init__(self, path, ids, fitted, notes, values):
        self.path, self.ids, self.fitted, self.notes, self.values = path, ids, fitted, notes, values


def shape_id(name, taken):
    """Returns `name` as a Mitsuba id not in `taken` (and adds it): letters, digits, _ and -, a letter first."""
    safe = re.sub(r"[^A-Za-z0-9_-]", "_", name) or "object"
    if not safe[0].isalpha():
        safe = "o" + safe
    chosen, count = safe, 1
    while chosen in taken:
        count += 1
        chosen = f"{safe}-{count}"
    taken.add(chosen)
    return chosen


def _matrix(value):
    return np.array([list(row) for row in value], dtype=np.float64)


def _numbers(values):
    return " ".join(f"{float(v):.9g}" for v in values)


def _add(parent, tag, name=None, **attributes):
    element = ElementTree.SubElement(parent, tag)
    if name is not None:
        element.set("name", name)
    for key, value in attributes.items():
        element.set(key, value)
    return element


def _float(parent, name, value):
    _add(parent, "float", name, value=f"{float(value):.9g}")


def _rgb(parent, name, value):
    _add(parent, "rgb", name, value=_numbers(list(value)[:3]))


def _transform(parent, matrix):
    transform = _add(parent, "transform", "to_world")
    _add(transform, "matrix", value=_numbers(np.asarray(matrix, dtype=np.float64).ravel()))


def _without_scale(matrix):
    """Returns a 4x4 matrix's rotation and translation, its scale (and any shear) taken out."""
    rotation, upper = np.linalg.qr(matrix[:3, :3])
    rotation = rotation @ np.diag(np.sign(np.diag(upper)))  # QR's signs chosen so the columns keep their direction
    result = np.eye(4)
    result[:3, :3], result[:3, 3] = rotation, matrix[:3, 3]
    return result


def _rendered(obj, view_layer):
    """Returns whether Cycles renders `obj`: in the view layer, not disabled in renders, nor is a collection of it."""
    if obj.hide_render or obj.name not in view_layer.objects:
        return False
    return not any(collection.hide_render for collection in obj.users_collection)


# --- meshes


def _mesh_arrays(mesh):
    """Returns (positions, corner normals, uvs or None, corner indices per triangle, material index per triangle)."""
    mesh.calc_loop_triangles()
    count = len(mesh.loop_triangles)
    corners = np.empty(count * 3, np.int64)
    mesh.loop_triangles.foreach_get("loops", corners)
    slots = np.empty(count, np.int64)
    mesh.loop_triangles.foreach_get("material_index", slots)
    vertex_of = np.empty(len(mesh.loops), np.int64)
    mesh.loops.foreach_get("vertex_index", vertex_of)
    positions = np.empty(len(mesh.vertices) * 3, np.float64)
    mesh.vertices.foreach_get("co", positions)
    normals = np.empty(len(mesh.loops) * 3, np.float64)
    mesh.corner_normals.foreach_get("vector", normals)
    uvs = None
    if mesh.uv_layers.active is not None:
        uvs = np.empty(len(mesh.loops) * 2, np.float64)
        mesh.uv_layers.active.data.foreach_get("uv", uvs)
        uvs = uvs.reshape(-1, 2)
    positions = positions.reshape(-1, 3)[vertex_of]
    return positions, normals.reshape(-1, 3), uvs, corners.reshape(-1, 3), slots


def _world_mesh(arrays, matrix, triangles):
    """Returns (positions, normals, uvs, triangles) of the chosen triangles in world space, corners shared where
    their vertex, normal and UV agree."""
    positions, normals, uvs, corners, _ = arrays
    used = corners[triangles]
    linear, offset = matrix[:3, :3], matrix[:3, 3]
    world = positions @ linear.T + offset
    turned = normals @ np.linalg.inv(linear)  # the inverse transpose, applied to rows
    length = np.linalg.norm(turned, axis=1, keepdims=True)
    turned = np.where(length > 0, turned / np.maximum(length, 1e-30), turned)
    flat_uvs = np.zeros((len(world), 2)) if uvs is None else np.column_stack([uvs[:, 0], 1.0 - uvs[:, 1]])
    table = np.column_stack([world, turned, flat_uvs]).astype(np.float32)
    unique, inverse = np.unique(table[used.ravel()], axis=0, return_inverse=True)
    faces = inverse.reshape(-1, 3).astype(np.int32)
    if np.linalg.det(linear) < 0:  # a mirroring transform turns the faces inside out: wind them back
        faces = faces[:, ::-1]
    return unique[:, 0:3], unique[:, 3:6], unique[:, 6:8], faces


def write_ply(path, positions, normals, uvs, triangles):
    """Writes a binary little-endian PLY with normals and UVs, the form Mitsuba reads (scene_library.write_ply's)."""
    names = ("x", "y", "z", "nx", "ny", "nz", "u", "v")
    vertex = np.empty(len(positions), dtype=[(name, "<f4") for name in names])
    for k, axis in enumerate("xyz"):
        vertex[axis] = positions[:, k]
        vertex["n" + axis] = normals[:, k]
    vertex["u"], vertex["v"] = uvs[:, 0], uvs[:, 1]
    faces = np.empty(len(triangles), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, triangles
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(positions)}\n"
        + "".join(f"property float {name}\n" for name in names)
        + f"element face {len(triangles)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with open(path, "wb") as file:
        file.write(header.encode("ascii"))
        file.write(vertex.tobytes())
        file.write(faces.tobytes())


def _modifier_notes(obj):
    """Returns a note where Cycles' render would evaluate the object's modifiers otherwise than the viewport."""
    differ = []
    for modifier in obj.modifiers:
        if modifier.show_viewport != modifier.show_render:
            differ.append(f"{modifier.name} (shown in {'renders' if modifier.show_render else 'the viewport'} only)")
        elif modifier.show_viewport and getattr(modifier, "render_levels", None) not in (None, modifier.levels):
            differ.append(f"{modifier.name} (levels {modifier.levels}, render {modifier.render_levels})")
    if not differ:
        return []
    return [f"object {obj.name!r}: modifiers as the viewport shows them: {', '.join(differ)}"]


# --- materials


def _principled_values(principled, volume, table):
    """Returns matfit's 19 named values of a Principled BSDF read by `material.read` (defaults where it decides
    none) and the notes of from_blender."""
    bounds = {entry["name"]: (entry["low"], entry["high"]) for entry in table}
    values, _, notes = blender_mapping.from_blender(principled, volume, bounds)
    return {entry["name"]: values.get(entry["name"], entry["default"]) for entry in table}, notes


def _write_principled(shape, values):
    """Adds Mitsuba's principled BSDF of matfit's values, with the keys of matfit's scene.bsdf."""
    bsdf = _add(shape, "bsdf", type="principled")
    _rgb(bsdf, "base_color", [values[name] for name in blender_mapping.BASE])
    for key in ("metallic", "roughness", "anisotropic", "specular", "spec_tint", "sheen", "sheen_tint", "clearcoat",
                "clearcoat_gloss", "spec_trans"):  # fmt: skip
        _float(bsdf, key, values[key])


def _write_diffuse(shape, colour):
    _rgb(_add(shape, "bsdf", type="diffuse"), "reflectance", colour)


def _write_medium(shape, volume):
    """Adds the homogeneous interior medium of `material.read`'s volume per world unit (radius 1)."""
    sigma_a = [volume["absorption_density"] * (1.0 - c) for c in volume["absorption_color"][:3]]
    sigma_s = [volume["scatter_density"] * c for c in volume["scatter_color"][:3]]
    sigma_t = [a + s for a, s in zip(sigma_a, sigma_s, strict=True)]
    scale = max(sigma_t)
    medium = _add(shape, "medium", "interior", type="homogeneous")
    _float(medium, "scale", scale)
    _rgb(medium, "sigma_t", [t / scale for t in sigma_t])
    _rgb(medium, "albedo", [s / t if t > 0 else 0.0 for s, t in zip(sigma_s, sigma_t, strict=True)])
    _float(_add(medium, "phase", type="hg"), "g", volume["anisotropy"])


def _material(shape, chosen, table, where, notes):
    """Adds the shape's BSDF (and medium) for the Blender material `chosen` of another object than the fitted;
    returns whether a medium was written."""
    if chosen is None:
        _write_diffuse(shape, [DEFAULT_GREY] * 3)
        return False
    try:
        principled, volume, read_notes = material.read(chosen, 1.0)
    except material.MaterialError as error:
        reason = str(error).split(": ", 1)[-1]
        notes.append(f"{where}: {reason}; exported as grey diffuse {DEFAULT_GREY}")
        _write_diffuse(shape, [DEFAULT_GREY] * 3)
        return False
    if float(principled["Specular IOR Level"]) <= 0.0:
        _write_diffuse(shape, principled["Base Color"])
        notes += [f"{where}: {note}" for note in read_notes]
        return False
    values, mapped_notes = _principled_values(principled, volume, table)
    notes += [f"{where}: {note}" for note in read_notes + mapped_notes]
    _write_principled(shape, values)
    if volume is not None and values["spec_trans"] > 0 and max(volume["absorption_density"], volume["scatter_density"]):
        _write_medium(shape, volume)
        return True
    return False


def fitted_material(obj, table):
    """Returns (matfit's 19 named values, notes) of the fitted object's active material, read as the picture's source.

    Raises material.MaterialError where it is no Principled BSDF. Densities are per world unit (radius 1), as
    matfit's medium in a scene file is.
    """
    principled, volume, notes = material.read(obj.active_material if obj.material_slots else None, 1.0)
    values, more = _principled_values(principled, volume, table)
    return values, notes + more


# --- camera, lights, world


def _camera(root, scene, depsgraph, notes):
    camera = scene.camera
    if camera is None:
        raise ExportError("matfit: the scene has no camera: add one and make it the scene's camera")
    data = camera.data
    if data.type != "PERSP":
        raise ExportError(
            f"matfit: camera {camera.name!r} is {data.type.lower()}, not perspective: matfit renders a perspective "
            "camera; set its Type to Perspective"
        )
    render = scene.render
    width = max(1, render.resolution_x * render.resolution_percentage // 100)
    height = max(1, render.resolution_y * render.resolution_percentage // 100)
    aspect = width * render.pixel_aspect_x / (height * render.pixel_aspect_y)
    fit = data.sensor_fit
    if fit == "AUTO":
        axis, sensor = ("x" if aspect >= 1 else "y"), data.sensor_width
    else:
        axis, sensor = ("x", data.sensor_width) if fit == "HORIZONTAL" else ("y", data.sensor_height)
    fov = math.degrees(2.0 * math.atan(sensor / (2.0 * data.lens)))
    sensor_element = _add(root, "sensor", type="perspective")
    _add(sensor_element, "string", "fov_axis", value=axis)
    _float(sensor_element, "fov", fov)
    _float(sensor_element, "near_clip", data.clip_start)
    _float(sensor_element, "far_clip", data.clip_end)
    world = _matrix(camera.evaluated_get(depsgraph).matrix_world)
    _transform(sensor_element, _without_scale(world) @ CAMERA_AXES)
    sampler = _add(sensor_element, "sampler", type="independent")
    _add(sampler, "integer", "sample_count", value="64")
    film = _add(sensor_element, "film", type="hdrfilm")
    _add(film, "integer", "width", value=str(width))
    _add(film, "integer", "height", value=str(height))
    _add(film, "string", "pixel_format", value="rgb")
    if data.shift_x or data.shift_y:
        notes.append(f"camera {camera.name!r}: its shift ignored")
    if data.dof.use_dof:
        notes.append(f"camera {camera.name!r}: depth of field ignored (a pinhole)")
    if render.pixel_aspect_x != render.pixel_aspect_y:
        notes.append("the render's pixel aspect ignored (square pixels)")


def _power(light, where, notes):
    """Returns the light's colour x power as RGB (Power x 2^Exposure), noting what is not carried."""
    power = light.energy * 2.0 ** getattr(light, "exposure", 0.0)
    if getattr(light, "use_temperature", False):
        notes.append(f"{where}: its colour temperature ignored (its Color used)")
    if light.use_nodes:
        notes.append(f"{where}: its node tree ignored")
    return [power * c for c in light.color]


def _light(root, obj, matrix, taken, notes):
    light = obj.data
    where = f"light {obj.name!r}"
    power = _power(light, where, notes)
    kind = light.type
    if kind in ("POINT", "SPOT") and light.shadow_soft_size > 0:
        notes.append(f"{where}: radius {light.shadow_soft_size:.3g} shown as a point (hard shadows)")
    if kind == "POINT":
        emitter = _add(root, "emitter", type="point")
        _add(emitter, "point", "position", **dict(zip("xyz", (f"{v:.9g}" for v in matrix[:3, 3]), strict=True)))
        _rgb(emitter, "intensity", [p / (4.0 * math.pi) for p in power])
    elif kind == "SPOT":
        emitter = _add(root, "emitter", type="spot")
        _transform(emitter, _without_scale(matrix) @ FACING_MINUS_Z)
        _rgb(emitter, "intensity", [p / (4.0 * math.pi) for p in power])
        cutoff = math.degrees(light.spot_size / 2.0)
        # Cycles' blend: a smoothstep of cos(angle) from cos(cutoff) up to cos(cutoff) + (1 - cos(cutoff)) x blend
        cosine = math.cos(light.spot_size / 2.0)
        full = math.degrees(math.acos(min(1.0, cosine + (1.0 - cosine) * light.spot_blend)))
        _float(emitter, "cutoff_angle", cutoff)
        _float(emitter, "beam_width", min(full, cutoff - SPOT_BLEND_FLOOR))
        if light.use_square:
            notes.append(f"{where}: square spot shown as round")
    elif kind == "SUN":
        emitter = _add(root, "emitter", type="directional")
        direction = matrix[:3, :3] @ np.array([0.0, 0.0, -1.0])
        _add(emitter, "vector", "direction", value=_numbers(direction / np.linalg.norm(direction)))
        _rgb(emitter, "irradiance", power)  # a sun's Strength is its irradiance, W/m^2
    else:
        _area_light(root, obj, matrix, power, taken, where, notes)


def _area_light(root, obj, matrix, power, taken, where, notes):
    light = obj.data
    across = light.size
    down = light.size_y if light.shape in ("RECTANGLE", "ELLIPSE") else light.size
    round_shape = light.shape in ("DISK", "ELLIPSE")
    local = np.diag([across / 2.0, down / 2.0, 1.0, 1.0]) @ FACING_MINUS_Z
    to_world = matrix @ local
    # the world area: Mitsuba's rectangle is [-1, 1]^2, its disk the unit disk
    area = float(np.linalg.norm(np.cross(to_world[:3, 0], to_world[:3, 1]))) * (math.pi if round_shape else 4.0)
    normalised = getattr(light, "normalize", True)
    if area <= 0.0:
        notes.append(f"{where}: no area; left out")
        return
    shape = _add(root, "shape", type="disk" if round_shape else "rectangle", id=shape_id(obj.name, taken))
    _transform(shape, to_world)
    _write_diffuse(shape, [0.0, 0.0, 0.0])  # Cycles' lights reflect nothing
    emitter = _add(shape, "emitter", type="area")
    _rgb(emitter, "radiance", [p / (math.pi * (area if normalised else 1.0)) for p in power])
    if light.spread < math.pi - 1e-4:
        notes.append(f"{where}: spread {math.degrees(light.spread):.0f} degrees shown as 180")


def _srgb_to_linear(values):
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)


def write_pfm(path, rgb_bottom_up):
    """Writes a float RGB image whose rows run bottom-up (Blender's order, PFM's too) as little-endian PFM."""
    height, width, _ = rgb_bottom_up.shape
    with open(path, "wb") as file:
        file.write(f"PF\n{width} {height}\n-1.0\n".encode("ascii"))
        file.write(np.ascontiguousarray(rgb_bottom_up, dtype="<f4").tobytes())


def _environment(root, node, strength, folder, notes):
    """Adds the Environment Texture's image as an envmap; returns False where it cannot (then noted)."""
    image = node.image
    if image is None or node.projection != "EQUIRECTANGULAR" or node.inputs["Vector"].is_linked:
        what = "no image" if image is None else "a mapping or projection matfit does not carry"
        notes.append(f"the world's Environment Texture has {what}; the world exported as its Background's Color")
        return False
    width, height = image.size
    if width == 0 or height == 0:
        notes.append(f"the world's image {image.name!r} has no pixels; the world exported as its Background's Color")
        return False
    pixels = np.empty(width * height * image.channels, np.float32)
    image.pixels.foreach_get(pixels)
    rgb = pixels.reshape(height, width, image.channels)[:, :, :3].astype(np.float64)
    space = image.colorspace_settings.name
    if space == "sRGB":
        rgb = _srgb_to_linear(rgb)
    elif not space.startswith("Linear") and space != "Non-Color":
        notes.append(f"the world's image's colour space {space} read as linear")
    write_pfm(os.path.join(folder, "world.pfm"), rgb)
    emitter = _add(root, "emitter", type="envmap")
    _add(emitter, "string", "filename", value="world.pfm")
    _float(emitter, "scale", strength)
    _transform(emitter, ENVMAP_TO_WORLD)
    return True


def _world(root, scene, folder, notes):
    world = scene.world
    if world is None:
        return
    if not world.use_nodes or world.node_tree is None:
        colour, strength = list(world.color), 1.0
    else:
        output = world.node_tree.get_output_node("CYCLES")
        source = material._source(output.inputs["Surface"]) if output is not None else None
        if source is None:
            return
        if source.bl_idname != "ShaderNodeBackground":
            notes.append(f"the world's {material._describe(source)} is not carried: no world light")
            return
        strength = source.inputs["Strength"].default_value
        if source.inputs["Strength"].is_linked:
            notes.append("the world's Strength is linked: read at its unlinked value")
        colour_source = material._source(source.inputs["Color"])
        if colour_source is not None and colour_source.bl_idname == "ShaderNodeTexEnvironment":
            if _environment(root, colour_source, strength, folder, notes):
                return
        elif colour_source is not None:
            notes.append(f"the world's Color ({material._describe(colour_source)}) read at its unlinked value")
        colour = list(source.inputs["Color"].default_value)[:3]
    radiance = [c * strength for c in colour[:3]]
    if max(radiance) > 0:
        _rgb(_add(root, "emitter", type="constant"), "radiance", radiance)


# --- the scene


def export(context, folder, fitted, table):
    """Writes the scene of `context` into `folder` (made if need be) and returns its `Export`.

    `fitted` is the object whose material is fitted (a mesh whose active material is a Principled BSDF): its
    shape holds that material (matfit's `--object` reads it as the fit's start), one shape whatever its slots.
    `table` is matfit's params.table() (parameters.json in the zip). Raises ExportError (no camera, a camera
    matfit cannot render, a fitted object with no surface) or material.MaterialError (the fitted object's
    material is no Principled BSDF).
    """
    scene, view_layer = context.scene, context.view_layer
    if fitted is None or fitted.type not in CONVERTIBLE:
        raise ExportError("matfit: select the object whose material to fit (a mesh)")
    notes = []
    root = ElementTree.Element("scene", version="3.0.0")
    integrator = _add(root, "integrator", type="path")
    bounces = getattr(getattr(scene, "cycles", None), "max_bounces", 12)
    _add(integrator, "integer", "max_depth", value=str(bounces + 2))  # Mitsuba counts the camera and light segments
    # The evaluated objects' matrices: an object moved since the last update has its new place there only.
    depsgraph = context.evaluated_depsgraph_get()
    _camera(root, scene, depsgraph, notes)
    os.makedirs(os.path.join(folder, MESHES), exist_ok=True)
    _world(root, scene, folder, notes)
    values, fitted_notes = fitted_material(fitted, table)
    notes += [f"fitted object {fitted.name!r}: {note}" for note in fitted_notes]
    if len([slot for slot in fitted.material_slots if slot.material is not None]) > 1:
        notes.append(
            f"fitted object {fitted.name!r}: {len(fitted.material_slots)} materials; its active one "
            f"{fitted.active_material.name!r} is fitted, on the whole object"
        )
    taken, ids, any_medium = set(), {}, False
    objects = sorted((obj for obj in scene.objects if _rendered(obj, view_layer)), key=lambda obj: obj is not fitted)
    if fitted not in objects:
        raise ExportError(f"matfit: object {fitted.name!r} is not rendered (hidden, or disabled in renders)")
    for obj in objects:
        matrix = _matrix(obj.evaluated_get(depsgraph).matrix_world)
        if obj.type == "LIGHT":
            _light(root, obj, matrix, taken, notes)
            continue
        if obj.type not in CONVERTIBLE:
            continue
        any_medium |= _mesh_object(
            root, obj, matrix, obj is fitted, values, depsgraph, folder, taken, ids, table, notes
        )
    instances = sum(1 for instance in depsgraph.object_instances if instance.is_instance)
    if instances:
        notes.append(f"{instances} instanced object(s) (collection instances, particles, geometry nodes) not exported")
    if any_medium:
        integrator.set("type", "volpath")
    ElementTree.indent(root)
    path = os.path.join(folder, "scene.xml")
    with open(path, "wb") as file:
        file.write(ElementTree.tostring(root, encoding="utf-8"))
    result = Export(path, ids, ids[fitted.name], notes, values)
    with open(os.path.join(folder, "matfit-export.json"), "w") as file:
        json.dump({"objects": ids, "fitted": {"name": fitted.name, "id": result.fitted}, "notes": notes}, file)
    return result


def _mesh_object(root, obj, matrix, is_fitted, values, depsgraph, folder, taken, ids, table, notes):
    """Writes one object's shapes (one per material slot it uses; the fitted object as one); returns whether a
    medium was written."""
    where = f"object {obj.name!r}"
    notes += _modifier_notes(obj)
    evaluated = obj.evaluated_get(depsgraph)
    try:
        mesh = evaluated.to_mesh()
    except RuntimeError as error:
        mesh, failure = None, str(error).strip().splitlines()[-1] if str(error).strip() else "no mesh"
    else:
        failure = "no faces" if mesh is None or len(mesh.polygons) == 0 else None
    try:
        if failure is not None:
            if is_fitted:
                raise ExportError(f"matfit: the fitted {where} gives no surface to render ({failure}): check its "
                                  "modifiers")  # fmt: skip
            if obj.type == "MESH" or mesh is None:
                notes.append(f"{where}: not exported ({failure})")
            return False
        arrays = _mesh_arrays(mesh)
    finally:
        if mesh is not None:
            evaluated.to_mesh_clear()
    slots = arrays[4]
    groups = [np.arange(len(slots))] if is_fitted else [np.flatnonzero(slots == s) for s in np.unique(slots)]
    medium = False
    base = shape_id(obj.name, taken)
    ids[obj.name] = base
    for number, triangles in enumerate(groups):
        if len(triangles) == 0:
            continue
        identifier = base if number == 0 else shape_id(f"{base}-{number + 1}", taken)
        mesh_file = f"{MESHES}/{identifier}.ply"
        write_ply(os.path.join(folder, mesh_file), *_world_mesh(arrays, matrix, triangles))
        shape = _add(root, "shape", type="ply", id=identifier)
        _add(shape, "string", "filename", value=mesh_file)
        _add(shape, "boolean", "face_normals", value="false")
        if is_fitted:
            _write_principled(shape, values)
            continue
        slot = int(slots[triangles[0]])
        chosen = obj.material_slots[slot].material if slot < len(obj.material_slots) else None
        medium |= _material(shape, chosen, table, where, notes)
    return medium
