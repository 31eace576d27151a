"""Writes the matfit Blender extension's zip: blender/extension/, the mapping table and the parameter bounds.

Usage: python blender/build.py OUT_FOLDER (`make blender-extension` writes dist/matfit-blender-VERSION.zip).
The zip carries matfit/rendering/blender_mapping.py itself, the one table the export writes with,
params.PARAMETERS' bounds as parameters.json and params.MINIMUM_EXTINCTION as medium.json, so that
Blender's Python needs neither numpy nor matfit to build a fitted material.
Prints the zip's path.
"""

import json
import sys
import tomllib
import zipfile
from pathlib import Path

from matfit import params
from matfit.rendering import blender_mapping

SOURCE = Path(__file__).resolve().parent / "extension"


def build(out: str) -> Path:
    """Returns the path of the extension zip written into the folder `out`."""
    manifest = tomllib.loads((SOURCE / "blender_manifest.toml").read_text())
    path = Path(out) / f"matfit-blender-{manifest['version']}.zip"
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for file in sorted(SOURCE.iterdir()):
            if file.is_file() and file.suffix in (".py", ".toml"):
                archive.write(file, file.name)
        archive.write(blender_mapping.__file__, "blender_mapping.py")
        archive.writestr("parameters.json", json.dumps(params.table(), indent=1))
        archive.writestr("medium.json", json.dumps({"minimum_extinction": params.MINIMUM_EXTINCTION}))
    return path


if __name__ == "__main__":
    print(build(sys.argv[1] if len(sys.argv) > 1 else "dist"))
