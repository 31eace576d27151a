"""A scene of the user's own: a Mitsuba 3 XML file and the id of the shape whose material matfit fits.

The file is read once (`read`): its shapes, its camera's film size, the files it names (meshes, images,
included XML: each must be there), and the fitted shape's own material where matfit can read it (a `principled`
BSDF, or a `diffuse` one as a principled without specular; nested in the shape or referenced by id). Every
render of it (`xml`) is the same file with three changes: the fitted shape's BSDF and interior medium become
matfit's principled BSDF and homogeneous medium of 19 parameters (`scene.bsdf`, `scene.medium`: the mapping
the test scene uses, so a material fitted here renders alike in the test scene and in the exports), the film
takes the size asked for (the camera's aspect kept), and the integrator may be replaced (the fit's
differentiable one). Camera, lights and every other shape stay as the file has them. The shape can also be
left out (`with_object=False`): the scene without it tells the fit which pixels the object changes (its
silhouette, its shadow, its reflections).

Written as ElementTree data rather than through a Mitsuba parser, so that reading the file and its checks
need no Mitsuba, and so that the shape's parameters live in `mi.traverse` under `<id>.bsdf...` and
`<id>.interior_medium...`, as the test scene's sphere does under `object.` (`engine.Keys`).
"""

from __future__ import annotations

import hashlib
import os
import re
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from typing import Any

import numpy as np

from matfit import params
from matfit.errors import SceneError
from matfit.rendering import export, scene

DEFAULT_FILM = (768, 576)  # Mitsuba's hdrfilm's width and height where the file gives none
MAX_SCENE_BYTES = 64 * 1024 * 1024  # an XML file larger than this is refused before parsing
# What one principled BSDF parameter of the file becomes: Mitsuba's own name is matfit's (scene.bsdf).
PRINCIPLED = ("metallic", "roughness", "anisotropic", "specular", "spec_tint", "sheen", "sheen_tint", "clearcoat",
              "clearcoat_gloss", "spec_trans")  # fmt: skip


@dataclass(frozen=True)
class SceneFile:
    """A Mitsuba scene file read and checked: where it lies, the shape fitted, its film, its shape's material."""

    path: str  # the XML file, absolute
    object: str  # the id of the shape whose material is fitted
    text: str  # the file's XML
    sha256: str  # of the file's bytes (params.json records it)
    width: int  # the camera's film, pixels
    height: int
    shapes: tuple[str, ...]  # the ids of every shape with one, in file order
    own: np.ndarray | None  # the shape's own material (19 physical values), where it could be read
    own_note: str  # how the shape's own material was read, or why not
    files: tuple[str, ...] = ()  # the files it names (meshes, images, included XML): inputs no output may replace

    @property
    def folder(self) -> str:
        """The folder the file's relative paths are read from."""
        return os.path.dirname(self.path)

    @property
    def aspect(self) -> float:
        """Width over height of the camera's film."""
        return self.width / self.height

    def size(self, longest: int) -> tuple[int, int]:
        """Returns (width, height) of a render whose longer side is `longest` pixels, the film's aspect kept."""
        if self.width >= self.height:
            return longest, max(1, round(longest * self.height / self.width))
        return max(1, round(longest * self.width / self.height)), longest


def _defaults(root: ElementTree.Element) -> dict[str, str]:
    return {d.get("name", ""): d.get("value", "") for d in root.iter("default")}


def _resolved(value: str | None, defaults: dict[str, str]) -> str | None:
    """Returns an attribute's value with a `$name` of the file's `<default>`s put in."""
    if value is None:
        return None
    return re.sub(r"\$(\w+)", lambda match: defaults.get(match.group(1), match.group(0)), value)


def _film_size(root: ElementTree.Element, defaults: dict[str, str], path: str) -> tuple[int, int]:
    sensor = root.find("sensor")
    if sensor is None:
        raise SceneError(f"scene {path} has no <sensor>: give the scene its camera (a perspective sensor)", "scene")
    size = list(DEFAULT_FILM)
    film = sensor.find("film")
    for element in () if film is None else film.findall("integer"):
        name = element.get("name")
        if name in ("width", "height"):
            text = _resolved(element.get("value"), defaults) or ""
            if not text.isdigit() or int(text) < 1:
                raise SceneError(f"scene {path}: the film's {name} {text!r} is not a whole number >= 1", "scene")
            size[0 if name == "width" else 1] = int(text)
    return size[0], size[1]


def _named_files(root: ElementTree.Element, defaults: dict[str, str], folder: str) -> tuple[list[str], list[str]]:
    """Returns (the files the scene names (meshes, images, included XML) that are not there, those that are)."""
    missing, found = [], []
    for element in root.iter():
        value = None
        if element.tag == "include":
            value = element.get("filename")
        elif element.tag == "string" and element.get("name") == "filename":
            value = element.get("value")
        value = _resolved(value, defaults)
        if value and not os.path.isfile(os.path.join(folder, value)):
            missing.append(value)
        elif value:
            found.append(os.path.join(folder, value))
    return missing, found


def _values(element: ElementTree.Element, defaults: dict[str, str]) -> dict[str, list[float]]:
    """Returns the float and rgb values a BSDF element gives directly, by name (textures are not read)."""
    found = {}
    for child in element:
        if child.tag in ("float", "rgb"):
            text = _resolved(child.get("value"), defaults) or ""
            try:
                numbers = [float(part) for part in re.split(r"[,\s]+", text.strip()) if part]
            except ValueError:
                continue
            if numbers:
                found[child.get("name", "")] = numbers * 3 if len(numbers) == 1 and child.tag == "rgb" else numbers
    return found


def _own_material(
    root: ElementTree.Element, shape: ElementTree.Element, defaults: dict[str, str]
) -> tuple[np.ndarray | None, str]:
    """Returns (the shape's material as 19 physical values, or None; how it was read or why not)."""
    bsdf = shape.find("bsdf")
    if bsdf is None:
        reference = next((r for r in shape.findall("ref") if r.get("name") in (None, "bsdf")), None)
        if reference is not None:
            bsdf = next((b for b in root.iter("bsdf") if b.get("id") == reference.get("id")), None)
    if bsdf is None:
        return None, "the shape has no BSDF of its own"
    inner = bsdf.find("bsdf")
    while bsdf.get("type") in ("twosided", "mask") and inner is not None:
        bsdf, inner = inner, inner.find("bsdf")
    kind = bsdf.get("type")
    given = _values(bsdf, defaults)
    values = params.DEFAULTS.astype(np.float64).copy()
    index = params.INDEX
    if kind == "principled":
        if "base_color" in given:
            values[index["base_color_r"] : index["base_color_b"] + 1] = given["base_color"][:3]
        for name in PRINCIPLED:
            if name in given:
                values[index[name]] = given[name][0]
        values[index["density"]] = 0.0  # a medium is not read: the fit starts clear
        note = "the shape's principled BSDF"
    elif kind == "diffuse":
        if "reflectance" not in given:
            return None, "the shape's diffuse BSDF has a texture, which matfit does not read"
        values[index["base_color_r"] : index["base_color_b"] + 1] = given["reflectance"][:3]
        values[index["metallic"]], values[index["specular"]], values[index["roughness"]] = 0.0, 0.0, 1.0
        values[index["spec_trans"]], values[index["density"]] = 0.0, 0.0
        note = "the shape's diffuse BSDF, as a principled one without specular"
    else:
        return None, f"the shape's {kind} BSDF is not read by matfit (principled and diffuse are)"
    low, high = params.LOW.astype(np.float64), params.HIGH.astype(np.float64)
    return np.clip(values, low, high), note


def read(path: str, object: str) -> SceneFile:
    """Returns the scene file at `path` read and checked, with `object` the id of the shape to fit (SceneError if
    it cannot be used: not XML, no camera, a file it names missing, no such shape, the shape an emitter)."""
    if not isinstance(object, str) or not object:
        raise SceneError(f"object {object!r} is no shape id: give the id of the shape whose material to fit", "object")
    if not os.path.isfile(path):
        raise SceneError(f"scene {path} is not a file: give a Mitsuba 3 XML scene", "scene")
    if os.path.getsize(path) > MAX_SCENE_BYTES:
        raise SceneError(
            f"scene {path} is over {MAX_SCENE_BYTES >> 20} MB: give the meshes as files beside it", "scene"
        )
    with open(path, "rb") as file:
        data = file.read()
    try:
        root = ElementTree.fromstring(data)
    except ElementTree.ParseError as error:
        raise SceneError(f"scene {path} is not XML ({error}): give a Mitsuba 3 XML scene", "scene") from None
    if root.tag != "scene":
        raise SceneError(f"scene {path}'s root is <{root.tag}>, not <scene>: give a Mitsuba 3 XML scene", "scene")
    defaults = _defaults(root)
    folder = os.path.dirname(os.path.abspath(path))
    missing, named = _named_files(root, defaults, folder)
    if missing:
        raise SceneError(
            f"scene {path} names {missing[0]!r}, which is not in {folder}: put the file beside the scene, or fix the "
            "path" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""),
            "scene",
        )
    shapes = [shape for shape in root.iter("shape")]
    ids = tuple(shape.get("id", "") for shape in shapes if shape.get("id"))
    chosen = [shape for shape in shapes if shape.get("id") == object]
    if not chosen:
        listed = ", ".join(ids[:12]) + (" ..." if len(ids) > 12 else "")
        raise SceneError(
            f"object {object!r} is not a shape of {path}: "
            + (f"its shapes with an id are {listed}" if ids else 'no shape in it has an id: give the shape id="..."'),
            "object",
        )
    shape = chosen[0]
    if shape.find("emitter") is not None:
        raise SceneError(
            f"object {object!r} is an emitter (an area light) in {path}: give the id of the shape whose material "
            "to fit",
            "object",
        )
    width, height = _film_size(root, defaults, path)
    own, note = _own_material(root, shape, defaults)
    return SceneFile(
        os.path.abspath(path),
        object,
        data.decode("utf-8", "replace"),
        hashlib.sha256(data).hexdigest(),
        width,
        height,
        ids,
        own,
        note,
        tuple(named),
    )


def _material_elements(values: np.ndarray) -> list[ElementTree.Element]:
    """Returns matfit's principled BSDF and interior medium of a material as XML elements, for inside a shape."""
    return [export.element("bsdf", scene.bsdf(values)), export.element("medium", scene.medium(values), name="interior")]


def xml(
    scene_file: SceneFile,
    values: np.ndarray,
    size: tuple[int, int],
    *,
    integrator: dict[str, object] | None = None,
    with_object: bool = True,
) -> str:
    """Returns the scene's XML with the fitted shape's material set to `values` (19 physical values), the film
    `size` (width, height), and `integrator` ({"type": ..., "max_depth": ...}) in place of the file's if given."""
    root = ElementTree.fromstring(scene_file.text)
    for parent in root.iter():
        for child in list(parent):
            if child.tag == "shape" and child.get("id") == scene_file.object:
                if not with_object:
                    parent.remove(child)
                    continue
                for old in list(child):
                    material = old.tag == "bsdf" or (old.tag == "medium" and old.get("name") == "interior")
                    if material or (old.tag == "ref" and old.get("name") in (None, "bsdf", "interior")):
                        child.remove(old)
                for element in _material_elements(values):
                    child.append(element)
    sensor = root.find("sensor")
    assert sensor is not None  # read() checked it
    film = sensor.find("film")
    if film is None:
        film = ElementTree.SubElement(sensor, "film", type="hdrfilm")
    for element in film.findall("integer"):
        if element.get("name") in ("width", "height"):
            film.remove(element)
    ElementTree.SubElement(film, "integer", name="width", value=str(size[0]))
    ElementTree.SubElement(film, "integer", name="height", value=str(size[1]))
    for element in film.findall("string"):
        if element.get("name") == "pixel_format":
            film.remove(element)
    ElementTree.SubElement(film, "string", name="pixel_format", value="rgb")
    if integrator is not None:
        for old in root.findall("integrator"):
            root.remove(old)
        element = ElementTree.Element("integrator", type=str(integrator["type"]))
        for key, value in integrator.items():
            if key != "type":
                ElementTree.SubElement(element, "integer", name=key, value=str(value))
        root.insert(0, element)
    return ElementTree.tostring(root, encoding="unicode")


def load(mi: Any, scene_file: SceneFile, text: str) -> Any:
    """Returns the Mitsuba scene of `xml`'s text, its relative paths read from the file's folder (SceneError naming
    Mitsuba's complaint where it cannot load)."""
    # Mitsuba's file resolver is the process's: this scene's folder goes first, so that a mesh of the same name in
    # another scene's folder (read earlier in this process) is never taken for this one's.
    resolver = mi.file_resolver()
    others = [str(path) for path in resolver if str(path) != scene_file.folder]
    resolver.clear()
    resolver.append(scene_file.folder)
    for path in others:
        resolver.append(path)
    import drjit

    threads = drjit.thread_count()
    if threads < 2:  # Mitsuba reads an EXR image on Dr.Jit's pool, and on one thread its read waits forever (measured)
        drjit.set_thread_count(2)
    try:
        return mi.load_string(text)
    except Exception as error:  # Mitsuba raises RuntimeError (and others) with a long trace of the XML
        message = str(error).strip().splitlines()[-1] if str(error).strip() else type(error).__name__
        raise SceneError(f"scene {scene_file.path} does not load in Mitsuba: {message[:300]}", "scene") from None
    finally:
        if threads < 2:
            drjit.set_thread_count(threads)


# Forward renders of a scene file (the picture to edit, the answer's render) use matfit's own integrator
# (`scene.INTEGRATOR`: volpathmis, so the interior medium shows), whatever the file's, without Russian roulette:
# Mitsuba 3.9's volpathmis divides a path's weight by the roulette's survival but not the weight its emitter
# sampling is set against, so where a path goes on past the roulette's depth and hits an emitter its light is
# under-counted. The bench's box under the sky read 0.4% darker with the jade cleared than `path`, `volpath` and
# `prbvolpath` (which the fit's steps render with), and with the jade 0.8 / 0.4 / 0.8%, 0.63 of 255 judged against
# the steps' renders; without the roulette alike within 1e-4, its renders 1.4 times as long and less noisy there
# (docs/scenes.md#the-roulettes-darkening). A fit whose material shows no medium judges with `path`
# (OPAQUE_INTEGRATOR), which renders an opaque material alike at a third of the time.
INTEGRATOR = {**scene.INTEGRATOR, "rr_depth": scene.MAX_DEPTH}
OPAQUE_INTEGRATOR = {"type": "path", "max_depth": 16}


class Renderer:
    """A scene file loaded once at one size, rendering any material of its shape (and the scene without the shape)."""

    def __init__(
        self,
        scene_file: SceneFile,
        size: tuple[int, int],
        variant: str | None = None,
        integrator: dict[str, object] | None = None,
    ):
        from matfit.rendering import engine

        self.variant, self.notice = engine.choose_variant(variant)
        self.mi = engine.mitsuba(self.variant)
        self.scene_file, self.size = scene_file, size
        self.integrator = dict(integrator or INTEGRATOR)
        start = scene_file.own if scene_file.own is not None else scene.all_lobes_values()
        self.scene = load(self.mi, scene_file, xml(scene_file, start, size, integrator=self.integrator))
        self.parameters = self.mi.traverse(self.scene)
        self.keys = engine.Keys(scene_file.object)
        self._without: Any = None

    def render(self, values: np.ndarray, seed: int = 0, spp: int = 64) -> np.ndarray:
        """Returns the linear float32 (H, W, 3) render of the scene with the shape's material set to `values`."""
        from matfit.rendering import engine

        engine.set_material(self.mi, self.parameters, values, self.keys)
        image = self.mi.render(self.scene, seed=int(seed) & 0xFFFFFFFF, spp=int(spp))
        return np.array(image, dtype=np.float32)[:, :, :3]

    def render_without(self, seed: int = 0, spp: int = 64) -> np.ndarray:
        """Returns the linear float32 (H, W, 3) render of the scene without the fitted shape."""
        if self._without is None:
            start = scene.all_lobes_values()
            text = xml(self.scene_file, start, self.size, integrator=self.integrator, with_object=False)
            self._without = load(self.mi, self.scene_file, text)
        image = self.mi.render(self._without, seed=int(seed) & 0xFFFFFFFF, spp=int(spp))
        return np.array(image, dtype=np.float32)[:, :, :3]
