import ast

import numpy as np
import pytest

from matfit import params
from matfit.rendering import export, presets


@pytest.mark.parametrize("name", ["gold", "amber-glass", "jade"])
def test_mitsuba_xml_loads_back_with_the_same_values(renderer, tmp_path, name):
    values = presets.preset(name)
    path = tmp_path / "mat.xml"
    path.write_text(export.mitsuba_xml(values))
    mi = renderer.mi
    scene = mi.load_string(
        f'<scene version="3.0.0"><include filename="{path}"/>'
        '<shape type="sphere"><ref id="matfit-material"/><ref name="interior" id="matfit-interior"/></shape></scene>'
    )
    loaded = mi.traverse(scene)
    v = dict(zip(params.NAMES, values, strict=True))
    np.testing.assert_allclose(np.array(loaded["matfit-material.base_color.value"]).ravel(), values[:3], rtol=1e-6)
    for key in (
        "metallic",
        "roughness",
        "anisotropic",
        "spec_tint",
        "sheen",
        "sheen_tint",
        "clearcoat",
        "clearcoat_gloss",
        "spec_trans",
    ):
        assert float(np.array(loaded[f"matfit-material.{key}.value"]).ravel()[0]) == pytest.approx(v[key], abs=1e-6)
    sigma_t, albedo = params.medium_coefficients(values)
    scale = float(np.array(loaded["matfit-interior.scale"]).ravel()[0])
    np.testing.assert_allclose(
        scale * np.array(loaded["matfit-interior.sigma_t.value.value"]).ravel(), sigma_t, rtol=1e-5
    )
    np.testing.assert_allclose(np.array(loaded["matfit-interior.albedo.value.value"]).ravel(), albedo, rtol=1e-6)
    assert float(np.array(loaded["matfit-interior.phase_function.g"]).ravel()[0]) == pytest.approx(
        v["phase_g"], abs=1e-6
    )


def test_blender_script_is_python_with_the_mapped_values():
    values = presets.preset("amber-glass")
    script = export.blender_script(values)
    tree = ast.parse(script)
    constants = {
        node.targets[0].id: ast.literal_eval(node.value)
        for node in tree.body
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name) and node.targets[0].id.isupper()
    }
    principled, volume = constants["PRINCIPLED"], constants["VOLUME"]
    assert principled["Transmission Weight"] == pytest.approx(values[params.INDEX["spec_trans"]])
    assert principled["Base Color"][:3] == pytest.approx(list(values[:3]))
    sigma_t, albedo = params.medium_coefficients(values)
    # absorption + scattering densities x colours give back sigma_a and sigma_s
    sigma_a = volume["absorption_density"] * (1 - np.array(volume["absorption_color"][:3]))
    sigma_s = volume["scatter_density"] * np.array(volume["scatter_color"][:3])
    np.testing.assert_allclose(sigma_a, (1 - albedo) * sigma_t, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(sigma_s, albedo * sigma_t, rtol=1e-6, atol=1e-9)
    assert principled["Coat Roughness"] ** 2 == pytest.approx(
        0.1 + (0.001 - 0.1) * values[params.INDEX["clearcoat_gloss"]]
    )
    assert principled["IOR"] == pytest.approx(export.eta_from_specular(values[params.INDEX["specular"]]))
