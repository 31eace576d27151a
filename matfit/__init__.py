"""matfit: photorealistic principled-BSDF parameters from an edited picture of a material (README.md, docs/api.md)."""

from matfit.api import Fit, Fitter, Material, MatfitError, Settings, fit, fit_sequence, load_model, render

__all__ = ["Fit", "Fitter", "Material", "MatfitError", "Settings", "fit", "fit_sequence", "load_model", "render"]
