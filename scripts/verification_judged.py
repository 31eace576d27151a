"""Verification's rule against the one it replaced, judged by independent renders (issue 41).

For the glass and media presets (every preset with transmission) and 20 reachable random targets
(`bench.reachable_targets`: the training distribution, fixed seed), each rendered in Mitsuba at the
model's resolution with TARGET_SPP samples, it fits with the default settings (`search.Settings()`,
`methods.CORRECTIONS` rounds of correction), lets both rules choose (`matfit.fitting.verify` as it is, and
the confirmation-seed rule of `verify.py` at git revision `--old`), and judges both kept
answers by an independent `bench.JUDGE_SPP`-spp render (seed `bench.JUDGE_SEED` + case, no
seed either rule or the target used) against the target. It prints per-case and mean RMSE and the
seconds of each fit (the gradient stage plus the rule's verification).

Slow (minutes per media case): every finished case is written to `--results` at once, and a run
resumes from that file. Run one at a time:

    nohup python scripts/verification_judged.py --results judged.json > judged.log 2>&1 &
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import types

import numpy as np

from matfit import images, params, shipped
from matfit.app.bench import reachable as bench  # the reachable targets and the judge of every benchmark
from matfit.fitting import fitfile, methods, search, verify
from matfit.rendering import presets
from matfit.rendering.engine import Renderer

OLD = "11d253a"  # the last revision whose verification kept the lead that held in a render with a confirmation seed
TARGET_SPP = 256
TARGET_SEED = 3  # the presets' target renders (the reachable targets have their own, `bench.reachable_targets`)
REACHABLE = 20


def old_rule(revision: str) -> types.ModuleType:
    """Returns matfit's `verify` module as it was at git `revision`, loaded beside today's."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    source = subprocess.run(
        ["git", "show", f"{revision}:matfit/fitting/verify.py"], cwd=root, check=True, capture_output=True, text=True
    ).stdout
    module = types.ModuleType("matfit_verify_old")
    sys.modules[module.__name__] = module
    exec(compile(source, f"verify.py@{revision}", "exec"), module.__dict__)
    return module


def cases() -> list[tuple[str, np.ndarray, int]]:
    """Returns (name, physical parameters, render seed) of every case: a transmissive preset, then four reachable
    targets (`bench.reachable_targets`' parameters and seeds), and so on, so that a run cut short has some of each."""
    chosen = [
        (name, presets.preset(name), TARGET_SEED)
        for name in presets.PRESETS
        if presets.preset(name)[params.INDEX["spec_trans"]] > 0
    ]
    reachable = [
        (f"reachable-{k + 1}", params.from_unit(params.sample_index(bench.TARGET_SEED, bench.TARGET_OFFSET + k)), seed)
        for k, seed in enumerate(bench.TARGET_OFFSET + np.arange(REACHABLE))
    ]
    every = len(reachable) // len(chosen)
    mixed = []
    for k, case in enumerate(chosen):
        mixed += [case, *reachable[k * every : (k + 1) * every]]
    return mixed + reachable[len(chosen) * every :]


def run_case(model, renderer, old, target: np.ndarray, judge_seed: int) -> dict:
    """Returns one case's figures: each rule's kept answer, its seconds, and the judge's RMSE of it."""
    started = time.perf_counter()
    result = search.neural_search(model, target, settings=search.Settings())
    fitted = time.perf_counter() - started
    row = {"fit_seconds": fitted}
    answers = {}
    for rule, module in (("old", old), ("new", verify)):
        started = time.perf_counter()
        if module is verify:  # today's verification: the rounds of correction, then the judgement
            checked = verify.correct_then_verify(renderer, result, target, model=model, corrections=methods.CORRECTIONS)
        else:  # the old revision's, whose `verify` ran both
            checked = module.verify(renderer, result, target, corrections=methods.CORRECTIONS, model=model)
        row[f"{rule}_seconds"] = fitted + time.perf_counter() - started
        row[f"{rule}_kept"] = checked.chosen
        answers[rule] = checked.unit
    judged: dict[bytes, float] = {}
    for name, unit in answers.items():
        key = np.asarray(unit, np.float64).tobytes()
        if key not in judged:
            judged[key] = bench.rendered_rmse(renderer, unit, target, judge_seed, bench.JUDGE_SPP)
        row[f"{name}_judged"] = judged[key]
    return row


def table(results: dict[str, dict]) -> str:
    """Returns the per-case rows and the means as a Markdown table."""
    lines = [
        f"| case | old rule ({bench.JUDGE_SPP}-spp judge) | new rule | old kept | new kept | old s | new s |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, row in results.items():
        lines.append(
            f"| {name} | {row['old_judged']:.3f} | {row['new_judged']:.3f} | "
            f"{row['old_kept']} | {row['new_kept']} | {row['old_seconds']:.1f} | {row['new_seconds']:.1f} |"
        )
    for label in ("presets", "reachable"):
        rows = [row for name, row in results.items() if name.startswith("reachable-") == (label == "reachable")]
        if rows:
            means = {key: np.mean([row[key] for row in rows]) for key in rows[0] if not key.endswith("kept")}
            worse = sum(row["new_judged"] > row["old_judged"] for row in rows)
            lines.append(
                f"| mean {label} ({len(rows)}) | {means['old_judged']:.3f} | "
                f"{means['new_judged']:.3f} | | new worse in {worse} | {means['old_seconds']:.1f} | "
                f"{means['new_seconds']:.1f} |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", default="verification_judged.json", help="checkpoint of finished cases (JSON)")
    parser.add_argument("--old", default=OLD, help="git revision of the rule compared against")
    parser.add_argument("--model", default=None, help="model directory (default: the shipped one)")
    parser.add_argument("--first", default="", help="comma-separated case names to run before the others")
    arguments = parser.parse_args()
    model = fitfile.load_model(arguments.model or str(shipped.MODEL))
    renderer = Renderer(model.resolution, verify.SPP, threads=1)
    old = old_rule(arguments.old)
    results = {}
    if os.path.isfile(arguments.results):
        with open(arguments.results) as file:
            results = json.load(file)
    every = list(enumerate(cases()))
    first = [name for name in arguments.first.split(",") if name]
    unknown = set(first) - {name for _, (name, _, _) in every}
    if unknown:
        parser.error(f"no case named {', '.join(sorted(unknown))}: name cases as the table does (jade, reachable-3)")
    every.sort(key=lambda case: first.index(case[1][0]) if case[1][0] in first else len(first))
    for k, (name, values, seed) in every:
        if name in results:
            continue
        target = images.srgb_encode(renderer.render(values, seed=int(seed), spp=TARGET_SPP))
        results[name] = run_case(model, renderer, old, target, bench.JUDGE_SEED + k)
        row = results[name]
        print(
            f"{name}: old {row['old_judged']:.3f} ({row['old_kept']}), new {row['new_judged']:.3f} ({row['new_kept']})",
            flush=True,
        )
        with open(arguments.results + ".tmp", "w") as file:
            json.dump(results, file, indent=1)
        os.replace(arguments.results + ".tmp", arguments.results)
    print(table(results))


if __name__ == "__main__":
    main()
