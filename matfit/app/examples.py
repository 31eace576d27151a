"""The example edits shipped in matfit/data/examples: a preset rendered, then changed as in a 2D editor.

- recoloured.png: red plastic with its hue turned by 120 degrees (green plastic);
- desaturated.png: copper with 85% of its saturation taken out (a grey metal);
- painted-highlight.png: red plastic with a sharp white highlight painted on (a local edit that
  asks for a glossier coat).

Run `make examples` (python -m matfit.app.examples matfit/data/examples) to make them again.
"""

from __future__ import annotations

import os
import sys

from matfit import images
from matfit.edits import hue_rotate, paint_highlight, saturate
from matfit.rendering import presets

SIZE = 256
SPP = 256


EXAMPLES = {
    "recoloured.png": ("red-plastic", lambda image: hue_rotate(image, 120.0)),
    "desaturated.png": ("copper", lambda image: saturate(image, 0.85)),
    "painted-highlight.png": ("red-plastic", lambda image: paint_highlight(image, (0.38, 0.38), 0.035, 0.95)),
}


def make(directory: str, size: int = SIZE, spp: int = SPP) -> list[str]:
    """Renders the presets and writes the edited examples into `directory`; returns their paths."""
    from matfit.rendering.engine import Renderer

    renderer = Renderer(size, spp)
    written = []
    for name, (preset, edit) in EXAMPLES.items():
        original = images.srgb_encode(renderer.render(presets.preset(preset)))
        path = os.path.join(directory, name)
        images.write(path, images.srgb_decode(edit(original)))
        written.append(path)
    return written


if __name__ == "__main__":
    for written_path in make(sys.argv[1] if len(sys.argv) > 1 else "matfit/data/examples"):
        print(f"wrote {written_path}")
