"""Runs inside Blender's Python for tests/test_blender_scene_export.py: a scene built here, exported, Cycles' renders.

Usage: python blender_scene_export_run.py job.json report.json, in a fresh user folder ($BLENDER_USER_RESOURCES).
job.json: {"zip", "out", "spp", "cases": [light kind], "loop": {"command", "size", "spp", "options", "edit": [argv]}}.
The scene: a UV sphere ("Ball", red principled) on a ground plane ("Ground", Specular IOR Level 0), a camera
at 64 x 48, and one light of each kind (sun, area, point, spot; "world" is a world colour, "world_image" an
environment image that differs left to right and up to down). Each case renders one light alone: the others
disabled in renders, the world black. Each case's export goes into out/CASE/ and Cycles' linear render (the
Standard view transform, EXR) into out/CASE/cycles.npy, top row first.
"loop": the extension's "Picture of this object" of the ball (sun, area light and world together), the edit
command run on that picture (argv + [picture, edited]), "Fit edited picture in this scene", and what it left.
"""

import json
import math
import os
import subprocess
import sys

import bpy
import numpy as np
from blender_extension_run import material_state, operator, slots  # beside this script

MODULE = "bl_ext.user_default.matfit"
SIZE = (64, 48)


def principled_material(name, colour, roughness, specular_level=0.5):
    material = bpy.data.materials.new(name)
    material.use_nodes = True
    bsdf = material.node_tree.nodes["Principled BSDF"]
    bsdf.distribution = "GGX"
    bsdf.inputs["Base Color"].default_value = (*colour, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Specular IOR Level"].default_value = specular_level
    return material


def light(name, kind, location, rotation, power, colour=(1.0, 1.0, 1.0), **settings):
    data = bpy.data.lights.new(name, kind)
    data.energy, data.color = power, colour
    for key, value in settings.items():
        setattr(data, key, value)
    obj = bpy.data.objects.new(name, data)
    obj.location, obj.rotation_euler = location, [math.radians(a) for a in rotation]
    bpy.context.scene.collection.objects.link(obj)
    return obj


def world_image():
    """Returns a small equirectangular image: warm on Blender's +x side, blue towards the zenith."""
    width, height = 64, 32
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height  # bottom row first, as Blender stores it
    longitude = (0.5 - u) * 2 * math.pi  # Blender's u = 1/2 - atan2(y, x) / 2 pi
    toward_x = 0.5 + 0.5 * np.cos(longitude)
    up = np.clip(v, 0, 1)[:, None]
    rgb = np.empty((height, width, 4), np.float32)
    rgb[..., 0] = 0.1 + 0.9 * toward_x[None, :] * (1 - 0.5 * up)
    rgb[..., 1] = 0.1 + 0.3 * toward_x[None, :] + 0.2 * up
    rgb[..., 2] = 0.1 + 0.8 * up
    rgb[..., 3] = 1.0
    image = bpy.data.images.new("sky", width, height, alpha=True, float_buffer=True)
    image.colorspace_settings.name = "Linear Rec.709"
    image.pixels.foreach_set(rgb.ravel())
    image.pack()
    return image


def build_scene():
    """Builds the scene; returns (ball, {case: the lights it uses}, world nodes)."""
    import bmesh

    scene = bpy.context.scene  # the empty factory scene: reading another file would turn the extension off
    render = scene.render
    render.resolution_x, render.resolution_y, render.resolution_percentage = SIZE[0] * 2, SIZE[1] * 2, 50
    mesh = bpy.data.meshes.new("Ball")
    geometry = bmesh.new()
    bmesh.ops.create_uvsphere(geometry, u_segments=48, v_segments=24, radius=1.0, calc_uvs=True)
    geometry.to_mesh(mesh)
    geometry.free()
    mesh.shade_smooth()
    mesh.materials.append(principled_material("Red", (0.7, 0.12, 0.08), 0.35))
    ball = bpy.data.objects.new("Ball", mesh)
    scene.collection.objects.link(ball)
    ground_mesh = bpy.data.meshes.new("Ground")
    ground_mesh.from_pydata([(-6, -6, -1), (6, -6, -1), (6, 6, -1), (-6, 6, -1)], [], [(0, 1, 2, 3)])
    ground_mesh.materials.append(principled_material("Floor", (0.5, 0.5, 0.5), 0.8, specular_level=0.0))
    ground = bpy.data.objects.new("Ground", ground_mesh)
    scene.collection.objects.link(ground)
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.location, camera.rotation_euler = (0.0, -6.5, 2.2), (math.radians(75), 0.0, 0.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    lights = {
        "sun": light("Sun", "SUN", (0, 0, 5), (35, 0, -40), 3.0, (1.0, 0.95, 0.9)),
        "area": light("Area", "AREA", (-2.0, -1.5, 3.0), (40, 0, -50), 300.0, shape="RECTANGLE", size=1.5, size_y=0.8),
        "point": light("Point", "POINT", (2.0, -2.0, 2.5), (0, 0, 0), 400.0, (0.9, 0.9, 1.0)),
        "spot": light("Spot", "SPOT", (0, -3, 4), (35, 0, 0), 800.0, spot_size=math.radians(50), spot_blend=0.3),
    }
    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    world.cycles.sampling_method, world.cycles.sample_map_resolution = "MANUAL", 64  # Cycles' default map takes seconds
    scene.world = world
    nodes, links = world.node_tree.nodes, world.node_tree.links
    background = nodes["Background"]
    texture = nodes.new("ShaderNodeTexEnvironment")
    texture.image = world_image()
    world_nodes = {"background": background, "texture": texture, "links": links}
    return ball, lights, world_nodes


def set_case(case, lights, world_nodes):
    """Leaves the case's light alone in renders: the others disabled, the world black unless it is the case."""
    for kind, obj in lights.items():
        obj.hide_render = kind != case
    background, texture, links = world_nodes["background"], world_nodes["texture"], world_nodes["links"]
    for link in list(background.inputs["Color"].links):
        links.remove(link)
    background.inputs["Color"].default_value = (0.35, 0.4, 0.5, 1.0)
    background.inputs["Strength"].default_value = 1.0 if case in ("world", "world_image", "loop") else 0.0
    if case == "loop":  # the sun, the area light and the world together
        for kind in ("sun", "area"):
            lights[kind].hide_render = False
    if case == "world_image":
        links.new(texture.outputs["Color"], background.inputs["Color"])


def cycles_settings(spp):
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.render.film_transparent = False
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.view_settings.view_transform = "Standard"  # AgX would not be linear
    scene.view_settings.look = "None"
    cycles = scene.cycles
    cycles.device, cycles.samples, cycles.seed = "CPU", spp, 0
    cycles.use_adaptive_sampling = cycles.use_denoising = False
    cycles.light_sampling_threshold = 0.0  # Cycles would leave out lights it judges dim: a bias
    cycles.sample_clamp_direct = cycles.sample_clamp_indirect = 0.0
    cycles.blur_glossy = 0.0
    cycles.pixel_filter_type, cycles.filter_width = "GAUSSIAN", 2.0  # Mitsuba's film filter (blender_scene.py)


def render(path):
    """Renders with Cycles into the EXR at `path`; returns linear float32 (H, W, 3), top row first."""
    bpy.context.scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(path)
    width, height = image.size
    pixels = np.empty(width * height * 4, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    bpy.data.images.remove(image)
    return np.ascontiguousarray(pixels.reshape(height, width, 4)[::-1, :, :3])


def select(obj):
    for other in bpy.context.scene.objects:
        other.select_set(other is obj)
    bpy.context.view_layer.objects.active = obj


def export_odd(extension, ball, lights, folder):
    """Returns the ids and notes of an export fitting "Odd thing": Multiscatter GGX, a texture on its Base Color, two
    materials; the point light with a radius. The scene is left as it was."""
    odd = bpy.data.objects.new("Odd thing", ball.data.copy())
    bpy.context.scene.collection.objects.link(odd)
    odd.data.materials.clear()
    textured = principled_material("Textured", (0.2, 0.5, 0.2), 0.3)
    nodes = textured.node_tree.nodes
    nodes["Principled BSDF"].distribution = "MULTI_GGX"
    texture = nodes.new("ShaderNodeTexImage")
    textured.node_tree.links.new(texture.outputs["Color"], nodes["Principled BSDF"].inputs["Base Color"])
    odd.data.materials.append(textured)
    odd.data.materials.append(principled_material("Second", (0.5, 0.5, 0.5), 0.5))
    odd.location = (2.5, 0.0, 0.0)
    lights["point"].data.shadow_soft_size = 0.1
    for obj in lights.values():
        obj.hide_render = False
    exported = extension.scene_export.export(bpy.context, folder, odd, extension.TABLE)
    lights["point"].data.shadow_soft_size = 0.0
    bpy.data.objects.remove(odd)
    return {"ids": exported.ids, "fitted": exported.fitted, "notes": exported.notes}


def main(job_path, report_path):
    with open(job_path) as file:
        job = json.load(file)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    installed = bpy.ops.extensions.package_install_files(
        filepath=job["zip"], repo="user_default", enable_on_install=True
    )
    report = {"installed": sorted(installed), "cases": {}}
    extension = sys.modules[MODULE]
    ball, lights, world_nodes = build_scene()
    cycles_settings(job["spp"])
    for case in job.get("cases", []):
        set_case(case, lights, world_nodes)
        folder = os.path.join(job["out"], case)
        exported = extension.scene_export.export(bpy.context, folder, ball, extension.TABLE)
        np.save(os.path.join(folder, "cycles.npy"), render(os.path.join(folder, "cycles.exr")))
        report["cases"][case] = {"path": exported.path, "object": exported.fitted, "ids": exported.ids,
                                 "notes": exported.notes}  # fmt: skip
    if "refusals" in job:  # what the operators say before any picture, and of a camera matfit cannot render
        set_case("loop", lights, world_nodes)
        select(ball)
        refusals = report["refusals"] = {}
        refusals["fit_first"] = operator(lambda: bpy.ops.matfit.scene_fit(filepath=job["refusals"]["edited"]))
        bpy.context.scene.camera.data.type = "ORTHO"
        bpy.context.scene.matfit.picture = os.path.join(job["out"], "refused", "picture.png")
        refusals["orthographic"] = operator(bpy.ops.matfit.scene_picture)
        refusals["left"] = sorted(os.listdir(job["out"]))
        bpy.context.scene.camera.data.type = "PERSP"
    if "notes" in job:  # what the export cannot carry, on an object made for it
        report["notes"] = export_odd(extension, ball, lights, os.path.join(job["out"], "notes"))
    if "loop" in job:
        loop = job["loop"]
        set_case("loop", lights, world_nodes)
        prefs = bpy.context.preferences.addons[MODULE].preferences
        prefs.command, prefs.size, prefs.spp = loop["command"], loop["size"], loop["spp"]
        prefs.scene_fit_options = loop["options"]
        settings = bpy.context.scene.matfit
        settings.picture = os.path.join(job["out"], "loop", "picture.png")
        select(ball)
        report["loop"] = {"picture": operator(bpy.ops.matfit.scene_picture), "scene_picture": settings.scene_picture}
        edited = os.path.join(job["out"], "loop", "edited.png")
        subprocess.run([*loop["edit"], settings.scene_picture, edited], check=True)
        report["loop"]["fit"] = operator(lambda: bpy.ops.matfit.scene_fit(filepath=edited))
        report["loop"]["slots"] = slots()
        report["loop"]["fitted"] = material_state("matfit Ball")
    with open(report_path, "w") as file:
        json.dump(report, file)


if __name__ == "__main__":
    main(*sys.argv[1:3])
