"""The material: the 19 shader parameters by name (`Material`), its params.json, Mitsuba and Blender forms, and its
render in the test scene (`render`)."""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from matfit import documents, params
from matfit.api.arguments import MAX_SIZE, Image, material_values, path_of, shown, whole
from matfit.errors import MatfitError, ParameterError, RenderError

if TYPE_CHECKING:
    from matfit.api.scenes import Scene
    from matfit.rendering.engine import Renderer

Array = npt.NDArray[np.float64]


def _default(name: str) -> float:
    return float(params.DEFAULTS[params.INDEX[name]])


@dataclass(frozen=True)
class Material:
    """A material: the 19 shader parameters by name, in physical units (`matfit params` lists their ranges).

    Names left out take their defaults; a value out of its range raises `MatfitError`. Edit one with
    `dataclasses.replace(material, roughness=0.1)`.
    """

    base_color_r: float = _default("base_color_r")
    base_color_g: float = _default("base_color_g")
    base_color_b: float = _default("base_color_b")
    metallic: float = _default("metallic")
    roughness: float = _default("roughness")
    anisotropic: float = _default("anisotropic")
    specular: float = _default("specular")
    spec_tint: float = _default("spec_tint")
    sheen: float = _default("sheen")
    sheen_tint: float = _default("sheen_tint")
    clearcoat: float = _default("clearcoat")
    clearcoat_gloss: float = _default("clearcoat_gloss")
    spec_trans: float = _default("spec_trans")
    medium_color_r: float = _default("medium_color_r")
    medium_color_g: float = _default("medium_color_g")
    medium_color_b: float = _default("medium_color_b")
    density: float = _default("density")
    scattering: float = _default("scattering")
    phase_g: float = _default("phase_g")

    def __post_init__(self) -> None:
        for name in params.NAMES:
            value = getattr(self, name)
            if isinstance(value, np.generic):  # a NumPy scalar (np.float32 is no float)
                value = value.item()
            object.__setattr__(self, name, params.check_value(name, value))

    @classmethod
    def from_array(cls, values: npt.ArrayLike) -> Material:
        """Returns the material of 19 physical values in `params.NAMES` order (`array()`'s)."""
        return cls(*(float(value) for value in material_values("values", values)))

    @classmethod
    def from_unit(cls, unit: npt.ArrayLike) -> Material:
        """Returns the material of 19 unit-cube coordinates (each parameter's range mapped onto [0, 1])."""
        return cls.from_array(params.from_unit(material_values("unit", unit)))

    @classmethod
    def from_dict(cls, values: Mapping[str, float]) -> Material:
        """Returns the material of named values; names left out take their defaults, unknown names are refused."""
        if not isinstance(values, Mapping):
            raise ParameterError(
                f'values {shown(values)} is no mapping of names to values: give a dict like {{"roughness": 0.2}}',
                field="values",
            )
        for name in values:
            if not isinstance(name, str):
                raise ParameterError(
                    f"parameter name {shown(name)} is not text: give the names `matfit params` lists", field="values"
                )
        plain = {name: value.item() if isinstance(value, np.generic) else value for name, value in values.items()}
        return cls.from_array(params.from_mapping(plain))

    @classmethod
    def from_json(cls, text: str | bytes) -> Material:
        """Returns the material of a params.json text (what `to_json` and `matfit fit` write, or a flat object)."""
        if not isinstance(text, str | bytes):
            raise ParameterError(
                f"text {shown(text)} is no params.json text: give its str or bytes (Material.read reads a file)",
                field="text",
            )
        return cls.from_array(params.parse_params_json(text))

    @classmethod
    def read(cls, path: str | os.PathLike[str]) -> Material:
        """Returns the material of a params.json file."""
        return cls.from_array(params.read_file(path_of("path", path, ParameterError, "give a params.json file's path")))

    @classmethod
    def preset(cls, name: str) -> Material:
        """Returns a named material (`presets()` lists them)."""
        from matfit.rendering import presets

        return cls.from_array(presets.preset(name))

    @classmethod
    def presets(cls) -> dict[str, Material]:
        """Returns every named material: gold, glass, jade, milk and the others of `matfit presets`."""
        from matfit.rendering import presets

        return {name: cls.preset(name) for name in presets.PRESETS}

    def array(self) -> Array:
        """Returns the 19 physical values, float64, in `params.NAMES` order."""
        return np.array([getattr(self, name) for name in params.NAMES], dtype=np.float64)

    def unit(self) -> Array:
        """Returns the 19 unit-cube coordinates the networks and optimisers see."""
        return np.asarray(params.to_unit(self.array()), dtype=np.float64)

    def to_dict(self) -> dict[str, float]:
        """Returns the named values."""
        return {name: float(getattr(self, name)) for name in params.NAMES}

    def to_json(self) -> str:
        """Returns the material as params.json text: values rounded to 6 decimals, with their units."""
        return documents.dumps(params.params_document(self.array()))

    def to_mitsuba(self) -> dict[str, Any]:
        """Returns {"bsdf": the principled BSDF, "interior": the homogeneous medium} as plain `mi.load_dict` data.

        Spread it into a shape (`{"type": "sphere", **material.to_mitsuba()}`); the medium shows with a volumetric
        integrator (`volpath`, `volpathmis`) on a closed shape, and only where the BSDF transmits (`spec_trans`).
        """
        from matfit.rendering import scene

        values = self.array()
        return {"bsdf": scene.bsdf(values), "interior": scene.medium(values)}

    def to_mitsuba_xml(self) -> str:
        """Returns a Mitsuba 3 XML scene to `<include>`: ids `matfit-material` (the BSDF) and `matfit-interior`."""
        from matfit.rendering import export

        return export.mitsuba_xml(self.array())

    def to_blender_script(self, name: str = "matfit") -> str:
        """Returns a Python script that builds the material, named `name`, on Blender 4.x's selected meshes."""
        from matfit.rendering import export

        if not isinstance(name, str):
            raise ParameterError(
                f"name {shown(name)} is not text: give the material's name, like 'matfit'", field="name"
            )
        try:
            return export.blender_script(self.array(), name)
        except MatfitError:
            raise
        except ValueError as error:  # the name
            raise ParameterError(str(error), field="name") from None


_renderers: dict[tuple[int, str | None], Renderer] = {}


def render(
    material: Material,
    *,
    size: int = 256,
    spp: int = 256,
    seed: int = 0,
    variant: str | None = None,
    scene: Scene | None = None,
) -> Image:
    """Returns the material rendered by Mitsuba in the test scene: linear RGB float32 (size, size, 3).

    `scene`: a `Scene` of your own instead, its shape given the material: (H, W, 3) with `size` pixels on the longer
    side and the camera's aspect.

    `seed` makes the noise: the same arguments give the same picture. The scene is loaded once a size and kept.
    Where no libLLVM >= 19 is found (and no GPU), it renders with the slower scalar_rgb and warns once
    (RuntimeWarning, the notice `matfit render` prints).
    `images.srgb_encode` (or `fit(..., linear=True)`) takes it from there.
    """
    from matfit.model import dataset
    from matfit.rendering import engine

    if not isinstance(material, Material):
        raise ParameterError(
            f"render takes a matfit.Material, got {type(material).__name__}: use Material.read(path), "
            "Material.preset(name) or Material.from_dict(...)",
            field="material",
        )
    if scene is not None:
        from matfit.api import scenes

        return scenes.render_values(material.array(), scene, size=size, spp=spp, seed=seed, variant=variant)
    size = whole("size", size, dataset.MIN_RESOLUTION, MAX_SIZE, RenderError)
    spp = whole("spp", spp, 1, dataset.MAX_SPP, RenderError)
    seed = whole("seed", seed, 0, params.MAX_SEED, RenderError)
    key = (size, variant)
    if key not in _renderers:
        made = engine.Renderer(size, spp, variant)
        if made.notice:  # the slower scalar_rgb: said once a scene, as `matfit render` says it
            warnings.warn(made.notice.removeprefix("notice: "), RuntimeWarning, stacklevel=2)
        _renderers[key] = made
    return _renderers[key].render(material.array(), seed=seed, spp=spp)
