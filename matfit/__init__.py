"""matfit: photorealistic principled-BSDF parameters from an edited picture of a material (README.md, docs/api.md)."""

import importlib
import inspect
import types
from typing import TYPE_CHECKING, Any

__all__ = [
    "Fit",
    "Fitter",
    "Material",
    "MatfitError",
    "Outputs",
    "Settings",
    "fit",
    "fit_sequence",
    "load_model",
    "render",
]


class _Callable(types.ModuleType):
    """The subpackages `matfit.fit` and `matfit.render`, callable as the public API's `fit` and `render`
    (`matfit.api`, imported at the first call): the import system sets `matfit.fit` to the subpackage whenever it
    is imported, so the function and the package are one object, whichever was imported first."""

    def _function(self) -> Any:
        api = importlib.import_module("matfit.api")  # makes this package api's callable one (`api._callable`)
        return getattr(api, self.__name__.rpartition(".")[2]).__wrapped__

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._function()(*args, **kwargs)

    @property
    def __signature__(self) -> inspect.Signature:
        return inspect.signature(self._function())


for _name in ("fit", "render"):  # their __init__ is a docstring alone: nothing heavy is imported
    importlib.import_module(f"matfit.{_name}").__class__ = _Callable

if TYPE_CHECKING:
    from matfit.api import (
        Fit,
        Fitter,
        Material,
        MatfitError,
        Outputs,
        Settings,
        fit,
        fit_sequence,
        load_model,
        render,
    )
else:

    def __getattr__(name: str) -> Any:
        """Returns a public name of `matfit.api`, imported at first use: `import matfit` (and so `python -m matfit`,
        whose Ctrl-C handling must come first) loads nothing else."""
        if name in __all__:
            from matfit import api

            return getattr(api, name)
        raise AttributeError(f"module 'matfit' has no attribute {name!r}")
