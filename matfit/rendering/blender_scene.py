"""The material test scene in Blender, rendered with Cycles: runs inside Blender's Python, not matfit's.

bpy 4.5 requires numpy < 2 and cannot share matfit's environment, so this module is run in a
subprocess by `matfit.rendering.blender` (`python -m matfit.rendering.blender_scene job.json` with a Python that has
bpy, or `blender -b -P matfit/rendering/blender_scene.py -- job.json`). It imports only bpy, NumPy, the
NumPy-only modules `params` and `scene`, and `blender_material` (the exported material script,
whose `node_tree` builds every node tree here too), so it runs with either NumPy.

The scene is `scene.scene` rebuilt node for node: the same camera (field of view, look-at), unit
sphere, checkered floor and backdrop (Mitsuba's checkerboard on the rectangles' uv, same cells and
phase), the key light (a one-sided emissive rectangle of the same radiance, which is what
Mitsuba's area emitter is), the same latitude-longitude environment bitmap at the same scale, and
Mitsuba's film filter (Gaussian, standard deviation 0.5 px). Cycles' Gaussian filter width was
measured: on the floor and backdrop (pixels away from the sphere, 3 materials, 64 px, 256 spp),
width 2 px gives RMSE 1.7-2.0 against Mitsuba, width 1.5 3.1-3.3, 2.5 3.0-3.2, 6 14-15, where two
Mitsuba renders with different seeds differ by 1.8. Mitsuba works with y up, Blender with z up: points (x, y, z) become
(x, -z, y). Cycles follows every path to 64 bounces of any kind (volpath's max depth), with no
clamping, no glossy filter and no denoiser. The sphere is a smooth-shaded UV sphere, rotated so
that its local z axis is Mitsuba's z: the default tangent of Blender's Principled BSDF runs around
the object's local z, Mitsuba's sphere's around its own z, so anisotropic highlights line up.

Job file: {"resolution": 64, "spp": 64, "seed": 0, "scripts": [paths], "out": folder}; for each
script i the exported material script runs with only the sphere selected, then the render is
saved as `out/i.npy`, linear float32 (H, W, 3), top row first.
"""

from __future__ import annotations

import json
import math
import os
import sys

import numpy as np

if __package__ in (None, ""):  # run as a file (`blender -P`, `python blender_scene.py`): import matfit from its folder
    # The folder alone, never its parent: for an installed matfit that is matfit's site-packages, whose packages
    # (NumPy 2, compiled for another Python) would shadow those of bpy's environment.
    import importlib.util

    _here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:] = [path for path in sys.path if os.path.abspath(path or ".") != _here]
    _spec = importlib.util.spec_from_file_location(
        "matfit",
        os.path.join(os.path.dirname(_here), "__init__.py"),
        submodule_search_locations=[os.path.dirname(_here)],
    )
    assert _spec is not None and _spec.loader is not None
    sys.modules["matfit"] = importlib.util.module_from_spec(_spec)
    _spec.loader.exec_module(sys.modules["matfit"])

import bpy

from matfit.rendering import scene
from matfit.rendering.blender_material import node_tree

# Mitsuba (x, y, z), y up -> Blender (x, -z, y), z up.
MITSUBA_TO_BLENDER = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
SPHERE_SEGMENTS = (128, 64)
# Cycles' Gaussian of width 2 px matches Mitsuba's (standard deviation 0.5 px): measured, see the module docstring.
FILTER_WIDTH = 2.0


def _look_at(origin, target, up) -> np.ndarray:
    """Returns Mitsuba's look-at matrix: columns left, up, direction, origin."""
    origin, target, up = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    direction = (target - origin) / np.linalg.norm(target - origin)
    left = np.cross(up, direction)
    left /= np.linalg.norm(left)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = left, np.cross(direction, left), direction, origin
    return matrix


def _rotate(axis, degrees) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    angle = math.radians(degrees)
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    matrix = np.eye(4)
    matrix[:3, :3] = np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * cross @ cross
    return matrix


def matrix(transform: scene.Transform) -> np.ndarray:
    """Returns the 4x4 Mitsuba-world matrix of a `scene.Transform` (first operation innermost)."""
    result = np.eye(4)
    for name, *arguments in transform.operations:
        step = np.eye(4)
        if name == "look_at":
            step = _look_at(*arguments)
        elif name == "rotate":
            step = _rotate(*arguments)
        elif name == "scale":
            step[:3, :3] = np.diag(arguments[0])
        elif name == "translate":
            step[:3, 3] = arguments[0]
        else:
            raise ValueError(f"unknown transform operation {name!r}")
        result = step @ result
    return result


def _to_blender(matrix_mitsuba: np.ndarray, local: np.ndarray | None = None):
    """Returns a Blender matrix_world for a Mitsuba to_world matrix (and a local axis change)."""
    from mathutils import Matrix

    world = MITSUBA_TO_BLENDER @ matrix_mitsuba @ (np.eye(4) if local is None else local)
    return Matrix(world.tolist())


def _rectangle(name: str, transform: scene.Transform, material) -> object:
    """Returns a mesh object of Mitsuba's rectangle: [-1, 1]^2 at z = 0, normal +z, uv = (p + 1) / 2."""
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(-1.0, -1.0, 0.0), (1.0, -1.0, 0.0), (1.0, 1.0, 0.0), (-1.0, 1.0, 0.0)], [], [(0, 1, 2, 3)])
    uv = mesh.uv_layers.new(name="UVMap")
    for loop in mesh.loops:
        x, y, _ = mesh.vertices[loop.vertex_index].co
        uv.data[loop.index].uv = ((x + 1.0) / 2.0, (y + 1.0) / 2.0)
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    obj.matrix_world = _to_blender(matrix(transform))
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _checker_material(name: str, description: dict):
    """Returns a diffuse material with Mitsuba's checkerboard on the uv of a rectangle.

    Mitsuba picks color0 where frac(u') > 0.5 and frac(v') > 0.5 agree (u' = u x scale); Cycles'
    checker picks Color1 where floor(x) and floor(y) differ in parity (z = 0), so x = 2 u' and
    Color1 = color1 (measured: the other phase puts every cell in the wrong colour).
    """
    texture = description["reflectance"]
    (operation, (across, down, _)) = texture["to_uv"].operations[0]  # scene.checker: one scale
    assert operation == "scale", texture["to_uv"]
    material = bpy.data.materials.new(name)
    nodes, links = node_tree(material)
    coordinates = nodes.new("ShaderNodeTexCoord")
    stretch = nodes.new("ShaderNodeVectorMath")
    stretch.operation = "MULTIPLY"
    stretch.inputs[1].default_value = (2.0 * across, 2.0 * down, 0.0)
    checker = nodes.new("ShaderNodeTexChecker")
    checker.inputs["Scale"].default_value = 1.0
    checker.inputs["Color1"].default_value = (*texture["color1"]["value"], 1.0)
    checker.inputs["Color2"].default_value = (*texture["color0"]["value"], 1.0)
    diffuse = nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Roughness"].default_value = 0.0
    output = nodes.new("ShaderNodeOutputMaterial")
    links.new(coordinates.outputs["UV"], stretch.inputs[0])
    links.new(stretch.outputs["Vector"], checker.inputs["Vector"])
    links.new(checker.outputs["Color"], diffuse.inputs["Color"])
    links.new(diffuse.outputs["BSDF"], output.inputs["Surface"])
    return material


def _light_material(radiance: list[float]):
    """Returns a material emitting `radiance` from the front only, diffuse grey 0.5 in front, black behind.

    Mitsuba's area emitter is one-sided, and a shape without a BSDF gets Mitsuba's default diffuse 0.5.
    """
    material = bpy.data.materials.new("matfit-key-light")
    material.cycles.emission_sampling = "FRONT"
    nodes, links = node_tree(material)
    emission = nodes.new("ShaderNodeEmission")
    emission.inputs["Color"].default_value = (*radiance, 1.0)
    emission.inputs["Strength"].default_value = 1.0
    diffuse = nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (0.5, 0.5, 0.5, 1.0)
    front = nodes.new("ShaderNodeAddShader")
    black = nodes.new("ShaderNodeBsdfDiffuse")
    black.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    geometry = nodes.new("ShaderNodeNewGeometry")
    mix = nodes.new("ShaderNodeMixShader")
    output = nodes.new("ShaderNodeOutputMaterial")
    links.new(emission.outputs["Emission"], front.inputs[0])
    links.new(diffuse.outputs["BSDF"], front.inputs[1])
    links.new(geometry.outputs["Backfacing"], mix.inputs["Fac"])
    links.new(front.outputs["Shader"], mix.inputs[1])
    links.new(black.outputs["BSDF"], mix.inputs[2])
    links.new(mix.outputs["Shader"], output.inputs["Surface"])
    return material


def _world(description: dict) -> None:
    """Sets the world to the environment bitmap, equirectangular, linear interpolation, same scale."""
    bitmap = np.asarray(description["bitmap"], dtype=np.float32)
    height, width, _ = bitmap.shape
    image = bpy.data.images.new("matfit-sky", width, height, alpha=True, float_buffer=True)
    image.colorspace_settings.name = "Linear Rec.709"
    rgba = np.concatenate(
        [bitmap[::-1], np.ones((height, width, 1), np.float32)], axis=2
    )  # Blender's rows run bottom-up
    image.pixels.foreach_set(rgba.ravel())
    image.pack()
    world = bpy.data.worlds.new("matfit-world")
    nodes, links = node_tree(world)
    texture = nodes.new("ShaderNodeTexEnvironment")
    texture.image = image
    texture.interpolation = "Linear"
    background = nodes.new("ShaderNodeBackground")
    background.inputs["Strength"].default_value = description["scale"]
    output = nodes.new("ShaderNodeOutputWorld")
    links.new(texture.outputs["Color"], background.inputs["Color"])
    links.new(background.outputs["Background"], output.inputs["Surface"])
    world.cycles.sampling_method = "MANUAL"
    world.cycles.sample_map_resolution = width  # the bitmap's own size: building Cycles' default map takes 2 s
    bpy.context.scene.world = world


def _camera(description: dict) -> None:
    camera_data = bpy.data.cameras.new("matfit-camera")
    camera_data.sensor_fit = "HORIZONTAL"
    camera_data.angle = math.radians(description["fov"])
    camera_data.clip_start = 0.01
    camera = bpy.data.objects.new("matfit-camera", camera_data)
    # Mitsuba's camera looks along local +z with +x to the image's left; Blender's along -z with +x right.
    camera.matrix_world = _to_blender(matrix(description["to_world"]), np.diag([-1.0, 1.0, -1.0, 1.0]))
    bpy.context.scene.collection.objects.link(camera)
    bpy.context.scene.camera = camera


def _sphere():
    import bmesh

    mesh = bpy.data.meshes.new("matfit-sphere")
    geometry = bmesh.new()
    bmesh.ops.create_uvsphere(geometry, u_segments=SPHERE_SEGMENTS[0], v_segments=SPHERE_SEGMENTS[1], radius=1.0)
    geometry.to_mesh(mesh)
    geometry.free()
    mesh.shade_smooth()
    sphere = bpy.data.objects.new("matfit-sphere", mesh)
    sphere.rotation_euler = (math.pi / 2.0, 0.0, 0.0)  # local z = Mitsuba's z, for the tangent
    bpy.context.scene.collection.objects.link(sphere)
    return sphere


def _render_settings(resolution: int, spp: int, seed: int) -> None:
    settings = bpy.context.scene
    render = settings.render
    render.engine = "CYCLES"
    render.resolution_x = render.resolution_y = resolution
    render.resolution_percentage = 100
    render.film_transparent = False
    render.image_settings.file_format = "OPEN_EXR"
    render.image_settings.color_depth = "32"
    render.image_settings.exr_codec = "ZIP"
    settings.view_settings.view_transform = "Standard"
    settings.view_settings.look = "None"
    cycles = settings.cycles
    cycles.device = "CPU"
    cycles.samples = spp
    cycles.seed = seed
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = False
    for bounces in (
        "max_bounces",
        "diffuse_bounces",
        "glossy_bounces",
        "transmission_bounces",
        "volume_bounces",
        "transparent_max_bounces",
    ):
        setattr(cycles, bounces, scene.MAX_DEPTH)
    cycles.caustics_reflective = cycles.caustics_refractive = True
    cycles.blur_glossy = 0.0
    cycles.sample_clamp_direct = cycles.sample_clamp_indirect = 0.0
    cycles.pixel_filter_type = "GAUSSIAN"
    cycles.filter_width = FILTER_WIDTH


def build(resolution: int, spp: int, seed: int = 0):
    """Builds the test scene in an empty Blender file; returns the sphere, the only selected object."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    description = scene.scene(resolution, spp)
    _render_settings(resolution, spp, seed)
    _camera(description["sensor"])
    _world(description["sky"])
    light = description["key_light"]
    _rectangle("matfit-key-light", light["to_world"], _light_material(light["emitter"]["radiance"]["value"]))
    for name in ("floor", "backdrop"):
        _rectangle(
            f"matfit-{name}",
            description[name]["to_world"],
            _checker_material(f"matfit-{name}", description[name]["bsdf"]),
        )
    sphere = _sphere()
    for obj in bpy.context.scene.objects:
        obj.select_set(obj is sphere)
    bpy.context.view_layer.objects.active = sphere
    return sphere


def run_script(path: str) -> None:
    """Runs an exported material script as Blender's Text Editor would, as __main__."""
    with open(path) as file:
        code = compile(file.read(), path, "exec")
    exec(code, {"__name__": "__main__", "__file__": path})


def render(path: str) -> np.ndarray:
    """Renders the scene with Cycles into an EXR at `path`; returns it as linear float32 (H, W, 3), top row first."""
    settings = bpy.context.scene
    settings.render.filepath = path
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(path)
    width, height = image.size
    pixels = np.empty(width * height * 4, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    bpy.data.images.remove(image)
    return np.ascontiguousarray(pixels.reshape(height, width, 4)[::-1, :, :3])


def main(argv: list[str]) -> int:
    """Renders every material script of a job file; see the module docstring."""
    if "--" in argv:
        argv = argv[argv.index("--") + 1 :]
    with open(argv[-1]) as file:
        job = json.load(file)
    for index, script in enumerate(job["scripts"]):
        build(job["resolution"], job["spp"], job.get("seed", 0))
        run_script(script)
        image = render(os.path.join(job["out"], f"{index}.exr"))
        np.save(os.path.join(job["out"], f"{index}.npy"), image)
        print(f"matfit-blender: rendered {index + 1}/{len(job['scripts'])}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
