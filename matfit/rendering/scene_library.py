"""Scenes that are not the test scene, written as Mitsuba XML files with their meshes beside them: the scenes
`matfit bench-scene` fits in, the tests' scene files, and examples of the file `matfit fit --scene` reads.

Two objects made in code (a torus knot, a rounded box: meshes written as binary PLY with normals and UVs) on a
grey floor, under three lightings: `studio` (a rectangular area light above-left and a dim constant
environment), `sky` (an environment image alone, the test scene's sky-to-ground gradient written as EXR) and
`sun` (a directional sun, a point light and a faint constant fill). The fitted shape's id is `object`.
"""

from __future__ import annotations

import os

import numpy as np

from matfit import images
from matfit.rendering import scene

OBJECTS = ("knot", "box")
LIGHTINGS = ("studio", "sky", "sun")
OBJECT_ID = "object"


def torus_knot(p: int = 2, q: int = 3, segments: int = 256, sides: int = 24, tube: float = 0.16) -> tuple:
    """Returns (positions, normals, uvs, triangles) of a (p, q) torus knot tube, about 1.3 units across."""
    t = np.linspace(0, 2 * np.pi, segments, endpoint=False)

    def curve(t: np.ndarray) -> np.ndarray:
        r = 0.6 + 0.25 * np.cos(q * t)
        return np.stack([r * np.cos(p * t), 0.25 * np.sin(q * t), r * np.sin(p * t)], axis=-1)

    centre = curve(t)
    tangent = curve(t + 1e-4) - curve(t - 1e-4)
    tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True)
    normal = np.cross(tangent, np.array([0.0, 1.0, 0.0]))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    binormal = np.cross(tangent, normal)
    angle = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.cos(angle)[None, :, None] * normal[:, None] + np.sin(angle)[None, :, None] * binormal[:, None]
    positions = (centre[:, None] + tube * ring).reshape(-1, 3)
    normals = ring.reshape(-1, 3)
    u, v = np.meshgrid(np.arange(segments) / segments, np.arange(sides) / sides, indexing="ij")
    uvs = np.stack([u.ravel(), v.ravel()], axis=-1)
    i, j = np.meshgrid(np.arange(segments), np.arange(sides), indexing="ij")
    a = i * sides + j
    b = ((i + 1) % segments) * sides + j
    c = ((i + 1) % segments) * sides + (j + 1) % sides
    d = i * sides + (j + 1) % sides
    triangles = np.concatenate(
        [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    )  # outwards
    return positions, normals, uvs, triangles


def rounded_box(resolution: int = 24, half: float = 0.55, radius: float = 0.18) -> tuple:
    """Returns (positions, normals, uvs, triangles) of a box with rounded edges: a cube's six faces, each a grid,
    pushed onto the surface at distance `radius` from the inner box of half-size `half - radius`."""
    inner = half - radius
    positions: list[np.ndarray] = []
    normals: list[np.ndarray] = []
    uvs: list[np.ndarray] = []
    triangles: list[np.ndarray] = []
    grid = np.linspace(-1.0, 1.0, resolution + 1)
    u, v = np.meshgrid(grid, grid, indexing="ij")
    for axis in range(3):
        for sign in (-1.0, 1.0):
            point = np.zeros((*u.shape, 3))
            others = [k for k in range(3) if k != axis]
            point[..., axis] = sign
            # the face's two axes in an order that makes its triangles face outwards
            first, second = (others[0], others[1]) if (sign > 0) == (axis != 1) else (others[1], others[0])
            point[..., first], point[..., second] = u, v
            # cube -> rounded box: clamp to the inner box, then out along the direction to the surface point
            on_cube = point * half
            core = np.clip(on_cube, -inner, inner)
            direction = on_cube - core
            direction /= np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-12)
            base = sum(len(p) for p in positions)
            positions.append((core + radius * direction).reshape(-1, 3))
            normals.append(direction.reshape(-1, 3))
            uvs.append(np.stack([(u.ravel() + 1) / 2, (v.ravel() + 1) / 2], axis=-1))
            i, j = np.meshgrid(np.arange(resolution), np.arange(resolution), indexing="ij")
            a = base + i * (resolution + 1) + j
            b = a + resolution + 1
            triangles.append(np.stack([a, b, b + 1], -1).reshape(-1, 3))
            triangles.append(np.stack([a, b + 1, a + 1], -1).reshape(-1, 3))
    return np.concatenate(positions), np.concatenate(normals), np.concatenate(uvs), np.concatenate(triangles)


def write_ply(path: str, mesh: tuple) -> None:
    """Writes a mesh (positions, normals, uvs, triangles) as binary little-endian PLY, the form Mitsuba reads."""
    positions, normals, uvs, triangles = mesh
    vertex = np.empty(len(positions), dtype=[(n, "<f4") for n in ("x", "y", "z", "nx", "ny", "nz", "u", "v")])
    for k, name in enumerate(("x", "y", "z")):
        vertex[name] = positions[:, k]
        vertex["n" + name] = normals[:, k]
    vertex["u"], vertex["v"] = uvs[:, 0], uvs[:, 1]
    faces = np.empty(len(triangles), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, triangles
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(positions)}\n"
        + "".join(f"property float {name}\n" for name in ("x", "y", "z", "nx", "ny", "nz", "u", "v"))
        + f"element face {len(triangles)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with open(path, "wb") as file:
        file.write(header.encode("ascii"))
        file.write(vertex.tobytes())
        file.write(faces.tobytes())


LIGHTS = {
    "studio": """  <emitter type="constant"><rgb name="radiance" value="0.12"/></emitter>
  <shape type="rectangle" id="key-light">
    <transform name="to_world"><scale x="0.8" y="0.8"/><lookat origin="-2.5, 3.5, 2.5" target="0, 0, 0" up="0, 1, 0"/>
    </transform>
    <emitter type="area"><rgb name="radiance" value="9"/></emitter>
  </shape>
""",
    "sky": """  <emitter type="envmap">
    <string name="filename" value="sky.exr"/><float name="scale" value="1.0"/>
  </emitter>
""",
    "sun": """  <emitter type="directional">
    <vector name="direction" value="0.4, -1, -0.5"/><rgb name="irradiance" value="2.5"/>
  </emitter>
  <emitter type="point"><point name="position" value="1.6, 1.4, 1.8"/><rgb name="intensity" value="3"/></emitter>
  <emitter type="constant"><rgb name="radiance" value="0.06"/></emitter>
""",
}

PLACEMENT = {  # the object's transform: resting on the floor (y = -0.55), turned to show its shape
    "knot": '<rotate x="1" angle="-20"/><rotate y="1" angle="25"/><translate y="-0.05"/>',
    "box": '<rotate y="1" angle="35"/><rotate x="1" angle="8"/>',
}


def write(folder: str, object: str = "knot", lighting: str = "studio", *, width: int = 128, height: int = 96) -> str:
    """Writes the scene `object` under `lighting` into `folder` (its XML, its mesh, the sky where used) and returns
    the XML file's path. The object's material there is a grey principled one."""
    if object not in OBJECTS or lighting not in LIGHTINGS:
        raise ValueError(f"scenes are {OBJECTS} x {LIGHTINGS}, not {object!r}, {lighting!r}")
    os.makedirs(folder, exist_ok=True)
    mesh = f"{object}.ply"
    if not os.path.isfile(os.path.join(folder, mesh)):
        write_ply(os.path.join(folder, mesh), torus_knot() if object == "knot" else rounded_box())
    if lighting == "sky" and not os.path.isfile(os.path.join(folder, "sky.exr")):
        images.write(os.path.join(folder, "sky.exr"), scene.environment_map(64, 128))
    path = os.path.join(folder, f"{object}-{lighting}.xml")
    text = f"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="12"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="38"/>
    <transform name="to_world"><lookat origin="0, 1.1, 3.6" target="0, -0.1, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="64"/></sampler>
    <film type="hdrfilm"><integer name="width" value="{width}"/><integer name="height" value="{height}"/></film>
  </sensor>
{LIGHTS[lighting]}  <shape type="ply" id="{OBJECT_ID}">
    <string name="filename" value="{mesh}"/>
    <transform name="to_world">{PLACEMENT[object]}</transform>
    <bsdf type="principled"><rgb name="base_color" value="0.5 0.5 0.5"/><float name="roughness" value="0.5"/></bsdf>
  </shape>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><scale value="6"/><rotate x="1" angle="-90"/><translate y="-0.56"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.45 0.43 0.4"/></bsdf>
  </shape>
</scene>
"""
    with open(path, "w", encoding="utf-8") as file:
        file.write(text)
    return path
