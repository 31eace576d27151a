"""The command line's options: each option that several commands take, declared once for Typer, and the long list
of `matfit fit`'s own.

Plain data for `cli`: importing it loads neither JAX nor Mitsuba, so `matfit params` stays fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import typer

import matfit
from matfit import params, shipped
from matfit.api.arguments import MAX_SIZE
from matfit.errors import SceneError
from matfit.fitting.methods import (
    CORRECTIONS,
    MAX_CORRECTIONS,
    MAX_EVALUATIONS,
    MAX_ITERATIONS,
    MAX_POLISH,
    MAX_REFINE,
    MAX_STARTS,
    MIN_EVALUATIONS,
    Box,
    Method,
)
from matfit.model import dataset
from matfit.rendering.engine import VARIANTS

DEFAULT_MODEL = shipped.MODEL


def seed(help: str):
    """Returns the option of a seed: every seed of matfit is in [0, params.MAX_SEED]."""
    return typer.Option(min=0, max=params.MAX_SEED, help=help)


def output(help: str):
    """Returns the option of the file a command writes: --output, -o."""
    return typer.Option("--output", "-o", help=help)


def out(help: str):
    """Returns the option of the folder a command writes into: --out, -o."""
    return typer.Option("--out", "-o", help=help)


def scene(path: Path | None, object: str | None) -> matfit.Scene:
    """Returns the `matfit.Scene` of --scene and --object (the one-line error of one without the other)."""
    if path is None or object is None:
        given, missing = ("--scene", "--object") if path is not None else ("--object", "--scene")
        raise SceneError(f"{given} needs {missing}: give the scene file and the id of its shape", field="scene")
    return matfit.Scene(str(path), object)


def text(path: Path | None) -> str | None:
    """Returns an optional path as the library takes it: a string, or None."""
    return None if path is None else str(path)


Model = Annotated[
    Path, typer.Option("--model", help="Model directory (default: the shipped model).", show_default=False)
]
Variant = Annotated[
    Literal[VARIANTS] | None,  # type: ignore[valid-type]  # a Literal of a tuple's values: Typer reads them at run time
    typer.Option(
        help="Mitsuba variant (default: cuda_ad_rgb with an NVIDIA GPU, else llvm_ad_rgb with libLLVM >= 19, "
        "else scalar_rgb)."
    ),
]
SAMPLERS = tuple(params.SAMPLERS)  # named, as VARIANTS is: a type checker then reads Sampler as a type
Sampler = Annotated[
    Literal[SAMPLERS],  # type: ignore[valid-type]  # as Variant's
    typer.Option(
        help="How parameters are drawn: the training distribution, or one of its corners (a supplement): "
        "dense-media (milky, jade-like), glass (transmissive dielectrics with a white or grey base colour) or "
        "tinted-glass (those dielectrics with an absorbing, coloured medium: amber-like)."
    ),
]
Spp = Annotated[int, typer.Option(min=1, max=dataset.MAX_SPP, help="Samples per pixel (of the renders).")]
Size = Annotated[
    int, typer.Option(min=dataset.MIN_RESOLUTION, max=MAX_SIZE, help="Image side in pixels (of the renders).")
]
Evaluations = Annotated[
    int,
    typer.Option(
        "--evals", min=MIN_EVALUATIONS, max=MAX_EVALUATIONS, help="Nelder-Mead budget in objective evaluations."
    ),
]
Refine = Annotated[
    int,
    typer.Option(
        "--refine",
        min=0,
        max=MAX_REFINE,
        help="Steps through Mitsuba's differentiable renderer after the fit (~0.1-1 s each), kept only if better; "
        "with --scene, the fit's own steps (0: 48).",
    ),
]
Answer = Annotated[
    Literal["clean", "best"],
    typer.Option(help="clean: the simplest material within the threshold of the best fit; best: the fit's own."),
]
Corrections = Annotated[
    int | None,
    typer.Option(
        "--corrections",
        min=0,
        max=MAX_CORRECTIONS,
        help="Rounds of fitting again on the target less the decoder's error at the answer, as a Mitsuba render shows "
        f"it (one decoder fit and one render each; default {CORRECTIONS} with verification, 0: none). "
        "A round's answer is kept only if Mitsuba prefers it.",
    ),
]
Init = Annotated[Path | None, typer.Option(help="params.json of the source material: joins the candidates.")]
SceneFile = Annotated[
    Path | None,
    typer.Option(
        "--scene", help="A Mitsuba 3 XML scene of your own: the picture is its render (docs/scenes.md); needs --object."
    ),
]
SceneObject = Annotated[
    str | None, typer.Option("--object", help="With --scene: the id of the shape whose material is fitted/rendered.")
]
Fitting = Annotated[
    Method,
    typer.Option(
        "--method",
        help="lbfgsb (best-of-n, then L-BFGS-B from the best --starts candidates), hybrid (the paper's: best-of-n, "
        "then Nelder-Mead), nn (best-of-n), optimize (Nelder-Mead from a random start), hybrid-lbfgsb (Nelder-Mead "
        "with --evals between the two).",
    ),
]
Host = Annotated[str, typer.Option(help="Address to listen on: 127.0.0.1 is this machine only; 0.0.0.0 every network.")]
Port = Annotated[int, typer.Option(min=1, max=65535, help="Port to listen on.")]
Watch = Annotated[
    Path | None, typer.Option(help="A picture your editor saves (or a folder of them): refitted on every save.")
]
ParamsFiles = Annotated[list[Path] | None, typer.Option("--params", help="A params.json to compare too (repeat it).")]
BlenderPython = Annotated[
    str | None, typer.Option(help="Python with bpy 4.5, or Blender 4.5 (default: .venv-blender, `make blender`).")
]
TargetCount = Annotated[
    int, typer.Option("--count", min=1, max=10_000, help="Reachable targets (256-spp renders of held-out parameters).")
]
FramesOut = Annotated[
    Path | None, typer.Option("--write-frames", help="Also write the sequence's frames to this folder.")
]
Full = Annotated[bool, typer.Option("--full", help="10 seeds, 60 s basin-hopping, 120 frames (quick: 5, 5 s, 40).")]
Mask = Annotated[
    Path | None, typer.Option(help="Per-pixel weights, the target's size: white = match here, black = ignore.")
]
BoxOption = Annotated[
    Box, typer.Option("--box", help="Keeping inside the parameter box: clip (clip + penalty) or barrier (the paper's).")
]
Fits = Annotated[int, typer.Option(min=10, max=100_000, help="Fits through the page before memory is read again.")]

# The options of `matfit fit` alone, declared here so that the command reads as what it does.
Polish = Annotated[int, typer.Option("--polish", min=0, max=MAX_POLISH, help="Projected-Adam steps after Nelder-Mead.")]
Report = Annotated[
    Path | None, typer.Option(help="Comparison picture: target | guess | fit | Mitsuba render | difference.")
]
RenderOutput = Annotated[Path | None, typer.Option(help="Render the fitted material with Mitsuba to this image.")]
MitsubaXml = Annotated[Path | None, typer.Option(help="Write the BSDF and medium as Mitsuba 3 XML.")]
BlenderScript = Annotated[Path | None, typer.Option(help="Write a Blender 4.x script that builds the material.")]
Starts = Annotated[int, typer.Option(min=1, max=MAX_STARTS, help="L-BFGS-B starts (the best best-of-n candidates).")]
Iterations = Annotated[
    int,
    typer.Option(min=1, max=MAX_ITERATIONS, help="L-BFGS-B steps of the best start (a value and gradient each)."),
]
NarrowAfter = Annotated[
    int,
    typer.Option(min=1, max=MAX_ITERATIONS, help="L-BFGS-B steps of every start; then the best goes on alone."),
]
Verify = Annotated[bool, typer.Option(help="Let Mitsuba choose among the final candidates.")]
