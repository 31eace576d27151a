"""`matfit bench-scene`: fits in scenes that are not the test scene (docs/scenes.md).

Built-in scenes (`rendering/scene_library`: a torus knot and a rounded box made in code, under a studio light, an
environment image alone, and a sun with a point light), truth materials (opaque, metal, glass, a medium) rendered
as targets at TARGET_SIZE pixels and TARGET_SPP samples, each fitted from a start 0.2 off in every unit-cube
coordinate; the glossy-plastic-to-rough-gold pair (one start sticks there); and edits of the object alone (a hue
turned, the colour taken out), judged against the edit.

The judge is noise-free: at JUDGE_SIZE pixels, two independent renders of each side (the answer and the truth, or
the edit twice), and the mean over the region the shape changes of the product of the two residuals, whose
expectation is the squared error without the renders' noise; its square root, 0-255 sRGB. The floor is the
target's own noise (two independent targets' RMSE / sqrt 2): what the fit's loss cannot go below. The judge's
floor is the truth judged so against two further truth renders: what the judge reads where the error is 0.
Each finished case is appended to `results.jsonl` in the output folder at once, so the same command again goes on
where a stopped one left off.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np

from matfit import edits, images, params
from matfit.fitting import scene_fit
from matfit.rendering import presets, scene_file, scene_library

TARGET_SIZE = 128
TARGET_SPP = 256
JUDGE_SIZE = 64
# each of the judge's renders: under the sun the truth judged against the truth at 256 spp read -80 to 49 (jade),
# -18 to 18 (glass), -4.5 to -0.7 (gold), squared, as large as what it had to tell; 2048 spp cuts that noise about
# eightfold (docs/scenes.md#what-the-judge-can-tell) for some 3-9 s a render at 64 px
JUDGE_SPP = 2048
OFFSET = 0.2
RESULTS = "results.jsonl"


@dataclass(frozen=True)
class Case:
    """One fit of the bench: where, from what to what, or from what edit."""

    name: str
    object: str
    lighting: str
    truth: np.ndarray  # physical (19,): the material rendered as the target (before the edit)
    start: np.ndarray  # physical (19,)
    kind: str  # "opaque", "metal", "glass", "medium", "pair", "edit"
    edit: str | None = None  # "hue", "desaturate"


def offset(values: np.ndarray, seed: int, amount: float = OFFSET) -> np.ndarray:
    """Returns physical values `amount` off in every unit-cube coordinate (signs drawn by `seed`), clipped."""
    signs = np.where(np.random.default_rng(seed).random(params.COUNT) < 0.5, -1.0, 1.0)
    unit = params.to_unit(values)
    moved = unit + amount * signs
    moved = np.where((moved < 0) | (moved > 1), unit - amount * signs, moved)  # inside the cube, the other way
    return params.from_unit(np.clip(moved, 0.0, 1.0))


def _with(values: np.ndarray, **changes: float) -> np.ndarray:
    changed = values.copy()
    for name, value in changes.items():
        changed[params.INDEX[name]] = value
    return changed


def cases(quick: bool = False) -> list[Case]:
    """Returns the bench's cases (quick: one opaque fit, for a smoke run)."""
    truths = {
        "opaque": presets.preset("red-plastic"),
        "metal": presets.preset("gold"),
        "glass": presets.preset("glass"),
        "medium": presets.preset("jade"),
    }
    scenes = [("knot", "studio"), ("box", "sky"), ("knot", "sun")]
    found = []
    for s, (obj, lighting) in enumerate(scenes):
        for t, (kind, truth) in enumerate(truths.items()):
            found.append(Case(f"{obj}-{lighting}-{kind}", obj, lighting, truth, offset(truth, 10 * s + t), kind))
    if quick:
        return found[:1]
    glossy_plastic = _with(presets.preset("red-plastic"), roughness=0.05, clearcoat=0.0)
    rough_gold = _with(presets.preset("gold"), roughness=0.6)
    found.append(Case("knot-studio-pair", "knot", "studio", rough_gold, glossy_plastic, "pair"))
    plastic = presets.preset("red-plastic")
    found.append(Case("knot-studio-hue", "knot", "studio", plastic, plastic, "edit", "hue"))
    found.append(Case("box-sky-desaturate", "box", "sky", plastic, plastic, "edit", "desaturate"))
    return found


def edited(srgb: np.ndarray, region: np.ndarray, edit: str) -> np.ndarray:
    """Returns the sRGB picture with the object's pixels (`region`) edited: a hue turned 120 degrees, or greyscale."""
    changed = edits.hue_rotate(srgb, 120.0) if edit == "hue" else edits.saturate(srgb, 1.0)
    return np.where(region[..., None], changed, srgb)


def noise_free_error(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], weights: np.ndarray) -> float:
    """Returns the 0-255 RMSE of two sides without their noise: sqrt of the weighted mean of (a1 - b1)(a2 - b2)."""
    product = ((a[0] - b[0]) * (a[1] - b[1])).mean(axis=2)
    return 255.0 * float(np.sqrt(max(0.0, float((product * weights).sum() / weights.sum()))))


def run_case(case: Case, folder: str, steps: int, *, size: int = TARGET_SIZE, judge_size: int = JUDGE_SIZE) -> dict:
    """Returns the figures of one case: the fit's and the start's noise-free errors, the floor, the time."""
    path = scene_library.write(os.path.join(folder, "scenes"), case.object, case.lighting)
    read = scene_file.read(path, scene_library.OBJECT_ID)
    target_renderer = scene_file.Renderer(read, read.size(size))
    target_srgb = images.srgb_encode(target_renderer.render(case.truth, seed=1, spp=TARGET_SPP))
    second = images.srgb_encode(target_renderer.render(case.truth, seed=2, spp=TARGET_SPP))
    judge = scene_file.Renderer(read, read.size(judge_size))
    region, _ = scene_fit.region(judge)
    weights = region.astype(np.float64)
    big_region = images.resample(region[..., None].astype(np.float32), *read.size(size))[..., 0] > 0.5
    if case.edit is not None:
        target_srgb = edited(target_srgb, big_region, case.edit)
    started, cpu = time.perf_counter(), time.process_time()
    outcome = scene_fit.fit(read, images.srgb_decode(target_srgb), start=case.start, steps=steps)
    seconds, cpu = time.perf_counter() - started, time.process_time() - cpu

    def pair(values: np.ndarray, seeds: tuple[int, int] = (101, 102)) -> tuple[np.ndarray, np.ndarray]:
        return tuple(  # type: ignore[return-value]
            images.srgb_encode(judge.render(values, seed=seed, spp=JUDGE_SPP)) for seed in seeds
        )

    def truth(seeds: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        if case.edit is not None:  # the edit applied to two independent truth renders: the edit without its noise
            return tuple(edited(side, region, case.edit) for side in pair(case.truth, seeds))  # type: ignore[return-value]
        return pair(case.truth, seeds)

    truth_pair = truth((101, 102))
    small = images.resample(target_srgb, *read.size(judge_size))
    floor = float(images.rmse(target_srgb, second if case.edit is None else target_srgb, big_region)) / np.sqrt(2)
    return {
        "case": case.name,
        "kind": case.kind,
        "fit": round(noise_free_error(pair(outcome.values), truth_pair, weights), 3),
        "start": round(noise_free_error(pair(case.start), truth_pair, weights), 3),
        "floor": round(floor, 3) if case.edit is None else None,
        # the truth judged against two further truth renders: what the judge reads where the error is 0
        "judge_floor": round(noise_free_error(truth((103, 104)), truth_pair, weights), 3),
        "target_vs_judge": round(float(images.rmse(small, truth_pair[0], weights)), 3),
        "accepted": outcome.accepted,
        "moved_off_bound": outcome.bounds.get("moved"),
        "lobes_off": outcome.plain.get("off"),
        "plain": outcome.plain,  # each try of plain lobes: the lobes off, behind by, its standard error, kept
        "robust_judge": outcome.judge.get("robust"),  # None: a transmissive fit, whose judge keeps the squares
        "noise_kurtosis": outcome.judge.get("kurtosis"),
        "darkening": outcome.residual.get("darkening"),  # None: a transmissive fit, whose residual is linear
        "linear_residual": outcome.residual.get("linear"),
        "by_channel": outcome.residual.get("by_channel"),  # None: no coloured medium at a transmissive start
        "again": outcome.again.get("kept"),  # None: an opaque fit, whose chosen start descends once
        "descents": outcome.again.get("errors"),  # the fit's judge's readings of each descent's answer and their mean
        "at_zero": cast(dict, outcome.bounds.get("at_zero", {})).get("zero"),
        "integrator": outcome.integrator,
        "seconds": round(seconds, 1),
        "cpu_seconds": round(cpu, 1),  # the fit's, all threads together: what a load beside it changes less
        "values": [round(float(v), 5) for v in outcome.values],
    }


def run(folder: str, *, quick: bool = False, steps: int = scene_fit.STEPS, log: Callable[[str], None] = print) -> list:
    """Returns every case's figures, fitting those `folder`'s results.jsonl does not hold yet (each appended as it
    ends)."""
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, RESULTS)
    done: dict[str, dict] = {}
    if os.path.isfile(path):
        with open(path, encoding="utf-8") as file:
            for line in file:
                if line.strip().endswith("}"):  # a line cut by a kill is fitted again
                    row = json.loads(line)
                    done[row["case"]] = row
    rows = []
    for case in cases(quick):
        if case.name in done:
            rows.append(done[case.name])
            continue
        log(f"{case.name}: fitting ({len(rows) + 1} of {len(cases(quick))})")
        row = run_case(case, folder, steps)
        with open(path, "a", encoding="utf-8") as file:
            file.write(json.dumps(row) + "\n")
            file.flush()
            os.fsync(file.fileno())
        log(f"{case.name}: fit {row['fit']:.2f}, start {row['start']:.2f}, {row['seconds']:.0f} s")
        rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    """Returns the bench's markdown table (rows of an older run, without the judge's floor or CPU seconds, leave
    those cells empty)."""
    lines = [
        "| case | kind | noise-free error: fit | start | target noise | judge's floor | integrator | kept | seconds "
        "| CPU seconds |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        floor = "" if row["floor"] is None else f"{row['floor']:.2f}"
        judge_floor = "" if row.get("judge_floor") is None else f"{row['judge_floor']:.2f}"
        cpu = "" if row.get("cpu_seconds") is None else f"{row['cpu_seconds']:.0f}"
        lines.append(
            f"| {row['case']} | {row['kind']} | {row['fit']:.2f} | {row['start']:.2f} | {floor} | {judge_floor} "
            f"| {row['integrator']} | {'yes' if row['accepted'] else 'no'} | {row['seconds']:.0f} | {cpu} |"
        )
    return "\n".join(lines)
