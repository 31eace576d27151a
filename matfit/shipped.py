"""Where the files that ship inside the package lie: the trained model, the example edits, the page's static files.

Located with `importlib.resources`, so they are found wherever matfit is installed (an editable clone, a wheel in any
virtual environment, pipx), never by a path built from a source file's location. Plain data: imports neither JAX nor
Mitsuba.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def _inside(*parts: str) -> Path:
    """Returns the path of a file or folder shipped in the package (installed packages are folders, never zips)."""
    return Path(str(resources.files("matfit").joinpath(*parts)))


PACKAGE = _inside()  # the matfit package's folder: in the clone, or in site-packages when installed
MODEL = _inside("data", "model")  # the networks `fit`, `serve` and `sequence` use unless given --model
EXAMPLES = _inside("data", "examples")  # edited pictures of presets (`make examples` makes them again)
STATIC = _inside("static")  # the page `matfit serve` serves
