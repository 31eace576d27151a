"""The picture of docs/blender.md#the-extension: the extension's two operators on red plastic, as an artist runs them.

Builds the extension, installs it into a fresh bpy session and runs it there (tests/blender_extension_run.py,
the driver the tests use): "Picture of this material" on the red-plastic preset built in Blender by its
exported script, then "Fit edited picture" on matfit/data/examples/recoloured.png (that picture with its hue
turned, as a 2D editor would) with matfit fit's default settings. The fitted material, as the extension put
it on the selected objects (to_blender of the params.json it saved beside the picture, the exported script's
inputs), is rendered in Cycles in Blender's copy of the test scene (`blender.render_scripts`).
Writes OUT (default data/blender/extension.png): picture | edited picture | fitted material in Cycles.

Usage: python scripts/blender_extension_picture.py [OUT]  (needs `make blender`; minutes on a 2-core CPU)
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np

from matfit import images, params, shipped
from matfit.rendering import blender, export, presets

ROOT = shipped.PACKAGE.parent
SIZE, SPP = 256, 256  # the example edits' size


def main(out: str) -> None:
    python = blender.find_blender()
    with tempfile.TemporaryDirectory(prefix="matfit-extension-") as folder:
        built = subprocess.run(
            [sys.executable, str(ROOT / "blender" / "build.py"), folder], capture_output=True, text=True, check=True
        )
        command = os.path.join(folder, "matfit")
        with open(command, "w") as file:
            file.write(f'#!/bin/sh\nexec "{sys.executable}" -m matfit "$@"\n')
        os.chmod(command, 0o755)
        with open(os.path.join(folder, "source.py"), "w") as file:
            file.write(export.blender_script(presets.preset("red-plastic")))
        edited = os.path.join(folder, "edited.png")
        shutil.copy(shipped.EXAMPLES / "recoloured.png", edited)
        job = {
            "zip": built.stdout.strip(),
            "command": command,
            "size": SIZE,
            "spp": SPP,
            "fit_options": "",
            "picture": {"script": os.path.join(folder, "source.py"), "out": os.path.join(folder, "picture.png")},
            "fit": edited,
        }
        with open(os.path.join(folder, "job.json"), "w") as file:
            json.dump(job, file)
        environment = {**os.environ, "PYTHONNOUSERSITE": "1", "BLENDER_USER_RESOURCES": os.path.join(folder, "user")}
        run = subprocess.run(
            [python, str(ROOT / "tests" / "blender_extension_run.py"), os.path.join(folder, "job.json"),
             os.path.join(folder, "report.json")],
            capture_output=True, text=True, env=environment,
        )  # fmt: skip
        print(*(line for line in run.stdout.splitlines() if line.startswith(("Info", "Warning", "Error"))), sep="\n")
        if run.returncode != 0:
            sys.exit(run.stderr[-2000:])
        fitted = params.read_file(os.path.join(folder, "edited.params.json"))
        cycles = blender.render_scripts([export.blender_script(fitted)], SIZE, SPP, blender=python)[0]
        tiles = [
            (images.read(job["picture"]["out"]), "1. Picture of this material"),
            (images.read(edited), "2. edited in a 2D editor"),
            (cycles, "3. Fit edited picture (Cycles)"),
        ]
    row = [images.label(images.srgb_encode(tile), caption) for tile, caption in tiles]
    images.write(out, images.srgb_decode(np.concatenate(row, axis=1)))
    print(out)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else str(ROOT / "data" / "blender" / "extension.png"))
