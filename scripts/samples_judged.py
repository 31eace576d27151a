"""How many samples a verification batch needs: the default fit's Mitsuba stages at several batch sizes, judged.

For the judged set of `verification_judged.py` (every transmissive preset and 20 reachable targets), each target
is fitted once (`search.neural_search`, default settings); then, for each batch size of `--spp`, verification
(`verify.correct_then_verify`, `methods.CORRECTIONS` rounds), the ranges and the clean answer (`clean.clean`) run
as a default fit runs them, on a `process.Pool`. Every kept answer is judged noise-free against the target: two
independent JUDGE_SPP renders R1, R2 (seeds no stage uses), the RMSE of the mean of (R1 - t)(R2 - t), whose
expectation is the squared error of the noise-free render (render noise cancels). It prints, per case and batch
size, what was kept, the judge's figure, the renders made and the samples rendered, and the means.

Every finished case is written to `--results` at once; a run resumes from that file:

    nohup python scripts/samples_judged.py --results samples.json > samples.log 2>&1 &
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from matfit import images, params, shipped
from matfit.fitting import clean, fitfile, methods, ranges, search, verify
from matfit.rendering.process import Pool

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from verification_judged import TARGET_SPP, cases  # the same judged set

JUDGE_SPP = 256
JUDGE_SEED = 7_000_001  # judge renders of case k: JUDGE_SEED + 2k, + 2k + 1; no stage's seed


def noise_free(renderer, unit: np.ndarray, target: np.ndarray, k: int) -> float:
    """Returns the judge's estimate of the RMSE (0-255) of the noise-free render of `unit` against `target`."""
    values = params.from_unit(unit)
    seeds = (JUDGE_SEED + 2 * k, JUDGE_SEED + 2 * k + 1)
    for seed in seeds:
        renderer.prefetch(values, seed, JUDGE_SPP)
    first, second = (images.srgb_encode(renderer.render(values, seed, JUDGE_SPP)) for seed in seeds)
    product = (np.asarray(first, np.float64) - target) * (np.asarray(second, np.float64) - target)
    return 255.0 * float(np.sqrt(max(float(np.mean(product)), 0.0)))


class Counted:
    """A renderer that counts the distinct renders asked of it (a prefetched one counts once)."""

    def __init__(self, renderer):
        self.renderer, self.keys = renderer, set()

    def prefetch(self, values, seed=0, spp=None):
        self.keys.add((np.asarray(values, np.float64).tobytes(), seed, spp))
        self.renderer.prefetch(values, seed, spp)

    def render(self, values, seed=0, spp=None):
        self.keys.add((np.asarray(values, np.float64).tobytes(), seed, spp))
        return self.renderer.render(values, seed, spp)


def stages(model, renderer, result, target: np.ndarray, size: str) -> dict:
    """Returns what the default fit's Mitsuba stages keep at `size` samples a batch ("32"; "32/64": the rounds'
    residual renders at 64), with their cost."""
    spp, _, residual = size.partition("/")
    spp, residual_spp = int(spp), int(residual or spp)
    renderer = Counted(renderer)
    started = time.perf_counter()
    verified = verify.correct_then_verify(
        renderer, result, target, model=model, corrections=methods.CORRECTIONS, spp=spp, residual_spp=residual_spp
    )
    verifying = time.perf_counter() - started
    decoding = ranges.Decoding(model.decoder.module)
    tau, source = ranges.threshold(model.path, verified.unit)
    found = ranges.measure(decoding, model.decoder.variables, verified.unit, None, tau, source)
    cleaned = clean.clean(
        decoding,
        model.decoder.variables,
        verified.unit,
        target,
        None,
        found,
        renderer,
        rendered=verified.renders,
        spp=spp,
    )
    renders = len(renderer.keys)
    return {
        "unit": [float(x) for x in cleaned.unit],
        "kept": f"{verified.chosen}/{cleaned.chosen}",
        "verify_seconds": verifying,
        "seconds": time.perf_counter() - started,
        "renders": renders,
        "samples": sum(int(key[2] or spp) for key in renderer.keys),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", default="samples_judged.json", help="checkpoint of finished cases (JSON)")
    parser.add_argument(
        "--spp", default="64,32,16", help="batch sizes to compare, comma-separated (32/64: residuals at 64)"
    )
    parser.add_argument("--count", type=int, default=None, help="only the first COUNT cases")
    parser.add_argument(
        "--label", default=None, help="record the one size of --spp under this name (a rule of another revision)"
    )
    arguments = parser.parse_args()
    sizes = arguments.spp.split(",")
    if arguments.label and len(sizes) != 1:
        parser.error("--label names one size: give --spp one")
    keys = dict(zip(sizes, [arguments.label] if arguments.label else sizes, strict=True))
    model = fitfile.load_model(str(shipped.MODEL))
    results: dict = {}
    if os.path.isfile(arguments.results):
        with open(arguments.results) as file:
            results = json.load(file)
    with Pool() as renderer:
        renderer.load(model.resolution, verify.SPP)
        for k, (name, values, seed) in enumerate(cases()[: arguments.count]):
            if name in results and all(keys[size] in results[name] for size in sizes):
                continue
            target = images.srgb_encode(renderer.render(values, seed=int(seed), spp=TARGET_SPP))
            result = search.neural_search(model, target, settings=search.Settings())
            row = results.get(name, {})
            judged: dict[bytes, float] = {}
            for size in sizes:
                if keys[size] in row:
                    continue
                out = stages(model, renderer, result, target, size)
                key = np.asarray(out["unit"], np.float64).tobytes()
                if key not in judged:
                    judged[key] = noise_free(renderer, np.asarray(out["unit"]), target, k)
                out["judged"] = judged[key]
                row[keys[size]] = out
                print(
                    f"{name} {keys[size]}: {out['judged']:.3f} kept {out['kept']}, {out['renders']} renders, "
                    f"{out['seconds']:.1f} s",
                    flush=True,
                )
            results[name] = row
            with open(arguments.results + ".tmp", "w") as file:
                json.dump(results, file, indent=1)
            os.replace(arguments.results + ".tmp", arguments.results)
    for label in ("presets", "reachable"):
        rows = [row for name, row in results.items() if name.startswith("reachable-") == (label == "reachable")]
        for size in sizes:
            done = [row[keys[size]] for row in rows if keys[size] in row]
            if done:
                print(
                    f"mean {label} ({len(done)}) {keys[size]}: judged {np.mean([r['judged'] for r in done]):.3f}, "
                    f"renders {np.mean([r['renders'] for r in done]):.1f}, "
                    f"seconds {np.mean([r['seconds'] for r in done]):.2f}"
                )


if __name__ == "__main__":
    main()
