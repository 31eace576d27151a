"""matfit: photorealistic principled-BSDF parameters from an edited picture of a material (README.md, docs/api.md)."""

from typing import TYPE_CHECKING, Any

__all__ = [
    "Fit",
    "Fitter",
    "Material",
    "MatfitError",
    "Outputs",
    "Scene",
    "Settings",
    "fit",
    "fit_sequence",
    "load_model",
    "render",
]

# Where each public name lives (matfit/api/): imported at first use, so that `import matfit` (and so `python -m
# matfit`, whose Ctrl-C handling must come first) loads nothing else.
_HOMES = {
    "Fit": "matfit.api.results",
    "Fitter": "matfit.api.fitter",
    "Material": "matfit.api.material",
    "MatfitError": "matfit.errors",
    "Outputs": "matfit.api.results",
    "Scene": "matfit.api.scenes",
    "Settings": "matfit.fitting.methods",
    "fit": "matfit.api.fitter",
    "fit_sequence": "matfit.api.sequences",
    "load_model": "matfit.api.fitter",
    "render": "matfit.api.material",
}

if TYPE_CHECKING:
    from matfit.api.fitter import Fitter, fit, load_model
    from matfit.api.material import Material, render
    from matfit.api.results import Fit, Outputs
    from matfit.api.scenes import Scene
    from matfit.api.sequences import fit_sequence
    from matfit.errors import MatfitError
    from matfit.fitting.methods import Settings
else:

    def __getattr__(name: str) -> Any:
        """Returns a public name, imported from its module at first use."""
        if name in _HOMES:
            import importlib

            return getattr(importlib.import_module(_HOMES[name]), name)
        raise AttributeError(f"module 'matfit' has no attribute {name!r}")
