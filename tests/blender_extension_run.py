"""Runs inside Blender's Python for tests/test_blender_extension.py: installs the extension zip, runs its operators.

Usage: python blender_extension_run.py job.json report.json, in a fresh user folder ($BLENDER_USER_RESOURCES).
job.json: {"zip", "command", "size", "spp", "fit_options", "imports": {name: exported script},
"picture": {"script", "out"}, "refusals": [kind], "unwritable": [picture path], "fit": edited picture,
"failures": [[command, edited]], "worker": whether to fit again in the worker and after killing it,
"planted": {"edited", "silent", "writers": {kind: command}, "blocked", "redirect", "crashes", "mute",
"mute_seconds": FIT_SECONDS there},
"follow": {"edited", "saved"}, "stages": {"edited", "fails", "go"}, "cancel": edited picture}.
The scene: "source" (active, selected, holds the material to picture), "bare" (selected, no slots),
"shared_a" (selected) and "shared_b" (not selected) sharing a mesh with the material "keep", and a selected light.
The report holds what each step gave back and the line each operator reported. Where the panel's operators run in
the background (a timer polls), this script ticks what their timer does: `Follower.step`, and Fit's `Fitting.show`
while its job runs, then `Fitting.finish`.
"""

import json
import os
import shutil
import signal
import sys
import time

import bpy
from blender_inspect import mesh_object  # beside this script (on sys.path as its folder)

MODULE = "bl_ext.user_default.matfit"


def build_scene():
    """Returns "source" of a new scene; everything before it is removed (loading a file would turn the add-on off)."""
    for collection in (bpy.data.objects, bpy.data.meshes, bpy.data.lights, bpy.data.materials):
        for item in list(collection):
            collection.remove(item)
    source = mesh_object("source")
    mesh_object("bare")
    shared_a = mesh_object("shared_a")
    mesh_object("shared_b", shared_a.data)
    shared_a.data.materials.append(bpy.data.materials.new("keep"))
    lamp = bpy.data.objects.new("lamp", bpy.data.lights.new("lamp", "POINT"))
    bpy.context.scene.collection.objects.link(lamp)
    for obj in bpy.context.scene.objects:
        obj.select_set(obj.name != "shared_b")
    bpy.context.view_layer.objects.active = source
    return source


def run_script(path, name="__main__"):
    with open(path) as file:
        exec(compile(file.read(), path, "exec"), {"__name__": name, "__file__": path})


def operator(call):
    """Returns (outcome, error line) of an operator call; Blender turns an ERROR report into a RuntimeError."""
    try:
        return sorted(call()), None
    except RuntimeError as error:
        return ["CANCELLED"], str(error).strip()


def refused_material(kind):
    """Returns a material matfit cannot represent: a texture on Base Color, a Glass BSDF or an Emission shader."""
    material = bpy.data.materials.new(kind)
    material.use_nodes = True
    nodes, links = material.node_tree.nodes, material.node_tree.links
    output = nodes["Material Output"]
    if kind == "texture":
        texture = nodes.new("ShaderNodeTexImage")
        links.new(texture.outputs["Color"], nodes["Principled BSDF"].inputs["Base Color"])
    else:
        shader = nodes.new("ShaderNodeBsdfGlass" if kind == "glass" else "ShaderNodeEmission")
        links.new(shader.outputs[0], output.inputs["Surface"])
    return material


def value(socket):
    default = socket.default_value
    return list(default) if hasattr(default, "__len__") else float(default)


def material_state(name="matfit"):
    """Returns every node's inputs (by kind), the links and the slots: what a fit may change, to compare."""
    material = bpy.data.materials.get(name)
    if material is None:
        return None
    nodes = {}
    for node in material.node_tree.nodes:
        inputs = {socket.name: value(socket) for socket in node.inputs if hasattr(socket, "default_value")}
        nodes[node.bl_idname] = {"inputs": inputs, "distribution": getattr(node, "distribution", None)}
    links = sorted(
        f"{link.from_node.bl_idname}.{link.from_socket.name}->{link.to_node.bl_idname}.{link.to_socket.name}"
        for link in material.node_tree.links
    )
    return {"nodes": nodes, "links": links, "slots": slots()}


def slots():
    return {
        obj.name: [(slot.link, slot.material.name if slot.material else None) for slot in obj.material_slots]
        for obj in bpy.context.scene.objects
        if obj.type == "MESH"
    }


def scene_state():
    """Returns what a fit may change anywhere: every material's name, the fitted material's nodes, the slots."""
    return {"materials": sorted(m.name for m in bpy.data.materials), "matfit": material_state(), "slots": slots()}


def shown(fitting, extension, wanted=None):
    """Ticks `fitting` as Fit's timer does until it has ended, or until the stage `wanted` is shown; returns
    {stage: what it showed}, the first state of each stage shown."""
    states, deadline = {}, time.monotonic() + 600
    while fitting.poll() is None and time.monotonic() < deadline:
        fitting.show()
        if fitting.shown is not None and fitting.shown[0] not in states:
            stage, document = fitting.shown
            preview = material_state(extension.PREVIEW)
            states[stage] = {
                "document": document,
                "preview": preview,
                "state": scene_state(),
                "status": fitting.status(),
            }
            if stage == wanted:
                break
        time.sleep(0.1)
    return states


def fit_again(edited, jobs):
    """Returns what Fit of `edited` gave twice more: in the first Fit's worker, and after that worker was killed."""
    first = jobs._worker[0].pid
    start = time.monotonic()
    outcome = operator(lambda: bpy.ops.matfit.fit(filepath=edited))
    again = {"outcome": outcome, "seconds": time.monotonic() - start, "fitted": material_state()}
    again["same_worker"] = jobs._worker[0].pid == first
    os.kill(first, signal.SIGKILL)  # between two fits
    outcome = operator(lambda: bpy.ops.matfit.fit(filepath=edited))
    killed = {"outcome": outcome, "fitted": material_state(), "new_worker": jobs._worker[0].pid != first}
    return {"again": again, "killed": killed}


def main(job_path, report_path):
    with open(job_path) as file:
        job = json.load(file)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    installed = bpy.ops.extensions.package_install_files(
        filepath=job["zip"], repo="user_default", enable_on_install=True
    )
    report = {"installed": sorted(installed), "version": bpy.app.version_string}
    prefs = bpy.context.preferences.addons[MODULE].preferences
    prefs.command, prefs.size, prefs.spp, prefs.fit_options = (
        job["command"],
        job["size"],
        job["spp"],
        job["fit_options"],
    )
    extension = sys.modules[MODULE]
    bounds = extension.BOUNDS

    report["imports"] = {}
    for name, script in job.get("imports", {}).items():
        build_scene()
        run_script(script)
        material = bpy.data.materials[name]
        principled, volume, notes = extension.material.read(material, 1.0)
        values, missing, more = extension.blender_mapping.from_blender(principled, volume, bounds)
        report["imports"][name] = {"values": values, "missing": missing, "notes": notes + more}

    if "picture" in job:
        source = build_scene()
        run_script(job["picture"]["script"])  # the preset's material on every selected mesh, "source" among them
        bpy.context.scene.matfit.picture = job["picture"]["out"]
        bpy.context.scene.matfit.radius = 1.0
        report["picture"] = operator(bpy.ops.matfit.picture)
        report["picture_material"] = source.active_material.name

    report["refusals"] = {}
    for kind in job.get("refusals", []):
        source = build_scene()
        source.data.materials.append(refused_material(kind))
        bpy.context.scene.matfit.picture = job["picture"]["out"] + f".{kind}.png"
        report["refusals"][kind] = operator(bpy.ops.matfit.picture)

    report["unwritable"] = {}
    for path in job.get("unwritable", []):  # a picture the extension cannot write, or matfit refuses
        build_scene()
        run_script(job["picture"]["script"])
        bpy.context.scene.matfit.picture = path
        report["unwritable"][path] = operator(bpy.ops.matfit.picture)

    if "fit" in job:
        build_scene()
        bpy.ops.ed.undo_push(message="before the fit")
        before = scene_state()
        start = time.monotonic()
        # undo=True: the undo step the panel's button gets, which a script's call does not push
        report["fit"] = operator(lambda: bpy.ops.matfit.fit("EXEC_DEFAULT", True, filepath=job["fit"]))
        report["fit_seconds"] = time.monotonic() - start
        report["slots"] = slots()
        report["shared_mesh_materials"] = [m.name for m in bpy.data.objects["shared_a"].data.materials]
        report["fitted"] = material_state()
        bpy.ops.ed.undo()
        report["fit_undone"] = [scene_state(), before]
        bpy.ops.ed.redo()
        report["fit_redone"] = material_state()
        if job.get("worker"):  # the same fit again, in the session's worker; then with that worker killed
            report["worker"] = fit_again(job["fit"], extension.jobs)
    report["failures"] = []
    for command, edited in job.get("failures", []):
        prefs.command = command
        report["failures"].append(operator(lambda path=edited: bpy.ops.matfit.fit(filepath=path)))
    prefs.command = job["command"]

    if "planted" in job:  # a script and a stale params.json beside the picture; outputs that are not written
        planted = job["planted"]
        build_scene()
        run_script(job["picture"]["script"])  # an earlier material "matfit" on the selected meshes
        shutil.copy(job["picture"]["out"], planted["edited"])  # jade's picture: a fit with a medium
        report["planted"] = {"before": material_state()}
        prefs.command = planted["silent"]  # exits 0 and writes nothing
        report["planted"]["silent"] = operator(lambda: bpy.ops.matfit.fit(filepath=planted["edited"]))
        report["planted"]["after_silent"] = material_state()
        report["planted"]["writers"] = {}
        writers = dict(planted["writers"])
        prefs.command = writers.pop("params.json")  # a params.json of matfit's form, not to be kept beside the picture
        report["planted"]["blocked"] = operator(lambda: bpy.ops.matfit.fit(filepath=planted["blocked"]))
        report["planted"]["after_blocked"] = material_state()
        run_script(job["picture"]["script"])  # the earlier material again
        for kind, command in writers.items():  # each writes, as the output, what is not a params.json
            prefs.command = command
            report["planted"]["writers"][kind] = operator(lambda: bpy.ops.matfit.fit(filepath=planted["edited"]))
        report["planted"]["after_writers"] = material_state()
        if "crashes" in planted:  # a worker that ends during every fit: started again once, then one line
            run_script(job["picture"]["script"])
            before = material_state()
            prefs.command = planted["crashes"]
            report["planted"]["crashes"] = operator(lambda: bpy.ops.matfit.fit(filepath=planted["edited"]))
            report["planted"]["crashes_unchanged"] = material_state() == before
        if "mute" in planted:  # a worker that stays alive and never answers: given up after what the fit can take
            run_script(job["picture"]["script"])
            before = material_state()
            prefs.command = planted["mute"]
            extension.jobs.FIT_SECONDS, allowed = planted["mute_seconds"], extension.jobs.FIT_SECONDS
            start = time.monotonic()
            report["planted"]["mute"] = operator(lambda: bpy.ops.matfit.fit(filepath=planted["edited"]))
            report["planted"]["mute_seconds"] = time.monotonic() - start
            extension.jobs.FIT_SECONDS = allowed
            report["planted"]["mute_unchanged"] = material_state() == before
        prefs.command, prefs.fit_options = job["command"], planted["redirect"]
        report["planted"]["redirect"] = operator(lambda: bpy.ops.matfit.fit(filepath=planted["edited"]))
        report["planted"]["after_redirect"] = material_state()
        prefs.fit_options = job["fit_options"]
        report["planted"]["fit"] = operator(lambda: bpy.ops.matfit.fit(filepath=planted["edited"]))
        report["planted"]["fitted"] = material_state()

    if "follow" in job:  # what the Follow operator does at each timer tick, ticked here
        build_scene()
        edited = job["follow"]["edited"]
        bpy.context.scene.matfit.edited = edited
        follower = extension.Follower(bpy.context)
        report["follow_idle"] = [follower.step(bpy.context), follower.status()]
        bpy.ops.ed.undo_push(message="before the followed fit")
        before = scene_state()
        shutil.copy(job["follow"]["saved"], edited)  # the 2D editor saves the picture
        seen = os.stat(edited).st_mtime_ns
        os.utime(edited, ns=(seen, max(seen, follower.seen) + 10**9))
        line, deadline, stages = None, time.monotonic() + 600, []
        while line is None and time.monotonic() < deadline:
            time.sleep(0.25)
            line = follower.step(bpy.context)
            fitting = follower.fitting
            if fitting is not None and fitting.shown is not None and fitting.shown[0] not in stages:
                stages.append(fitting.shown[0])
        report["follow"] = line
        report["follow_shown"] = stages
        report["follow_fitted"] = material_state()
        bpy.ops.ed.undo()  # the followed fit is one undo step
        report["follow_undone"] = [scene_state(), before]
        bpy.ops.ed.redo()
        report["follow_redone"] = material_state()

    if "stages" in job:  # Fit from the panel, its timer ticked here: the answers shown as they land, then the final
        stages = job["stages"]
        build_scene()
        run_script(job["picture"]["script"])  # an earlier material "matfit" on the selected meshes
        before = scene_state()
        fitting = extension.Fitting(bpy.context, stages["edited"])
        states = shown(fitting, extension)
        report["stages"] = {"before": before, "shown": states, "line": fitting.finish(), "after": scene_state()}
        # cancelled (Esc) once the neural answer is on the meshes: each mesh's materials as they were
        build_scene()
        before = scene_state()
        fitting = extension.Fitting(bpy.context, stages["edited"])
        states = shown(fitting, extension, wanted="neural")
        fitting.cancel()
        report["stages"]["cancelled"] = {"before": before, "shown": states, "after": scene_state()}
        # a fit that fails once its neural answer is on the meshes: the same
        prefs.command = stages["fails"]
        build_scene()
        before = scene_state()
        fitting = extension.Fitting(bpy.context, stages["edited"])
        states = shown(fitting, extension, wanted="neural")
        open(stages["go"], "w").close()  # its answer now: a failure
        fitting.wait()
        try:
            line = fitting.finish()
        except Exception as error:  # what the operator reports in one line
            line = extension.one_line(error)
        report["stages"]["failed"] = {"before": before, "shown": states, "line": line, "after": scene_state()}
        prefs.command = job["command"]

    if "cancel" in job:  # what Esc does to a running fit
        running = extension.jobs.Job(prefs.command, ["fit", job["cancel"], "-o", job["cancel"] + ".json"])
        time.sleep(1.0)
        status = running.status()
        start = time.monotonic()
        running.cancel()
        report["cancel"] = {"status": status, "code": running.poll(), "seconds": time.monotonic() - start}
    with open(report_path, "w") as file:
        json.dump(report, file)


if __name__ == "__main__":
    main(*sys.argv[1:3])
