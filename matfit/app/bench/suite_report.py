"""`matfit bench`: runs the edit suite's tables and writes its report (Markdown, JSON, the plot, a picture per
case)."""

from __future__ import annotations

import io
import os
import time

import numpy as np

from matfit import documents, files, images, params
from matfit.app.bench.optimisers import optimiser_table
from matfit.app.bench.reachable import no_worse
from matfit.app.bench.sequence import black_level_sequence, sequence_table
from matfit.app.bench.suite import BUDGETS, main_table, suite_targets
from matfit.fitting import search
from matfit.fitting.methods import CORRECTIONS
from matfit.model import models


def case_picture(
    model: models.Model, renderer, target: np.ndarray, row: dict, budget: int, spp: int = 256
) -> np.ndarray:
    """Returns target | best-of-9 | optimiser | hybrid | Mitsuba render of hybrid (| of the default, if `row` has it),
    and stores in `row` the RMSE of Mitsuba renders of the best-of-9, optimiser (seed 0), hybrid and default results."""
    from matfit.fitting import report

    best = search.neural_search(model, target, settings=search.Settings(method=search.Method.nn))

    def decode(values):
        return model.decode(params.to_unit(np.asarray(values)))[0]

    hybrid_values = np.asarray(row[f"hybrid_{budget}_values"])
    rendered = images.srgb_encode(renderer.render(hybrid_values, seed=11, spp=spp))
    rendered_best = images.srgb_encode(renderer.render(best.values, seed=11, spp=spp))
    rendered_optimiser = images.srgb_encode(
        renderer.render(np.asarray(row[f"optimize_{budget}_values"]), seed=11, spp=spp)
    )
    hybrid_render_rmse = float(images.rmse(rendered, target))
    row[f"mitsuba_hybrid_{budget}"] = hybrid_render_rmse
    row["mitsuba_best_of_n"] = float(images.rmse(rendered_best, target))
    row[f"mitsuba_optimize_{budget}"] = float(images.rmse(rendered_optimiser, target))
    extra_panels = []
    renders = {}  # by point: a default that kept its start is the start's very render (two renders of one
    # material differ in the last bits, the threads' order of summation, which must not read as worse)
    for key in ("start", "default"):  # independent of verification's seed: the honest comparison
        if f"{key}_values" in row:
            values = np.asarray(row[f"{key}_values"], np.float64)
            if values.tobytes() not in renders:
                renders[values.tobytes()] = images.srgb_encode(renderer.render(values, seed=11, spp=spp))
            rendered_key = renders[values.tobytes()]
            row[f"mitsuba_{key}"] = float(images.rmse(rendered_key, target))
            if key == "default":
                extra_panels.append((rendered_key, f"default, Mitsuba {row['mitsuba_default']:.2f}"))
    panels = [
        (target, f"{row['case']}"),
        (best.image, f"best-of-9 {best.rmse:.2f}"),
        (decode(row[f"optimize_{budget}_values"]), f"optimiser {row[f'optimize_{budget}']:.2f}"),
        (decode(hybrid_values), f"hybrid {row[f'hybrid_{budget}']:.2f}"),
        (rendered, f"Mitsuba {hybrid_render_rmse:.2f}"),
        *extra_panels,
    ]
    return report.compose(panels, size=128, caption=14)


def suite_report(
    main: list[dict], optimisers: list[dict], sequence: str, budgets=BUDGETS, seeds: int = 5, settings: str = ""
) -> str:
    """Returns the Markdown report of the edit suite: main table with Mitsuba column, optimisers, sequence, timings."""
    lines = ["# matfit bench: the paper's tables on the built-in edit suite", "", settings, ""]
    lines += main_section(main, budgets, seeds)
    lines += default_section(main, budgets[-1])
    lines += optimiser_section(optimisers)
    lines += ["", "## 3. Sequence: rising black level, per-frame fitting against reinitialisation", "", sequence, ""]
    lines += timings_section(main, budgets)
    lines += pictures_section(main)
    return "\n".join(lines) + "\n"


def main_section(main: list[dict], budgets, seeds: int) -> list[str]:
    """Returns section 1 of the report: per case, random guess, best-of-9, optimiser and hybrid per budget, and the
    Mitsuba renders of the results at the largest budget."""
    lines = ["## 1. Main table (RMSE, 0-255 sRGB)", ""]
    header = (
        "| case | random guess | best-of-9 | "
        + " | ".join(f"optimiser {b} | hybrid {b}" for b in budgets)
        + " | Mitsuba: best-of-9 | Mitsuba: optimiser | Mitsuba: hybrid |"
    )
    lines += [header, "|---|" + "---|" * (5 + 2 * len(budgets))]
    for row in main:
        cells = [f"{row['random']:.2f}", f"{row['best_of_n']:.2f}"]
        for b in budgets:
            cells += [
                f"{row[f'optimize_{b}']:.2f}",
                f"**{row[f'hybrid_{b}']:.2f}**"
                if row[f"hybrid_{b}"] <= row[f"optimize_{b}"] + 1e-6
                else f"{row[f'hybrid_{b}']:.2f}",
            ]
        cells += [
            f"{row['mitsuba_best_of_n']:.2f}",
            f"{row[f'mitsuba_optimize_{budgets[-1]}']:.2f}",
            f"{row[f'mitsuba_hybrid_{budgets[-1]}']:.2f}",
        ]
        lines.append(f"| {row['case']} | " + " | ".join(cells) + " |")
    return [
        *lines,
        "",
        f"Optimiser = Nelder-Mead from a uniformly random start, mean over {seeds} seeds (the random-guess column is "
        "the mean RMSE of those starts).",
        "Hybrid = Nelder-Mead from the best-of-9 guess; bold where it is at least as good as the optimiser. The "
        "Mitsuba columns render the result",
        f"(best-of-9, optimiser seed 0 and hybrid at {budgets[-1]}) at 256 spp and compare it with the target: "
        "the neural renderer's own error shows there.",
        "",
    ]


def default_section(main: list[dict], budget: int) -> list[str]:
    """Returns section 1b of the report: matfit's default against its start and the paper's hybrid at `budget`."""
    return [
        f"## 1b. matfit's default ({search.Settings().method.value}, Mitsuba-verified, {CORRECTIONS} corrections) "
        "against its start and the paper's hybrid",
        "",
        "Mitsuba RMSE of a fresh 256-spp render (seed independent of verification's) against the target.",
        "",
        "| case | neural: default | evaluations | time (s) | kept | Mitsuba: start (best-of-9) | Mitsuba: "
        f"hybrid {budget} | Mitsuba: default | default <= start |",
        "|---|---|---|---|---|---|---|---|---|",
        *default_rows(main, budget),
        "",
    ]


def optimiser_section(optimisers: list[dict]) -> list[str]:
    """Returns section 2 of the report: every optimiser from both starts, per case (RMSE, seconds, evaluations)."""
    lines = [
        "## 2. Optimisers from a random and from the best-of-9 start (RMSE; seconds and evaluations spent in brackets)",
        "",
        f"Budget {1500} objective evaluations each, a value-and-gradient counted as {search.GRADIENT_COST:g}; "
        "basin-hopping is time-boxed.",
        "",
    ]
    names = [key for key in optimisers[0] if key != "case" and not key.endswith(("seconds", "evaluations"))]
    lines += ["| case | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for row in optimisers:
        cells = [f"{row[n]:.2f} ({row[n + ' seconds']:.1f} s, {row[n + ' evaluations']})" for n in names]
        lines.append(f"| {row['case']} | " + " | ".join(cells) + " |")
    return lines


def timings_section(main: list[dict], budgets) -> list[str]:
    """Returns section 4 of the report: seconds per warm fit of the optimiser and the hybrid, median over cases."""
    lines = ["## 4. Timings (seconds per fit, warm, median over cases)", ""]
    lines += ["| method | " + " | ".join(str(b) for b in budgets) + " |", "|---|" + "---|" * len(budgets)]
    for method in ("optimize", "hybrid"):
        lines.append(
            f"| {method} | "
            + " | ".join(f"{np.median([row[f'{method}_{b}_seconds'] for row in main]):.3f}" for b in budgets)
            + " |"
        )
    return lines


def pictures_section(main: list[dict]) -> list[str]:
    """Returns section 5 of the report: the budget plot and a picture per case (written beside the report)."""
    lines = [
        "",
        "## 5. Pictures",
        "",
        "Mean RMSE over the suite against the budget:",
        "",
        "![RMSE against evaluations](rmse-vs-evaluations.png)",
        "",
        "target | best-of-9 | optimiser | hybrid | Mitsuba renders of the hybrid and of the default result, per case:",
        "",
    ]
    return lines + [f"![{row['case']}](cases/{slug(row['case'])}.png)" for row in main]


def default_rows(main: list[dict], budget: int) -> list[str]:
    """Returns the rows of table 1b, and a row of means."""
    rows = [row for row in main if "mitsuba_default" in row]
    lines = [
        f"| {row['case']} | {row['default']:.2f} | {row['default_evaluations']} | {row['default_seconds']:.2f} | "
        f"{row['default_kept']} | {row['mitsuba_start']:.2f} | {row[f'mitsuba_hybrid_{budget}']:.2f} | "
        f"**{row['mitsuba_default']:.2f}** | "
        f"{'yes' if no_worse(row['mitsuba_default'], row['mitsuba_start']) else 'NO'} |"
        for row in rows
    ]
    if rows:
        mean = {
            key: np.mean([row[key] for row in rows])
            for key in ("mitsuba_start", f"mitsuba_hybrid_{budget}", "mitsuba_default")
        }
        lines.append(
            f"| mean | | | | | {mean['mitsuba_start']:.2f} | {mean[f'mitsuba_hybrid_{budget}']:.2f} | "
            f"**{mean['mitsuba_default']:.2f}** | "
            f"{sum(bool(no_worse(row['mitsuba_default'], row['mitsuba_start'])) for row in rows)}/{len(rows)} |"
        )
    return lines


def slug(name: str) -> str:
    """Returns a file-name-safe version of a case name."""
    return "".join(c if c.isalnum() else "-" for c in name).strip("-")


def budget_plot(main: list[dict], path: str, budgets=BUDGETS) -> None:
    """Writes the main table as a plot: mean RMSE over the cases against the budget (optimiser, hybrid, best-of-9)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot

    mean = {
        key: [float(np.mean([row[f"{key}_{b}"] for row in main])) for b in budgets] for key in ("optimize", "hybrid")
    }
    best_of_n = float(np.mean([row["best_of_n"] for row in main]))
    figure, axes = pyplot.subplots(figsize=(6.4, 4.0), dpi=100)
    axes.plot(budgets, mean["optimize"], "o-", color="tab:red", label="optimiser (Nelder-Mead from a random start)")
    axes.plot(budgets, mean["hybrid"], "o-", color="tab:blue", label="hybrid (Nelder-Mead from best-of-9)")
    axes.axhline(best_of_n, color="grey", linestyle="--", label="best-of-9 (no optimisation)")
    axes.set_xscale("log")
    axes.set_xticks(list(budgets), [str(b) for b in budgets])
    axes.set_ylim(bottom=0.0)
    axes.set_xlabel("budget (objective evaluations)")
    axes.set_ylabel("mean RMSE over the suite (0-255 sRGB)")
    axes.set_title(f"The edit suite ({len(main)} cases): neural RMSE against budget")
    axes.grid(True, which="major", alpha=0.3)
    axes.legend()
    figure.tight_layout()
    encoded = io.BytesIO()
    figure.savefig(encoded, format="png")
    pyplot.close(figure)
    files.write_bytes(path, encoded.getvalue())


def run_suite(model: models.Model, model_label: str, out: str, full: bool = False, log=print) -> str:
    """Runs the paper's tables on the edit suite; writes report.md, report.json, the plot, a picture per case to `out`.

    Quick: 5 seeds, basin-hopping time-boxed to 5 s, 40 sequence frames; `full`: 10, 60 s, 120.
    Returns the report's Markdown.
    """
    from matfit.rendering.engine import Renderer

    files.check_folder(out, [(name, os.path.join(out, name)) for name in ("report.md", "report.json")])
    seeds, basin_seconds, frames = (10, 60.0, 120) if full else (5, 5.0, 40)
    os.makedirs(os.path.join(out, "cases"), exist_ok=True)
    renderer = Renderer(model.resolution, 256)
    started = time.perf_counter()
    cases = suite_targets(renderer)
    log(f"main table: {len(cases)} cases x (best-of-9, optimiser over {seeds} seeds, hybrid) at {BUDGETS} evaluations")
    main = main_table(model, cases, seeds=seeds, renderer=renderer)
    for (name, _, target), row in zip(cases, main, strict=True):
        picture = case_picture(model, renderer, target, row, BUDGETS[-1])
        images.write(os.path.join(out, "cases", f"{slug(name)}.png"), images.srgb_decode(picture))
    log(f"optimiser table: L-BFGS-B, SLSQP, CG, Nelder-Mead, basin-hopping ({basin_seconds:g} s) from two starts")
    optimisers = optimiser_table(model, cases, basin_seconds=basin_seconds)
    log(f"sequence table: {frames} frames")
    _, sequence_frames = black_level_sequence(renderer, frames)
    sequence_text = sequence_table(model, sequence_frames, every=max(1, frames // 12))
    settings = (
        f"{'Full' if full else 'Quick'} version (`matfit bench{' --full' if full else ''}`), model {model_label}, "
        f"targets at {model.resolution} px rendered at 256 spp; {seeds} seeds; basin-hopping time-boxed to "
        f"{basin_seconds:g} s per run; {frames} sequence frames. Total {time.perf_counter() - started:.0f} s on this "
        "machine."
    )
    budget_plot(main, os.path.join(out, "rmse-vs-evaluations.png"))
    report_text = suite_report(main, optimisers, sequence_text, seeds=seeds, settings=settings)
    files.write_text(os.path.join(out, "report.md"), report_text)
    document = {"main": main, "optimisers": optimisers, "sequence": sequence_text, "settings": settings}
    files.write_text(os.path.join(out, "report.json"), documents.dumps(document, indent=1))
    return report_text
