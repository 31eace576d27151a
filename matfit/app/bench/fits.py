"""`matfit bench-fit`: the fitting methods compared on reachable targets.

Each configuration fits every target; the table reports the neural RMSE (phi(x) against the
target) and, for chosen configurations, the RMSE of a fresh Mitsuba render of the result against
the target: the honest figure.
"""

from __future__ import annotations

import time

import numpy as np

from matfit import images
from matfit.app.bench.reachable import JUDGE_SEED, JUDGE_SPP, Targets, no_worse, reachable_targets, rendered_rmse
from matfit.fitting import search, verify
from matfit.fitting.methods import CORRECTIONS
from matfit.model import models

_DEFAULT = search.Settings()
DEFAULT_LABEL = (
    f"lbfgsb, {_DEFAULT.starts} starts x {_DEFAULT.narrow_after}, the best to {_DEFAULT.iterations} (default)"
)


def default_configurations(evaluations: int) -> dict[str, search.Settings]:
    """Returns the compared configurations: the paper's three methods and our variations."""
    return {
        "nn (best-of-n)": search.Settings(method=search.Method.nn),
        f"optimize {evaluations} (random start)": search.Settings(
            method=search.Method.optimize, evaluations=evaluations
        ),
        "hybrid 50": search.Settings(method=search.Method.hybrid, evaluations=50),
        "hybrid 300": search.Settings(method=search.Method.hybrid, evaluations=300),
        f"hybrid {evaluations}": search.Settings(method=search.Method.hybrid, evaluations=evaluations),
        f"hybrid {evaluations}, paper's barrier": search.Settings(
            method=search.Method.hybrid, evaluations=evaluations, box=search.Box.barrier
        ),
        f"hybrid {evaluations}, fixed coefficients": search.Settings(
            method=search.Method.hybrid, evaluations=evaluations, adaptive=False
        ),
        f"hybrid {evaluations} + polish 200": search.Settings(
            method=search.Method.hybrid, evaluations=evaluations, polish_steps=200
        ),
        "lbfgsb, 1 start": search.Settings(method=search.Method.lbfgsb, starts=1),
        "lbfgsb, 4 starts x 50": search.Settings(iterations=50, narrow_after=50),
        DEFAULT_LABEL: search.Settings(),
        "hybrid-lbfgsb 300, 4 starts": search.Settings(method=search.Method.hybrid_lbfgsb, evaluations=300, starts=4),
    }


def compare(
    model: models.Model, targets: Targets, configurations: dict[str, search.Settings], progress=None
) -> dict[str, dict]:
    """Fits every target with every configuration; returns per configuration the results' figures."""
    table = {}
    for label, settings in configurations.items():
        search.neural_search(model, targets.images[0], settings=settings)  # compile outside the timing
        errors, seconds, results = [], [], []
        for k, target in enumerate(targets.images):
            started = time.perf_counter()
            result = search.neural_search(model, target, settings=settings)
            seconds.append(time.perf_counter() - started)
            errors.append(result.rmse)
            results.append(result)
            if progress is not None:
                progress(label, k + 1, len(targets.images))
        table[label] = {"rmse": np.array(errors), "seconds": np.array(seconds), "results": results}
    return table


def mitsuba_rmse(renderer, results: list[search.Result], targets: Targets, spp: int = 256) -> np.ndarray:
    """Returns the RMSE of a fresh Mitsuba render of each result against its target."""
    errors = []
    for k, (result, target) in enumerate(zip(results, targets.images, strict=True)):
        rendered = images.srgb_encode(renderer.render(result.values, seed=7 + k, spp=spp))
        errors.append(float(images.rmse(rendered, target)))
    return np.array(errors)


VERIFICATION_SPP = (16, 32, 64, 128)  # verification's spp compared by `verification_table` (verify.SPP among them)


def verification_table(renderer, results: list[search.Result], targets: Targets, spps=VERIFICATION_SPP) -> str:
    """Returns how verification's spp decides (Markdown): per spp, its renders' seconds, the Mitsuba RMSE of the
    candidate it keeps as an independent JUDGE_SPP render sees it, and how often it keeps what the highest spp keeps.
    """
    kept: dict[int, list[str]] = {spp: [] for spp in spps}
    seconds: dict[int, list[float]] = {spp: [] for spp in spps}
    judged = []
    for k, (result, target) in enumerate(zip(results, targets.images, strict=True)):
        judge = {
            name: rendered_rmse(renderer, unit, target, JUDGE_SEED + k, JUDGE_SPP)
            for name, unit in verify.candidates(result).items()
        }
        judged.append(judge)
        for spp in spps:
            checked = verify.verify_candidates(renderer, result, target, spp=spp)
            kept[spp].append(checked.chosen)
            seconds[spp].append(checked.seconds)
    lines = [
        f"| verification spp | seconds (median) | kept candidate: mean Mitsuba RMSE at {JUDGE_SPP} spp "
        f"| same choice as {spps[-1]} spp |",
        "|---|---|---|---|",
    ]
    for spp in spps:
        mean = np.mean([judge[name] for judge, name in zip(judged, kept[spp], strict=True)])
        same = sum(a == b for a, b in zip(kept[spp], kept[spps[-1]], strict=True))
        lines.append(f"| {spp} | {np.median(seconds[spp]):.2f} | {mean:.3f} | {same}/{len(judged)} |")
    oracle, start = np.mean([min(judge.values()) for judge in judged]), np.mean([judge["start"] for judge in judged])
    lines += [f"| the best candidate (oracle) | | {oracle:.3f} | |", f"| the best-of-n start | | {start:.3f} | |"]
    return "\n".join(lines)


def judged_table(renderer, answers: dict[str, list[np.ndarray]], targets: Targets, start: str) -> str:
    """Returns the answers' physical quality (Markdown): per label, the mean Mitsuba RMSE of its unit-cube answers
    as independent JUDGE_SPP renders see them (one seed per target for every answer), the share of that above the
    judge's noise floor (the target's true parameters so rendered), and on how many targets it is no worse than the
    answers labelled `start`.
    """
    floor_label = "the true parameters (the judge's noise floor)"
    judged = {
        label: np.array(
            [
                rendered_rmse(renderer, unit, target, JUDGE_SEED + k, JUDGE_SPP)
                for k, (unit, target) in enumerate(zip(units, targets.images, strict=True))
            ]
        )
        for label, units in {floor_label: list(targets.unit), **answers}.items()
    }
    floor = judged.pop(floor_label)
    lines = [
        f"| answer | mean Mitsuba RMSE ({JUDGE_SPP} spp judge) | above the noise floor | no worse than the {start} |",
        "|---|---|---|---|",
        f"| {floor_label} | {np.mean(floor):.3f} | | |",
    ]
    for label, errors in judged.items():
        held = int(np.sum(no_worse(errors, judged[start])))
        lines.append(f"| {label} | {errors.mean():.3f} | {errors.mean() - np.mean(floor):.3f} | {held}/{len(errors)} |")
    return "\n".join(lines)


def markdown(table: dict[str, dict], reference: str, mitsuba: dict[str, np.ndarray]) -> str:
    """Returns the comparison as a Markdown table; `reference` is the configuration others are compared to."""
    lines = [
        f"| configuration | neural RMSE mean | median | targets where {reference} is lower or equal | Mitsuba RMSE "
        "mean | fit time, warm (s) |",
        "|---|---|---|---|---|---|",
    ]
    base = table[reference]["rmse"]
    for label, row in table.items():
        wins = "" if label == reference else f"{int(np.sum(base <= row['rmse'] + 1e-9))}/{len(base)}"
        render = f"{mitsuba[label].mean():.2f}" if label in mitsuba else ""
        lines.append(
            f"| {label} | {row['rmse'].mean():.2f} | {np.median(row['rmse']):.2f} | {wins} | {render} | "
            f"{np.median(row['seconds']):.3f} |"
        )
    return "\n".join(lines)


def fit_comparison(model: models.Model, count: int, evaluations: int, log=print) -> str:
    """Returns the methods compared on `count` reachable targets: neural and Mitsuba RMSE, warm fit time (Markdown)."""
    from matfit.rendering.engine import Renderer

    renderer = Renderer(model.resolution, 256)
    log(f"rendering {count} reachable targets at {model.resolution} px, 256 spp")
    targets = reachable_targets(renderer, count)
    table = compare(model, targets, default_configurations(evaluations))
    reference = f"hybrid {evaluations}"
    shown = ("nn (best-of-n)", reference, "lbfgsb, 4 starts x 50", DEFAULT_LABEL, "hybrid-lbfgsb 300, 4 starts")
    mitsuba = {label: mitsuba_rmse(renderer, table[label]["results"], targets) for label in shown}
    default = table[DEFAULT_LABEL]["results"]
    log("verification at each spp, judged by independent renders")
    verification = verification_table(renderer, default, targets)
    log(f"every answer judged by an independent {JUDGE_SPP}-spp render")
    answers = {
        "best-of-n start": [result.start for result in default],
        reference: [result.unit for result in table[reference]["results"]],
        "default, not verified": [result.unit for result in default],
        "default, verified, not corrected": [
            verify.verify_candidates(renderer, result, target).unit
            for result, target in zip(default, targets.images, strict=True)
        ],
        f"default, verified, {CORRECTIONS} corrections (what `matfit fit` answers)": [
            verify.correct_then_verify(renderer, result, target, model=model, corrections=CORRECTIONS).unit
            for result, target in zip(default, targets.images, strict=True)
        ],
    }
    judged = judged_table(renderer, answers, targets, "best-of-n start")
    return (
        f"{markdown(table, reference, mitsuba)}\n\nVerification of the default's candidates:\n\n{verification}"
        f"\n\nThe answers as the user keeps them, in Mitsuba:\n\n{judged}"
    )
