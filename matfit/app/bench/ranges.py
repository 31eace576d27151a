"""What the picture decides, calibrated: ranges, verdicts and the clean answer on reachable targets.

Each reachable target (`reachable.reachable_targets`: the training distribution, a held-out seed,
256-spp Mitsuba renders) is fitted as `matfit fit` does by default (`search.Settings()`,
verification with `methods.CORRECTIONS` rounds of correction); the ranges of the kept answer
(`ranges.measure`, tau from the model's evaluation.json) are then compared with the true
parameters. Per parameter the table gives, by verdict, how often the true value lies inside the
reported range and the mean width in physical units, with tau each of the card's STATISTICS (the
ranges of the same answer measured again with the mean, the default `ranges.STATISTIC`, and with
the 95th percentile). Mitsuba checks the ranges' ends on a
sample: CHECKED parameters per target (fixed seed), each end rendered in VERIFY batches with
verification's seeds beside the answer's, and the noise-free RMSE between the two estimated
without bias (`verify.squared_error` of the paired differences); for a "free" parameter that
distance must stay below tau. The first `judged` targets also judge the clean answer against
the fit's (`clean.clean`) by an independent `reachable.JUDGE_SPP`-spp render each
(docs/fitting.md#what-the-picture-decides). Each case is written to the results file as it ends
and a run given the same file goes on from the cases it holds (measuring their stored answers again
when the ranges' settings changed since).
"""

from __future__ import annotations

import json
import os
import time

import numpy as np

from matfit import files, images, params
from matfit.app.bench import reachable
from matfit.fitting import clean, ranges, search, verify
from matfit.fitting.methods import CORRECTIONS
from matfit.model import models

CHECKED = 3  # parameters per target whose range ends Mitsuba renders
CHECK_SEED = 4242
VERIFY = verify.BATCHES  # batches of each end and of the answer
STATISTICS = ("mean", "p95")  # the card's figures the ranges are calibrated with as tau, `ranges.STATISTIC` among them


def mitsuba_distance(renderer, a: np.ndarray, b: np.ndarray) -> float:
    """Returns the estimated noise-free RMSE (0-255) between the Mitsuba renders of unit-cube materials a and b:
    VERIFY batches of each with verification's seeds, the unbiased estimate of their paired differences."""
    differences = []
    for j in range(VERIFY):
        seed = verify.BATCH_SEED + j
        first = images.srgb_encode(renderer.render(params.from_unit(a), seed=seed, spp=verify.SPP))
        second = images.srgb_encode(renderer.render(params.from_unit(b), seed=seed, spp=verify.SPP))
        differences.append(first - second)
    zero = np.zeros_like(differences[0])
    estimate, _ = verify.squared_error(differences, zero, np.ones(zero.shape[:2], np.float32))
    return 255.0 * float(np.sqrt(max(estimate, 0.0)))


def fit_case(model: models.Model, renderer, target: np.ndarray) -> tuple[verify.Verified, float]:
    """Returns (the default fit's verification, its seconds: the fit and verification with correction)."""
    started = time.perf_counter()
    result = search.neural_search(model, target, settings=search.Settings())
    kept = verify.correct_then_verify(renderer, result, target, model=model, corrections=CORRECTIONS)
    return kept, time.perf_counter() - started


def settings() -> dict:
    """Returns what the ranges of a case depend on besides its answer: `ranges`' settings and the statistics."""
    return {
        "checks": ranges.CHECKS,
        "settled": ranges.SETTLED,
        "hold": ranges.HOLD,
        "start": ranges.START,
        "bisections": ranges.BISECTIONS,
        "sweeps": ranges.SWEEPS,
        "growth": ranges.GROWTH,
        "statistics": list(STATISTICS),
    }


def calibrate(
    model: models.Model, decoding, answer: np.ndarray, truth: np.ndarray | None
) -> tuple[dict, ranges.Ranges]:
    """Returns ({statistic: the ranges of `answer` with tau that statistic of the card, whether `truth` lies inside
    each}, the ranges with tau `ranges.STATISTIC`)."""
    calibration, measured_by = {}, {}
    for statistic in STATISTICS:
        tau, _ = ranges.threshold(model.path, answer, statistic=statistic)
        started = time.perf_counter()
        measured = ranges.measure(decoding, model.decoder.variables, answer, None, tau)
        calibration[statistic] = {
            "threshold": tau,
            "verdicts": list(measured.verdicts),
            "low": measured.low.tolist(),
            "high": measured.high.tolist(),
            "seconds": time.perf_counter() - started,
        }
        if truth is not None:
            inside = (truth >= measured.low - 1e-6) & (truth <= measured.high + 1e-6)
            calibration[statistic]["inside"] = inside.tolist()
        measured_by[statistic] = measured
    if truth is not None:  # whether the truth is one of the materials the ranges describe (within tau of the answer)
        pictures = ranges.decoded(decoding, np.stack([answer, truth]).astype(np.float32), model.decoder.variables)
        distance = float(images.rmse(np.asarray(pictures[1]), np.asarray(pictures[0])))
        for figures in calibration.values():
            figures["truth_rmse"] = distance
    return calibration, measured_by[ranges.STATISTIC]


def mitsuba_checks(renderer, found: ranges.Ranges, answer: np.ndarray, index: int) -> list[dict]:
    """Returns the Mitsuba checks of the range ends of CHECKED parameters (drawn with seed [CHECK_SEED, index]): per
    end that moved, its verdict, its decoded and its Mitsuba distance to the answer (`mitsuba_distance`)."""
    checks = []
    chosen = np.random.default_rng([CHECK_SEED, index]).choice(params.COUNT, CHECKED, replace=False)
    for i in chosen:
        for side in (0, 1):
            end = found.ends[i, side]
            if np.max(np.abs(end - answer)) <= ranges.FACE:
                continue
            checks.append(
                {
                    "parameter": params.NAMES[i],
                    "verdict": found.verdicts[i],
                    "neural": float(found.end_rmse[i, side]),
                    "mitsuba": mitsuba_distance(renderer, end, answer),
                }
            )
    return checks


def case(
    model: models.Model,
    renderer,
    target: np.ndarray,
    truth: np.ndarray | None,
    index: int,
    judge: bool,
    fitted: tuple[np.ndarray, float] | None = None,
) -> dict:
    """Returns one target's figures (see the module docstring); `truth`: its unit-cube parameters, or None;
    `fitted`: (the answer, the fit's seconds) of an earlier run of this case, or None to fit it (then the clean
    answer's judgement reuses verification's batches of the answer, as `matfit fit` does). The top-level range
    figures are those of `ranges.STATISTIC`; `calibration` has them for each of STATISTICS."""
    truth = None if truth is None else np.asarray(truth, np.float64)
    rendered: list[np.ndarray] = []
    if fitted is None:
        kept, fit_seconds = fit_case(model, renderer, target)
        answer, rendered = np.asarray(kept.unit, np.float64), kept.renders
    else:
        answer, fit_seconds = fitted
    decoding = ranges.Decoding(model.decoder.module)
    calibration, found = calibrate(model, decoding, answer, truth)
    started = time.perf_counter()
    tried = clean.candidates(decoding, model.decoder.variables, answer, None, found)
    simplest_seconds = time.perf_counter() - started
    out = {
        "answer": answer.tolist(),
        "settings": settings(),
        "truth": None if truth is None else truth.tolist(),
        **calibration[ranges.STATISTIC],
        "calibration": calibration,
        "fit_seconds": fit_seconds,
        "range_seconds": calibration[ranges.STATISTIC]["seconds"],
        "simplest_seconds": simplest_seconds,
        "dropped": list(tried[-1][0]) if tried else [],
        "free_before": clean.free_away_from_neutral(answer, found.verdicts),
    }
    out["checks"] = mitsuba_checks(renderer, found, answer, index)
    if judge:
        cleaned = clean.clean(
            decoding, model.decoder.variables, answer, target, None, found, renderer, rendered=rendered
        )
        seed = reachable.JUDGE_SEED + index
        out["judged"] = {
            "best": reachable.rendered_rmse(renderer, answer, target, seed, reachable.JUDGE_SPP),
            "clean": reachable.rendered_rmse(renderer, cleaned.unit, target, seed, reachable.JUDGE_SPP),
            "kept": cleaned.chosen,
            "free_before": cleaned.free_before,
            "free_after": cleaned.free_after,
            "clean_seconds": cleaned.seconds,
            "features_off": list(cleaned.dropped) if cleaned.chosen == "clean" else [],
            "renders": sum(cleaned.batches.values()),
            "candidates": cleaned.candidates,
        }
    return out


def warm_up(model: models.Model, renderer, target: np.ndarray) -> None:
    """Compiles every stage once (fit, verification, ranges, the clean answer), so that the timings are warm."""
    kept, _ = fit_case(model, renderer, target)
    answer = np.asarray(kept.unit, np.float64)
    decoding = ranges.Decoding(model.decoder.module)
    found = ranges.measure(decoding, model.decoder.variables, answer, None, 2.0)
    clean.candidates(decoding, model.decoder.variables, answer, None, found)


def finished(results: str | None) -> dict[str, dict]:
    """Returns {case name: its figures} of the cases of a results file written by `run` that hold their answer; {}
    when there is none."""
    if results is None or not os.path.isfile(results):
        return {}
    with open(results, encoding="utf-8") as file:
        cases = json.load(file).get("cases", [])
    return {c["name"]: c for c in cases if "answer" in c}


def run(
    model: models.Model,
    count: int,
    judged: int,
    examples: list[tuple[str, np.ndarray]],
    log=print,
    results: str | None = None,
) -> dict:
    """Returns every case's figures: `count` reachable targets (the first `judged` also judged clean against best),
    then the named sRGB `examples` (judged, no truth); each finished case is written to `results` (JSON) at once.
    A case `results` already holds is taken from it when it was measured with today's `settings` (and judged if
    it must be), else measured again from its stored answer without fitting again."""
    from matfit.rendering.engine import Renderer

    renderer = Renderer(model.resolution, verify.SPP)
    targets = reachable.reachable_targets(renderer, count)
    done = finished(results)
    cases: list[dict] = []
    warm = False

    def save() -> None:  # the cases of this run so far, then the file's others: none is lost to an interruption
        if results is not None:
            ours = {c["name"] for c in cases}
            files.write_text(results, json.dumps({"cases": cases + [c for n, c in done.items() if n not in ours]}))

    work = [
        (f"reachable-{k}", target, truth, k < judged)
        for k, (truth, target) in enumerate(zip(targets.unit, targets.images, strict=True))
    ]
    work += [(name, target, None, True) for name, target in examples]
    for k, (name, target, truth, judge) in enumerate(work):
        earlier = done.get(name)
        if earlier is not None and earlier.get("settings") == settings() and (not judge or "judged" in earlier):
            cases.append(earlier)
        else:
            if not warm:
                warm_up(model, renderer, target)
                warm = True
            # a case fitted before keeps its answer: only what follows the fit is measured again
            fitted = None if earlier is None else (np.asarray(earlier["answer"]), earlier["fit_seconds"])
            cases.append({"name": name, **case(model, renderer, target, truth, k, judge, fitted)})
            save()
        log(f"{name} ({k + 1}/{len(work)})")
    return {"cases": cases}


def calibration_table(cases: list[dict], statistic: str) -> list[str]:
    """Returns the markdown lines of the calibration with tau the card's `statistic`: per parameter, by verdict,
    the share of true values inside the range (count) and the mean width in physical units."""
    calibrated = [c["calibration"][statistic] for c in cases if c.get("truth") is not None]
    taus = sorted({round(c["threshold"], 2) for c in calibrated})
    lines = [
        f"Calibration on {len(calibrated)} reachable targets (default fit, tau = the decoder's "
        f"{ranges.STATISTICS[statistic]} error on the answer's kind of material: {', '.join(map(str, taus))}): share "
        "of true values inside the range, by verdict (count), and mean width.",
        "",
        "| parameter | decided: inside | partly: inside | free: inside | mean width decided | mean width partly |",
        "|---|---|---|---|---|---|",
    ]
    totals = {verdict: [0, 0] for verdict in ranges.VERDICTS}
    for i, p in enumerate(params.PARAMETERS):
        cells, widths = [], []
        for verdict in ranges.VERDICTS:
            hits = [c["inside"][i] for c in calibrated if c["verdicts"][i] == verdict]
            totals[verdict][0] += sum(hits)
            totals[verdict][1] += len(hits)
            cells.append(f"{np.mean(hits):.0%} ({len(hits)})" if hits else "- (0)")
        for verdict in ("decided", "partly"):
            width = [(c["high"][i] - c["low"][i]) * (p.high - p.low) for c in calibrated if c["verdicts"][i] == verdict]
            widths.append(f"{np.mean(width):.3g} {p.unit}" if width else "-")
        lines.append(f"| {p.name} | {' | '.join(cells)} | {' | '.join(widths)} |")
    overall = [f"{hit / total:.0%} ({total})" if total else "- (0)" for hit, total in totals.values()]
    lines.append(f"| all | {' | '.join(overall)} | | |")
    misses = [
        c["truth_rmse"] <= c["threshold"]
        for c in calibrated
        if "truth_rmse" in c
        for i, verdict in enumerate(c["verdicts"])
        if verdict == "decided" and not c["inside"][i]
    ]
    if misses:
        lines += [
            "",
            f"Of the {len(misses)} decided ranges that miss the true value, {sum(misses)} belong to a target whose "
            "truth decodes within tau of the answer: a material the range should have reached.",
        ]
    return lines


def table(figures: dict) -> str:
    """Returns the markdown tables of a run: the calibration (the default tau first, then the other STATISTICS),
    the Mitsuba checks, the clean answer, the cost."""
    cases = figures["cases"]
    lines = []
    for statistic in sorted(STATISTICS, key=lambda s: s != ranges.STATISTIC):
        lines += [*calibration_table(cases, statistic), ""]
    checks = [check for c in cases for check in c["checks"]]
    lines += [
        f"Mitsuba at the ranges' ends ({len(checks)} ends of {CHECKED} parameters per target): the estimated "
        "noise-free RMSE between the end's render and the answer's, against tau.",
        "",
        "| verdict | ends | neural RMSE (mean) | Mitsuba RMSE (mean) | Mitsuba within tau |",
        "|---|---|---|---|---|",
    ]
    taus = {c["name"]: c["threshold"] for c in cases}
    for verdict in ranges.VERDICTS:
        chosen = [(check, taus[c["name"]]) for c in cases for check in c["checks"] if check["verdict"] == verdict]
        if chosen:
            within = np.mean([check["mitsuba"] <= tau for check, tau in chosen])
            lines.append(
                f"| {verdict} | {len(chosen)} | {np.mean([check['neural'] for check, _ in chosen]):.2f} | "
                f"{np.mean([check['mitsuba'] for check, _ in chosen]):.2f} | {within:.0%} |"
            )
    judged = [c for c in cases if "judged" in c]
    if judged:
        best = np.array([c["judged"]["best"] for c in judged])
        answer = np.array([c["judged"]["clean"] for c in judged])
        lines += [
            "",
            f"The clean answer (the default) against the fit's own on {len(judged)} targets, each judged by an "
            f"independent {reachable.JUDGE_SPP}-spp render (seed {reachable.JUDGE_SEED} + case):",
            "",
            "| answer | mean Mitsuba RMSE | worst difference to best | clean kept | free parameters not neutral |",
            "|---|---|---|---|---|",
            f"| best (--answer best) | {best.mean():.3f} | | | "
            f"{np.mean([c['judged']['free_before'] for c in judged]):.2f} per answer |",
            f"| clean (default) | {answer.mean():.3f} | {np.max(answer - best):+.3f} | "
            f"{sum(c['judged']['kept'] == 'clean' for c in judged)}/{len(judged)} | "
            f"{np.mean([c['judged']['free_after'] for c in judged]):.2f} per answer |",
            "",
            "| case | best | clean | kept | features off (answer returned) | simplest candidate's | renders |",
            "|---|---|---|---|---|---|---|",
            *(
                f"| {c['name']} | {c['judged']['best']:.3f} | {c['judged']['clean']:.3f} | {c['judged']['kept']} | "
                f"{', '.join(c['judged']['features_off']) or '-'} | {', '.join(c['dropped']) or '-'} | "
                f"{c['judged']['renders']} |"
                for c in judged
            ),
        ]
    fit = np.mean([c["fit_seconds"] for c in cases])
    extra = np.mean([c["range_seconds"] for c in cases])
    simplest = np.mean([c["simplest_seconds"] for c in cases])
    lines += [
        "",
        f"Cost (warm, mean per target): default fit with verification {fit:.2f} s; ranges {extra:.3f} s "
        f"({extra / fit:.1%}); the clean answer's candidates {simplest:.3f} s ({simplest / fit:.1%}), plus its "
        "Mitsuba judgement where a feature was turned off.",
    ]
    return "\n".join(lines)
