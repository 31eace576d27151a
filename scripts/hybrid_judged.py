"""The default fit against the paper's plain hybrid on unedited presets, judged noise-free (issue 48).

For each preset of PRESETS and each of SEEDS, the preset is rendered at TARGET_SIZE px with TARGET_SPP samples and
written as an 8-bit PNG (what a user would fit); each method of METHODS fits it as `matfit fit` would
(`fitfile.fit_file`, one `process.Pool`), and its answer is judged against the truth without either side's noise:
JUDGE_RENDERS independent JUDGE_SPP renders of the answer (R_i) and as many of the truth (T_a), all with seeds no
stage uses, at the model's resolution; the figure is 255 sqrt of the mean over i != j, a != b of
mean((R_i - T_a)(R_j - T_b)), whose expectation is the squared difference of the two noise-free pictures (signed:
below zero, the two are alike within the judge's noise). It prints each case and the mean of each method per
preset; every finished case goes to `--results` at once and a run resumes from it:

    nohup python scripts/hybrid_judged.py --results hybrid.json > hybrid.log 2>&1 &
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import tempfile
import time

import numpy as np

from matfit import images, shipped
from matfit.fitting import fitfile
from matfit.fitting.methods import Method, Settings
from matfit.fitting.request import Request
from matfit.rendering import presets
from matfit.rendering.engine import Renderer
from matfit.rendering.process import Pool

PRESETS = ("jade", "glass", "milk", "amber-glass", "gold", "red-plastic")
SEEDS = (11, 12, 13)
TARGET_SIZE = 128
TARGET_SPP = 256
JUDGE_SPP = 256
JUDGE_RENDERS = 4  # independent renders of each side
JUDGE_SEED = 9_000_001  # case k's judge: JUDGE_SEED + 8k .. + 8k + 7; no stage's seed
METHODS = {
    "default": {},
    "hybrid": {"settings": Settings(Method.hybrid), "verified": False, "answer": "best"},
    "hybrid-lbfgsb": {"settings": Settings(Method.hybrid_lbfgsb)},
}


def noise_free(renderer, answer: np.ndarray, truth: np.ndarray, k: int) -> float:
    """Returns the judge's RMSE (0-255) between the noise-free renders of two materials (physical values), signed: a
    negative figure is an estimate below zero (the two are alike within the judge's noise)."""
    seeds = [JUDGE_SEED + 2 * JUDGE_RENDERS * k + j for j in range(2 * JUDGE_RENDERS)]
    jobs = [(answer, seed) for seed in seeds[:JUDGE_RENDERS]] + [(truth, seed) for seed in seeds[JUDGE_RENDERS:]]
    for values, seed in jobs:
        renderer.prefetch(values, seed, JUDGE_SPP)
    renders = [np.asarray(images.srgb_encode(renderer.render(v, s, JUDGE_SPP)), np.float64) for v, s in jobs]
    ours, theirs = renders[:JUDGE_RENDERS], renders[JUDGE_RENDERS:]
    products = [
        float(np.mean((ours[i] - theirs[a]) * (ours[j] - theirs[b])))
        for i, j in itertools.permutations(range(JUDGE_RENDERS), 2)
        for a, b in itertools.permutations(range(JUDGE_RENDERS), 2)
    ]
    estimate = float(np.mean(products))  # every pair of independent differences: the noise cancels
    return 255.0 * float(np.sign(estimate) * np.sqrt(abs(estimate)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", default="hybrid_judged.json", help="checkpoint of finished cases (JSON)")
    parser.add_argument("--methods", default=",".join(METHODS), help="methods to compare, comma-separated")
    arguments = parser.parse_args()
    methods = arguments.methods.split(",")
    model = fitfile.load_model(str(shipped.MODEL))
    results: dict = {}
    if os.path.isfile(arguments.results):
        with open(arguments.results) as file:
            results = json.load(file)
    large = Renderer(TARGET_SIZE, TARGET_SPP, threads=1)
    with Pool() as pool, tempfile.TemporaryDirectory() as folder:
        pool.load(model.resolution, 64)
        cases = [(name, seed) for name in PRESETS for seed in SEEDS]
        for k, (name, seed) in enumerate(cases):
            case = f"{name}-{seed}"
            row = results.get(case, {})
            if all(method in row for method in methods):
                continue
            truth = presets.preset(name)
            picture = os.path.join(folder, f"{case}.png")
            images.write(picture, large.render(truth, seed=seed))
            for method in methods:
                if method in row:
                    continue
                started = time.perf_counter()
                outcome, _ = fitfile.fit_file(Request(picture, **METHODS[method]), model, renderer=pool)
                seconds = time.perf_counter() - started
                row[method] = {
                    "judged": noise_free(pool, outcome.values, truth, k),
                    "seconds": seconds,
                    "unit": [float(x) for x in outcome.unit],
                }
                print(f"{case} {method}: {row[method]['judged']:.3f} ({seconds:.1f} s)", flush=True)
            results[case] = row
            with open(arguments.results + ".tmp", "w") as file:
                json.dump(results, file, indent=1)
            os.replace(arguments.results + ".tmp", arguments.results)
    print("| preset | " + " | ".join(methods) + " |")
    print("|---|" + "---|" * len(methods))
    for name in PRESETS:
        rows = [row for case, row in results.items() if case.rsplit("-", 1)[0] == name]
        means = [np.mean([row[m]["judged"] for row in rows if m in row]) for m in methods]
        print(f"| {name} | " + " | ".join(f"{value:.3f}" for value in means) + " |")


if __name__ == "__main__":
    main()
