"""What `matfit fit` prints as each fit, or each stage's answer, ends (`report_answer`, `report_fit`), and several
pictures fitted into a folder as the command does it (`fit_several`)."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import typer

import matfit
from matfit import interrupt
from matfit.app import console

echo_lines = console.echo_lines
log = functools.partial(typer.echo, err=True)  # what was written, and notices, go to standard error


def fit_several(fitter: matfit.Fitter, targets: list[Path], folder: str, **chosen: Any) -> None:
    """Fits several pictures into `folder` (`matfit.Fitter.fit_all` with `chosen` options), each reported as it ends;
    exit 2 where one failed."""
    interrupt.set_message(
        "each picture fitted so far is written, the one in hand is not: run the same command to go on"
    )
    failed = fitter.fit_all([str(target) for target in targets], folder, **chosen, done=report_fit)
    log(f"fitted {len(targets) - failed} of {len(targets)} pictures into {folder}")
    if failed:
        log("run the same command again to fit the pictures that failed; those fitted are kept")
        raise typer.Exit(2)


def report_answer(fitted: matfit.Fit) -> None:
    """Prints one stage's answer as it lands (`matfit fit` of one picture): the stage, its figure (Mitsuba's, where
    the stage rendered it, else the neural one) and the seconds since the fit began."""
    if fitted.mitsuba_rmse is not None:
        figure = f"Mitsuba RMSE {fitted.mitsuba_rmse:.2f}"
    else:
        figure = f"neural RMSE {fitted.neural_rmse:.2f}"
    log(f"{fitted.stage} answer: {figure} ({fitted.document['wall_time_s']:.1f} s)")


def report_fit(picture: str, params: str, fitted: matfit.Fit | matfit.MatfitError | None) -> None:
    """Prints what one picture of several came to: its notices and summary line, its error, or (None) that an earlier
    run of the same command fitted it."""
    if fitted is None:
        log(f"{params}: kept, fitted by an earlier run of this command (same picture and settings)")
        return
    if isinstance(fitted, matfit.MatfitError):
        log(f"error: {picture}: {fitted}")
        return
    echo_lines(fitted.notices)
    log(fitted.summary)
