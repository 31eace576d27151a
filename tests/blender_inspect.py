"""Runs inside Blender's Python for tests/test_blender.py: applies an exported script, reports what it did.

Scene: "bare" (a mesh without material slots) and "shared_a" are selected; "shared_b" shares
shared_a's mesh, which holds the material "keep", and is not selected; "lamp" is a selected light.
Usage: python blender_inspect.py script.py report.json
"""

import json
import sys

import bpy


def mesh_object(name, mesh=None):
    if mesh is None:
        mesh = bpy.data.meshes.new(name)
        mesh.from_pydata([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)], [], [(0, 1, 2)])
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def value(socket):
    default = socket.default_value
    return list(default) if hasattr(default, "__len__") else float(default)


def main(script, report):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bare = mesh_object("bare")
    shared_a = mesh_object("shared_a")
    shared_b = mesh_object("shared_b", shared_a.data)
    shared_a.data.materials.append(bpy.data.materials.new("keep"))
    lamp = bpy.data.objects.new("lamp", bpy.data.lights.new("lamp", "POINT"))
    bpy.context.scene.collection.objects.link(lamp)
    for obj in bpy.context.scene.objects:
        obj.select_set(obj.name in ("bare", "shared_a", "lamp"))
    with open(script) as file:
        exec(compile(file.read(), script, "exec"), {"__name__": "__main__", "__file__": script})
    material = bpy.data.materials["matfit"]
    nodes = {}
    for node in material.node_tree.nodes:
        inputs = {socket.name: value(socket) for socket in node.inputs if hasattr(socket, "default_value")}
        nodes[node.bl_idname] = {"inputs": inputs, "distribution": getattr(node, "distribution", None)}
    links = sorted(
        f"{link.from_node.bl_idname}.{link.from_socket.name}->{link.to_node.bl_idname}.{link.to_socket.name}"
        for link in material.node_tree.links
    )
    slots = {
        obj.name: [(slot.link, slot.material.name if slot.material else None) for slot in obj.material_slots]
        for obj in (bare, shared_a, shared_b)
    }
    mesh_materials = [m.name if m else None for m in shared_a.data.materials]
    with open(report, "w") as file:
        json.dump(
            {
                "nodes": nodes,
                "links": links,
                "slots": slots,
                "shared_mesh_materials": mesh_materials,
                "homogeneous_volume": material.cycles.homogeneous_volume,
                "version": bpy.app.version_string,
            },
            file,
        )


if __name__ == "__main__":
    main(*sys.argv[1:3])
