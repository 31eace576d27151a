"""matfit in Blender: a picture of the active material for a 2D editor, and the edited picture back to a material.

A panel in the Material properties (docs/blender.md#the-extension) with operators, each of which
runs the matfit command line (its path in the extension's preferences) in a subprocess:
- `matfit.picture`: reads the active material (`material.read`) into matfit's parameters through
  blender_mapping, the table the export writes with, and renders it in matfit's test scene
  (`matfit render`) to a PNG;
- `matfit.fit`: fits the edited picture (`matfit fit ... -o params.json` into the job's own new
  folder, run by the session's `matfit worker`, which keeps the model and Mitsuba loaded) and builds
  the material from that params.json through blender_mapping.to_blender (`material.write`), as the
  exported script would, on the meshes selected when it started (`Fitting`); while it runs, each
  earlier answer the worker sends (the neural search's first, not yet checked in Mitsuba) is put on
  them at once, and a fit that fails or is cancelled puts back the materials they had. The whole fit
  is one undo step. No script is run: a
  params.json this job did not write, or none, is one report line and the material stays as it was.
- `matfit.scene_picture` ("Picture of this object"): exports the current scene for Mitsuba (`scene_export`) and
  renders the active object's material in it (`matfit render --scene`), the scene kept beside the picture;
- `matfit.scene_fit` ("Fit edited picture in this scene"): fits the edited picture in that scene
  (`matfit fit --scene`, in the worker) and puts the material on the active object alone, one undo step.
From the panel they run in the background (a timer polls the subprocess, its last line in the status
bar, Esc cancels); called from Python (`bpy.ops.matfit.fit(filepath=...)`, as headless Blender and
the tests do) they wait for it, and only the final answer is put on the meshes. `matfit.follow` refits each
time the edited file changes (`Follower`, one step per timer tick), each fit as Fit's from the panel, one undo
step each.
Every failure is one line in Blender's report, never a traceback.
"""

import json
import os
import shutil
import tempfile

import bpy
from bpy.props import BoolProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from . import blender_mapping, fitted, jobs, material, scene_export

with open(os.path.join(os.path.dirname(__file__), "parameters.json")) as _file:
    TABLE = json.load(_file)  # matfit's params.table(): names, bounds, defaults
with open(os.path.join(os.path.dirname(__file__), "medium.json")) as _file:
    MINIMUM_EXTINCTION = json.load(_file)["minimum_extinction"]  # params.MINIMUM_EXTINCTION
BOUNDS = {p["name"]: (p["low"], p["high"]) for p in TABLE}
NAME = "matfit"  # the fitted material, as the exported script names it
PREVIEW = f"{NAME} (not final)"  # a running fit's earlier answer, on the meshes until its final one replaces it
POLL_SECONDS = 0.25
OUTPUT_OPTIONS = ("-o", "--output")


def preferences(context):
    return context.preferences.addons[__package__].preferences


class MatfitPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    command: StringProperty(
        name="matfit command",
        description="The matfit executable (or a command line such as 'python -m matfit')",
        default="matfit",
    )
    size: IntProperty(name="Picture size", description="Side of the picture in pixels", default=512, min=8)
    spp: IntProperty(name="Samples per pixel", description="Of the picture and the fit's renders", default=256, min=1)
    fit_options: StringProperty(
        name="Fit options", description="More options for `matfit fit`, e.g. '--method nn'", default=""
    )
    scene_fit_options: StringProperty(
        name="Scene fit options",
        description="More options for `matfit fit --scene` (Fit edited picture in this scene), e.g. '--refine 24'",
        default="",
    )

    def draw(self, context):
        for name in ("command", "size", "spp", "fit_options", "scene_fit_options"):
            self.layout.prop(self, name)


class MatfitSettings(bpy.types.PropertyGroup):
    picture: StringProperty(
        name="Picture", description="Where the picture is saved", default="//matfit-picture.png", subtype="FILE_PATH"
    )
    edited: StringProperty(
        name="Edited picture", description="The picture as the 2D editor saved it", subtype="FILE_PATH"
    )
    radius: FloatProperty(
        name="Object radius",
        description="The medium's densities are per unit of this radius; 0: half the active object's largest side",
        default=0.0,
        min=0.0,
    )
    following: BoolProperty(name="Following", default=False)
    scene_picture: StringProperty(
        name="Scene picture",
        description="The last Picture of this object: its scene (NAME.scene) is the one Fit in this scene fits in",
        subtype="FILE_PATH",
    )


def one_line(error):
    """Returns the report line of an error: the extension's own as written, any other with its kind."""
    if isinstance(error, (material.MaterialError, jobs.JobError, fitted.FitError, scene_export.ExportError)):
        return str(error)
    text = str(error).strip().splitlines()
    return f"matfit: {type(error).__name__}: {text[-1] if text else 'no message'}"


def _absolute(path):
    """Returns a panel path as an absolute one: "//" is the .blend file's folder, or the home folder while unsaved."""
    if path.startswith("//") and not bpy.data.filepath:
        return os.path.join(os.path.expanduser("~"), path[2:])
    return os.path.abspath(bpy.path.abspath(path))


def _writable_folder(path):
    """Raises JobError unless a file can be written beside the picture `path` (its folder made if need be)."""
    folder = os.path.dirname(path)
    try:
        os.makedirs(folder, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder):
            pass
    except OSError as error:
        raise jobs.JobError(
            f"matfit: cannot write the picture {path} ({error.strerror or error}): "
            "choose a folder you can write to in the panel's Picture"
        ) from None


def _save(path, data):
    """Writes `data` (bytes) to `path` as a new file put in place, never through a link; returns None or why not."""
    try:
        descriptor, temporary = tempfile.mkstemp(dir=os.path.dirname(path), prefix=".matfit-")
    except OSError as error:
        return f"{os.path.basename(path)} not saved ({error.strerror or error})"
    try:
        with os.fdopen(descriptor, "wb") as file:
            file.write(data)
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    except OSError as error:
        os.unlink(temporary)
        return f"{os.path.basename(path)} not saved ({error.strerror or error})"
    return None


def _radius(context, settings):
    if settings.radius > 0:
        return settings.radius
    obj = context.active_object
    return max(obj.dimensions) / 2 if obj is not None and max(obj.dimensions) > 0 else 1.0


class _Background:
    """What both operators share: start a job, wait for it (execute) or poll it (invoke + modal), then finish."""

    _job = None
    _timer = None

    def _run(self, context):
        try:
            self._job = self.start(context)
        except Exception as error:  # every failure is one report line, never a traceback
            self.report({"ERROR"}, one_line(error))
            return False
        return True

    def _end(self, context):
        note = getattr(self._job, "note", None)  # a fit run without matfit's worker says so, once
        if note:
            self.report({"INFO"}, note)
        try:
            self.finish(context, self._job)
        except Exception as error:  # every failure is one report line, never a traceback
            self.report({"ERROR"}, one_line(error))
            return {"CANCELLED"}
        return {"FINISHED"}

    def execute(self, context):
        if not self._run(context):
            return {"CANCELLED"}
        self._job.wait()
        return self._end(context)

    def invoke(self, context, event):
        if not self._run(context):
            return {"CANCELLED"}
        manager = context.window_manager
        self._timer = manager.event_timer_add(POLL_SECONDS, window=context.window)
        manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _stop(self, context):
        context.window_manager.event_timer_remove(self._timer)
        context.workspace.status_text_set(None)

    def running(self, context):
        """Called at each timer tick while the job runs (Fit shows the answers that landed)."""

    def modal(self, context, event):
        if event.type == "ESC":
            self._job.cancel()
            self._stop(context)
            self.report({"WARNING"}, f"matfit: {self.bl_label.lower()} cancelled")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if self._job.poll() is None:
            self.running(context)
            context.workspace.status_text_set(f"{self._job.status()} (Esc cancels)")
            return {"PASS_THROUGH"}
        self._stop(context)
        return self._end(context)


class MATFIT_OT_picture(_Background, bpy.types.Operator):  # noqa: N801 (Blender's naming of operators and panels)
    """Render the active material in matfit's test scene and save the picture, to edit in a 2D editor"""

    bl_idname = "matfit.picture"
    bl_label = "Picture of this material"

    @classmethod
    def poll(cls, context):
        return context.object is not None

    def start(self, context):
        settings = context.scene.matfit
        principled, volume, self._notes = material.read(context.object.active_material, _radius(context, settings))
        values, _, notes = blender_mapping.from_blender(principled, volume, BOUNDS)
        self._notes += notes
        self._picture = _absolute(settings.picture)
        _writable_folder(self._picture)
        self._source = json.dumps({"params": values}, indent=2).encode()
        prefs = preferences(context)
        options = ["--size", str(prefs.size), "--spp", str(prefs.spp)]
        # The parameters go to the job's own folder and beside the picture only once it is rendered:
        # a render matfit refuses (a .gif) leaves nothing behind.
        folder = jobs.new_folder()
        source = os.path.join(folder, "source.json")
        with open(source, "wb") as file:
            file.write(self._source)
        return jobs.Job(prefs.command, ["render", source, "-o", self._picture, *options], folder)

    def finish(self, context, job):
        try:
            job.check()
        finally:
            job.remove()
        # .source.json, not .params.json: a fit of the picture edited in place writes NAME.params.json
        unsaved = _save(os.path.splitext(self._picture)[0] + ".source.json", self._source)
        unmapped = [f"not mapped: {', '.join(self._notes)}"] if self._notes else []
        line = "; ".join([f"matfit: picture saved to {self._picture}", *unmapped, *([unsaved] if unsaved else [])])
        self.report({"WARNING"} if self._notes or unsaved else {"INFO"}, line)


class MATFIT_OT_fit(_Background, bpy.types.Operator):  # noqa: N801 (Blender's naming of operators and panels)
    """Fit the edited picture and put the material on the selected objects"""

    bl_idname = "matfit.fit"
    bl_label = "Fit edited picture"
    # One undo step, pushed as the fit finishes: the earlier answers shown while it ran are no step of their own.
    bl_options = {"REGISTER", "UNDO"}  # noqa: RUF012 (Blender's form)

    filepath: StringProperty(
        name="Edited picture", description="Default: the panel's Edited picture", subtype="FILE_PATH"
    )

    def start(self, context):
        return Fitting(context, self.filepath or context.scene.matfit.edited)

    def running(self, context):
        self._job.show()

    def finish(self, context, job):
        self.report({"INFO"}, job.finish())


def _edited(path):
    """Returns the edited picture's absolute path, or raises JobError where there is none."""
    if not path:
        raise jobs.JobError("matfit: choose the edited picture first (the panel's Edited picture)")
    edited = _absolute(path)
    if not os.path.isfile(edited):
        raise jobs.JobError(f"matfit: no edited picture at {edited}: choose the file the 2D editor saved")
    return edited


def _fit_options(text, label, saved):
    """Returns the words of the preferences' fit options, or raises JobError where they name an output."""
    options = jobs.split(text)
    for word in options:
        if word in OUTPUT_OPTIONS or word.startswith("--output=") or (word.startswith("-o") and word[:2] != "--"):
            raise jobs.JobError(
                f"matfit: the {label} name an output ({word}): remove it from the extension's preferences; "
                f"the fit's params.json is saved beside the picture as {os.path.basename(saved)}"
            )
    return options


def start_fit(context, path):
    """Returns the running `matfit fit` of the edited picture at `path`; remembers the path in the scene.

    The fit writes its params.json into the job's own new folder (`finish_fit` reads it from there
    only), and `finish_fit` saves a copy beside the picture as NAME.params.json.
    """
    edited = _edited(path)
    context.scene.matfit.edited = edited
    saved = os.path.splitext(edited)[0] + ".params.json"
    prefs = preferences(context)
    options = _fit_options(prefs.fit_options, "Fit options", saved)
    folder = jobs.new_folder()
    arguments = ["fit", edited, "--size", str(prefs.size), "--spp", str(prefs.spp), *options]
    job = jobs.WorkerJob(prefs.command, [*arguments, "-o", os.path.join(folder, "params.json")], folder)
    job.outputs = {"params": saved}
    return job


def build(name, values):
    """Returns the material `name` built from a fit's named values through blender_mapping.to_blender, as the export:
    the same inputs as the exported script's."""
    sigma_t, albedo = fitted.medium_coefficients(values, MINIMUM_EXTINCTION)
    principled, volume = blender_mapping.to_blender(values, sigma_t, albedo)
    with_volume = blender_mapping.has_volume(principled, volume)
    return material.write(bpy.data.materials, name, principled, volume, with_volume)


def finish_fit(job, objects):
    """Builds the material from the params.json this job wrote and puts it on the meshes among `objects`; returns the
    report line."""
    try:
        job.check()
        values, document, data = fitted.read(job.path("params.json"), TABLE, job.command)
        meshes = material.assign(build(NAME, values), objects)
        unsaved = _save(job.outputs["params"], data)
    finally:
        job.remove()
    hint = "" if meshes else " (select meshes and fit again to put it on them)"
    neural, mitsuba = fitted.figure(document, "neural_rmse"), fitted.figure(document, "mitsuba_rmse")
    figures = [f"neural RMSE {neural:.2f}"] if neural is not None else []
    figures += [f"Mitsuba RMSE {mitsuba:.2f}"] if mitsuba is not None else []  # absent with --no-verify
    figures += [unsaved] if unsaved else []
    return f"matfit: material {NAME!r} on {len(meshes)} selected mesh(es){hint}" + "".join(f", {f}" for f in figures)


class Fitting:
    """A fit of the edited picture (`start_fit`) for the meshes selected as it starts, with `WorkerJob`'s poll, wait,
    status, note and cancel: each earlier answer the worker sends (the neural search's first) is put on them as it
    lands (`show`, at each timer tick) in the material PREVIEW, then the final one from its params.json (`finish`).
    A fit that fails or is cancelled puts back the materials the meshes had before its first answer was shown.

    Nothing here pushes an undo step: Fit's own (as the operator finishes) and Follow's (after `finish`) hold the
    whole fit, the answers shown before it included.
    """

    def __init__(self, context, path):
        self.job = start_fit(context, path)
        self.meshes = [obj.name for obj in context.selected_objects if obj.type == "MESH"]  # names outlive an undo
        self.saved = None  # what the meshes' slots held before the first answer was shown
        self.shown = None  # (stage, params.json document) of the answer on the meshes

    @property
    def note(self):
        return self.job.note

    def poll(self):
        return self.job.poll()

    def wait(self):
        self.job.wait()

    def _objects(self):
        return [bpy.data.objects[name] for name in self.meshes if name in bpy.data.objects]

    def show(self):
        """Puts the latest answer that came since the last call on the meshes, in PREVIEW. One that is not matfit's
        params.json is not shown: the final answer's file is checked, and said wrong, as ever."""
        for stage, document in reversed(self.job.stages()):
            try:
                values = fitted.values(document, TABLE)
            except fitted.FitError:
                continue
            if self.saved is None:
                self.saved = material.slots(self._objects())
            material.assign(build(PREVIEW, values), self._objects())
            self.shown = (stage, document)
            return

    def status(self):
        """Returns the status bar's text: the job's, and the answer on the meshes while it runs."""
        if self.shown is None:
            return self.job.status()
        stage, document = self.shown
        mitsuba = fitted.figure(document, "mitsuba_rmse")
        checked = f"Mitsuba RMSE {mitsuba:.2f}" if mitsuba is not None else "not yet checked in Mitsuba"
        return f"{self.job.status()}; the {stage} answer shown, {checked}"

    def finish(self):
        """Returns the report line of the final answer put on the meshes (`finish_fit`); raises as it does, the meshes'
        materials put back."""
        try:
            line = finish_fit(self.job, self._objects())
        except BaseException:
            self._take_back()
            raise
        self._remove_preview()
        return line

    def cancel(self):
        self.job.cancel()
        self._take_back()

    def _take_back(self):
        if self.saved is not None:
            material.restore(self.saved)
        self._remove_preview()

    def _remove_preview(self):
        if self.saved is not None and PREVIEW in bpy.data.materials:
            bpy.data.materials.remove(bpy.data.materials[PREVIEW])
        self.saved = self.shown = None


def scene_picture_path(picture, shape):
    """Returns where the picture of the shape `shape` goes: the panel's Picture with the shape's id and the view
    transform in its name (`-standard`: sRGB of linear light, as Blender's Standard transform shows it; `-linear`
    for EXR and HDR), so that it is never taken for a picture of Blender's AgX or Filmic."""
    stem, extension = os.path.splitext(picture)
    transform = "linear" if extension.lower() in (".exr", ".hdr") else "standard"
    return f"{stem}-{shape}-{transform}{extension}"


def scene_folder(picture):
    """Returns the folder of the scene exported with a Picture of this object: NAME.scene beside NAME.png."""
    return os.path.splitext(picture)[0] + ".scene"


def _put_folder(source, target):
    """Moves the folder `source` to `target`, replacing the folder (or link, or file) there; returns None or why not."""
    try:
        if os.path.islink(target) or os.path.isfile(target):
            os.unlink(target)
        elif os.path.isdir(target):
            shutil.rmtree(target)
        shutil.move(source, target)
    except OSError as error:
        return f"{os.path.basename(target)} not saved ({error.strerror or error})"
    return None


class MATFIT_OT_scene_picture(_Background, bpy.types.Operator):  # noqa: N801 (Blender's naming of operators and panels)
    """Export this scene for Mitsuba and render the active object's material in it, to edit in a 2D editor"""

    bl_idname = "matfit.scene_picture"
    bl_label = "Picture of this object"

    @classmethod
    def poll(cls, context):
        return context.object is not None

    def start(self, context):
        settings, obj = context.scene.matfit, context.object
        folder = jobs.new_folder()
        try:
            self._export = scene_export.export(context, os.path.join(folder, "scene"), obj, TABLE)
            self._picture = scene_picture_path(_absolute(settings.picture), self._export.fitted)
            _writable_folder(self._picture)
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        self._object = obj.name
        self._source = json.dumps({"params": self._export.values}, indent=2).encode()
        source = os.path.join(folder, "source.json")
        with open(source, "wb") as file:
            file.write(self._source)
        prefs = preferences(context)
        arguments = ["render", source, "--scene", self._export.path, "--object", self._export.fitted]
        options = ["--size", str(prefs.size), "--spp", str(prefs.spp)]
        return jobs.Job(prefs.command, [*arguments, "-o", self._picture, *options], folder)

    def finish(self, context, job):
        try:
            job.check()
            # The scene and the parameters go beside the picture only once it is rendered.
            stem = os.path.splitext(self._picture)[0]
            unsaved = [_put_folder(job.path("scene"), scene_folder(self._picture))]
            unsaved.append(_save(stem + ".source.json", self._source))
        finally:
            job.remove()
        context.scene.matfit.scene_picture = self._picture
        unsaved = [line for line in unsaved if line]
        notes = [f"not carried: {'; '.join(self._export.notes)}"] if self._export.notes else []
        line = "; ".join(
            [
                f"matfit: picture of {self._object!r} in this scene saved to {self._picture} (Standard view "
                f"transform; shape {self._export.fitted!r} of {os.path.basename(scene_folder(self._picture))})",
                *notes,
                *unsaved,
            ]
        )
        self.report({"WARNING"} if notes or unsaved else {"INFO"}, line)


class MATFIT_OT_scene_fit(_Background, bpy.types.Operator):  # noqa: N801 (Blender's naming of operators and panels)
    """Fit the edited picture in the scene of the last Picture of this object and put the material on the object"""

    bl_idname = "matfit.scene_fit"
    bl_label = "Fit edited picture in this scene"
    bl_options = {"REGISTER", "UNDO"}  # noqa: RUF012 (Blender's form) the material put on the object: one undo step

    filepath: StringProperty(
        name="Edited picture", description="Default: the panel's Edited picture", subtype="FILE_PATH"
    )

    @classmethod
    def poll(cls, context):
        return context.object is not None

    def start(self, context):
        settings, obj = context.scene.matfit, context.object
        edited = _edited(self.filepath or settings.edited)
        picture = _absolute(settings.scene_picture) if settings.scene_picture else ""
        scene = os.path.join(scene_folder(picture), "scene.xml") if picture else ""
        if not scene or not os.path.isfile(scene):
            raise jobs.JobError(
                "matfit: no scene exported: make the object's picture first (Picture of this object), then edit it"
            )
        try:
            with open(os.path.join(scene_folder(picture), "matfit-export.json")) as file:
                shapes = json.load(file)["objects"]
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise jobs.JobError(
                f"matfit: cannot read the scene's matfit-export.json ({error}): make the picture again"
            ) from None
        if obj.name not in shapes:
            raise jobs.JobError(
                f"matfit: object {obj.name!r} is not in the scene of {os.path.basename(picture)}: make its picture "
                "(Picture of this object) first"
            )
        settings.edited = edited
        saved = os.path.splitext(edited)[0] + ".params.json"
        prefs = preferences(context)
        options = _fit_options(prefs.scene_fit_options, "Scene fit options", saved)
        self._object, self._shape = obj.name, shapes[obj.name]
        folder = jobs.new_folder()
        arguments = ["fit", edited, "--scene", scene, "--object", self._shape]
        arguments += ["--size", str(prefs.size), "--spp", str(prefs.spp), *options]
        job = jobs.WorkerJob(prefs.command, [*arguments, "-o", os.path.join(folder, "params.json")], folder)
        job.outputs = {"params": saved}
        return job

    def finish(self, context, job):
        """Builds the material `matfit OBJECT` from the params.json this job wrote and puts it on the object alone."""
        try:
            job.check()
            values, document, data = fitted.read(job.path("params.json"), TABLE, job.command)
            name = f"{NAME} {self._object}"
            # the medium per world unit: a scene's shape has matfit's medium at the scene's own scale (radius 1)
            built = build(name, values)
            obj = bpy.data.objects.get(self._object)
            material.assign(built, [obj] if obj is not None else [])
            unsaved = _save(job.outputs["params"], data)
        finally:
            job.remove()
        figures = []
        mitsuba = fitted.figure(document, "mitsuba_rmse")
        start = document.get("start")
        start_rmse = fitted.figure(start, "rmse") if isinstance(start, dict) else None
        if mitsuba is not None:
            figures.append(
                f"Mitsuba RMSE {mitsuba:.2f}" + (f" (start {start_rmse:.2f})" if start_rmse is not None else "")
            )
        figures += [unsaved] if unsaved else []
        where = "" if obj is not None else " (the object is gone: the material is kept)"
        self.report(
            {"INFO"},
            f"matfit: material {name!r} on {self._object!r}{where}, fitted in its scene"
            + "".join(f", {f}" for f in figures),
        )


class Follower:
    """Refits the edited picture each time its file changes: `step` once per timer tick, headless too. Each fit is
    Fit's (`Fitting`): its earlier answers shown as they land, the final one pushed as one undo step."""

    def __init__(self, context):
        settings = context.scene.matfit
        self.path = _absolute(settings.edited)
        if not settings.edited or not os.path.isfile(self.path):
            raise jobs.JobError("matfit: fit an edited picture once first: Follow watches that file")
        self.seen = os.stat(self.path).st_mtime_ns
        self.fitting = None
        self.note = None  # a fit run without matfit's worker says so, once

    def step(self, context):
        """Shows the running fit's latest answer, or finishes it once it has ended (one undo step), and starts one if
        the file changed; returns the finished fit's line."""
        line = None
        if self.fitting is not None and self.fitting.poll() is None:
            self.fitting.show()
        elif self.fitting is not None:
            fitting, self.fitting = self.fitting, None
            self.note = fitting.note
            line = fitting.finish()
            bpy.ops.ed.undo_push(message=f"matfit: fit of {os.path.basename(self.path)}")
        changed = os.stat(self.path).st_mtime_ns
        if self.fitting is None and changed != self.seen:
            self.seen = changed
            self.fitting = Fitting(context, self.path)
        return line

    def status(self):
        activity = self.fitting.status() if self.fitting is not None else "waiting for the picture to change"
        return f"matfit follows {os.path.basename(self.path)}: {activity} (Esc stops)"

    def stop(self):
        if self.fitting is not None:
            self.fitting.cancel()


class MATFIT_OT_follow(bpy.types.Operator):  # noqa: N801 (Blender's naming of operators and panels)
    """Refit each time the 2D editor saves the edited picture (Esc or the button stops)"""

    bl_idname = "matfit.follow"
    bl_label = "Follow the picture"

    _timer = None
    _follower = None

    def invoke(self, context, event):
        settings = context.scene.matfit
        if settings.following:
            settings.following = False  # the running operator sees it at its next tick and stops
            return {"FINISHED"}
        try:
            self._follower = Follower(context)
        except jobs.JobError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        settings.following = True
        # a step of its own, so that undoing a followed fit goes back to a scene that is still followed
        bpy.ops.ed.undo_push(message=f"matfit: {self.bl_label.lower()}")
        self._timer = context.window_manager.event_timer_add(POLL_SECONDS * 4, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC" or not context.scene.matfit.following:
            self._follower.stop()
            context.window_manager.event_timer_remove(self._timer)
            context.scene.matfit.following = False
            context.workspace.status_text_set(None)
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            line = self._follower.step(context)
            if line is not None:
                self.report({"INFO"}, line)
        except Exception as error:  # every failure is one report line, never a traceback
            self.report({"ERROR"}, one_line(error))
        if self._follower.note:
            self.report({"INFO"}, self._follower.note)
            self._follower.note = None
        context.workspace.status_text_set(self._follower.status())
        return {"PASS_THROUGH"}


class MATFIT_PT_material(bpy.types.Panel):  # noqa: N801 (Blender's naming of operators and panels)
    bl_label = "matfit"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "material"

    def draw(self, context):
        settings = context.scene.matfit
        layout = self.layout
        layout.prop(settings, "picture")
        layout.prop(settings, "radius")
        layout.operator(MATFIT_OT_picture.bl_idname, icon="RENDER_STILL")
        layout.separator()
        layout.prop(settings, "edited")
        layout.operator(MATFIT_OT_fit.bl_idname, icon="IMPORT")
        label = "Stop following" if settings.following else MATFIT_OT_follow.bl_label
        layout.operator(MATFIT_OT_follow.bl_idname, text=label, icon="FILE_REFRESH")
        layout.separator()
        layout.label(text="In this scene (Mitsuba, the Standard view transform)")
        layout.operator(MATFIT_OT_scene_picture.bl_idname, icon="SCENE")
        layout.operator(MATFIT_OT_scene_fit.bl_idname, icon="IMPORT")


CLASSES = (
    MatfitPreferences,
    MatfitSettings,
    MATFIT_OT_picture,
    MATFIT_OT_fit,
    MATFIT_OT_follow,
    MATFIT_OT_scene_picture,
    MATFIT_OT_scene_fit,
    MATFIT_PT_material,
)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.matfit = PointerProperty(type=MatfitSettings)


def unregister():
    jobs.stop_workers()
    del bpy.types.Scene.matfit
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
