"""matfit's CUDA measurements (issue 37): may CUDA and LLVM renders share a dataset, how fast do datasets render on
one GPU with 1 to 12 processes, and what does a default `matfit fit` cost there.

    python scripts/device/cuda.py prepare            here, with llvm_ad_rgb: writes .device/ (~8 MB)
    python scripts/device/cuda.py measure OUT         on the GPU machine: writes OUT/cuda.json and OUT/cuda.log
    python scripts/device/cuda.py measure OUT --rehearse   the same steps on a CPU, llvm_ad_rgb, tiny counts

`scripts/device/cuda.sh` wraps both (and installs the wheels on the device). Every step of `measure` runs in a
process of its own under a share of one time budget; a step that fails or runs out of time is recorded in
cuda.json as such, and the steps after it still run.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)  # this checkout's matfit, here and in every step's process (PYTHONPATH below)
os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [os.environ.get("PYTHONPATH"), ROOT]))
PREPARED = os.path.join(ROOT, ".device")
COMPARE_FILE = "compare.npz"
TARGET_FILE = "recoloured.png"
MODEL_DIR = "model"
NETWORKS = ("decoder", "encoder-8")  # the decoder and the smallest encoder: the model fits in what may travel
RESOLUTION = 64  # the shipped model's, and its datasets'
PASSES = ((16, 0), (16, 1), (256, 0), (256, 1))  # (spp, seed) of each render of each material
SAMPLES = 9  # training-distribution materials beside the presets
MAX_PREPARED_BYTES = 10 * 2**20
BUDGET_S = 220  # the whole measurement, installation excluded
# (resolution, workers, images) of each render-dataset timing, most wanted first; one dataset per resolution grows
# run after run, so only its first run renders the scene without its sphere (4096 spp): a warm-up of one chunk.
DATASET_RUNS = ((128, 1, 192), (128, 8, 768), (128, 4, 384), (128, 12, 768), (64, 1, 192), (64, 8, 768))
REHEARSAL_RUNS = ((16, 1, 32), (16, 2, 64), (8, 2, 32))
WARM_UP = 16
SPP = 16


def log(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", flush=True)


def materials() -> tuple[list[str], np.ndarray]:
    """Returns the names and physical values (N, 19) of the compared materials: every preset, then samples."""
    from matfit import params
    from matfit.rendering import presets

    names = list(presets.PRESETS) + [f"sample-{i}" for i in range(SAMPLES)]
    values = [presets.preset(name) for name in presets.PRESETS]
    values += [params.from_unit(params.sample_index(0, i)) for i in range(SAMPLES)]
    return names, np.stack(values).astype(np.float64)


def render_all(values: np.ndarray, variant: str | None) -> tuple[np.ndarray, str, dict]:
    """Returns (renders (N, len(PASSES), R, R, 3) float32 linear, the variant, versions) of every material."""
    from matfit.rendering import engine

    renderer = engine.Renderer(RESOLUTION, PASSES[0][0], variant)
    renderer.render(values[0], seed=99, spp=1)  # compiles the kernels
    images = np.stack([[renderer.render(v, seed=seed, spp=spp) for spp, seed in PASSES] for v in values])
    return images.astype(np.float32), renderer.variant, engine.versions()


def prepare() -> None:
    """Writes .device/: LLVM renders of the compared materials, a slim copy of the model, the example to fit."""
    from matfit import shipped
    from matfit.rendering import engine

    engine.choose_variant(engine.LLVM_VARIANT)  # the reference is LLVM's: refused here without libLLVM >= 19
    names, values = materials()
    log(f"rendering {len(names)} materials x {len(PASSES)} passes at {RESOLUTION} px with llvm_ad_rgb")
    started = time.perf_counter()
    images, variant, versions = render_all(values, engine.LLVM_VARIANT)
    log(f"rendered in {time.perf_counter() - started:.1f} s")
    shutil.rmtree(PREPARED, ignore_errors=True)
    os.makedirs(os.path.join(PREPARED, MODEL_DIR))
    np.savez_compressed(
        os.path.join(PREPARED, COMPARE_FILE),
        names=np.array(names),
        values=values,
        images=images,
        passes=np.array(PASSES),
        variant=np.array(variant),
        versions=np.array(json.dumps(versions)),
    )
    for name in NETWORKS:
        for suffix in (".json", ".msgpack"):
            shutil.copy(os.path.join(shipped.MODEL, name + suffix), os.path.join(PREPARED, MODEL_DIR))
    shutil.copy(os.path.join(shipped.EXAMPLES, TARGET_FILE), PREPARED)
    commit = subprocess.run(["git", "-C", ROOT, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    manifest = {"commit": commit, "made": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "variant": variant}
    with open(os.path.join(PREPARED, "manifest.json"), "w") as file:
        json.dump({**manifest, "versions": versions, "networks": list(NETWORKS)}, file, indent=2)
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(PREPARED) for f in fs)
    log(f"wrote {PREPARED} ({size / 2**20:.1f} MiB)")
    if size > MAX_PREPARED_BYTES:
        raise SystemExit(f"error: {PREPARED} is {size / 2**20:.1f} MiB, more than {MAX_PREPARED_BYTES >> 20} MiB")


def srgb_rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Returns matfit's image RMSE (sRGB, 0-255) of two linear renders."""
    from matfit import images

    return float(images.rmse(images.srgb_encode(a), images.srgb_encode(b)))


def compare(result: str, variant: str | None, count: int | None = None) -> None:
    """Renders the prepared materials (the first `count`; None: all) with `variant` (None: the automatic choice) and
    compares them with LLVM's."""
    data = np.load(os.path.join(PREPARED, COMPARE_FILE))
    if [tuple(p) for p in data["passes"].tolist()] != list(PASSES):
        raise SystemExit("error: .device/compare.npz was made with other passes: run the prepare step again")
    values, llvm, names = data["values"][:count], data["images"][:count], data["names"].tolist()[:count]
    started = time.perf_counter()
    ours, chosen, versions = render_all(values, variant)
    seconds = time.perf_counter() - started
    rows = []
    for name, mine, reference in zip(names, ours, llvm, strict=True):
        row = {"material": name}
        for spp, (first, second) in ((16, (0, 1)), (256, (2, 3))):
            row[f"llvm_seeds_{spp}"] = srgb_rmse(reference[first], reference[second])
            row[f"ours_seeds_{spp}"] = srgb_rmse(mine[first], mine[second])
            # other seeds on each side: the figure to set beside llvm_seeds (noise only, if the two agree on average)
            row[f"cross_{spp}"] = 0.5 * (
                srgb_rmse(mine[first], reference[second]) + srgb_rmse(mine[second], reference[first])
            )
            row[f"same_seed_{spp}"] = srgb_rmse(mine[first], reference[first])
        mean_ours = mine[2:].mean(axis=(0, 1, 2))  # 256 spp, both seeds, per channel (linear)
        mean_llvm = reference[2:].mean(axis=(0, 1, 2))
        row["mean_ours_256"] = mean_ours.tolist()
        row["mean_llvm_256"] = mean_llvm.tolist()
        row["mean_difference_percent"] = float(100 * np.abs(mean_ours - mean_llvm).max() / max(mean_llvm.mean(), 1e-6))
        seed_spread = np.abs(reference[2].mean(axis=(0, 1)) - reference[3].mean(axis=(0, 1))).max()
        row["llvm_seed_mean_difference_percent"] = float(100 * seed_spread / max(mean_llvm.mean(), 1e-6))
        rows.append(row)

    def ratio(spp):
        return float(np.mean([r[f"cross_{spp}"] for r in rows]) / np.mean([r[f"llvm_seeds_{spp}"] for r in rows]))

    worst = max(rows, key=lambda r: r["cross_256"] / max(r["llvm_seeds_256"], 1e-9))
    summary = {
        "variant": chosen,
        "llvm_variant": str(data["variant"]),
        "versions": versions,
        "llvm_versions": json.loads(str(data["versions"])),
        "materials": len(rows),
        "resolution": RESOLUTION,
        "render_seconds": round(seconds, 2),
        "cross_over_llvm_seeds_16": ratio(16),
        "cross_over_llvm_seeds_256": ratio(256),
        "worst_material_256": worst["material"],
        "worst_cross_over_llvm_seeds_256": worst["cross_256"] / max(worst["llvm_seeds_256"], 1e-9),
        "max_mean_difference_percent": max(r["mean_difference_percent"] for r in rows),
        "max_llvm_seed_mean_difference_percent": max(r["llvm_seed_mean_difference_percent"] for r in rows),
        "mean_same_seed_16": float(np.mean([r["same_seed_16"] for r in rows])),
        "mean_llvm_seeds_16": float(np.mean([r["llvm_seeds_16"] for r in rows])),
        # The rule: a variant whose renders differ from LLVM's by no more than LLVM's differ from each other (other
        # seeds, 256 spp: mostly noise-free, so a bias would show) may share a dataset with them.
        "mixable": ratio(256) <= 1.1 and ratio(16) <= 1.05,
        "rows": rows,
    }
    write_json(result, summary)


def write_json(path: str, data: dict) -> None:
    with open(path, "w") as file:
        json.dump(data, file, indent=2)


class Steps:
    """The measurement's steps, each a process of its own, under one time budget; results gathered in one dict."""

    def __init__(self, out: str, work: str, budget: float, rehearse: bool):
        self.out, self.work, self.rehearse = out, work, rehearse
        self.deadline = time.monotonic() + budget
        self.results: dict = {"rehearsal": rehearse, "budget_s": budget, "errors": {}, "skipped": []}
        self.python = sys.executable
        self.variant = ["--variant", "llvm_ad_rgb"] if rehearse else []  # on the GPU: the automatic choice

    def left(self) -> float:
        return self.deadline - time.monotonic()

    def run(self, name: str, command: list[str], limit: float, poll=None) -> tuple[int | None, float, str]:
        """Runs a command with at most `limit` seconds (less if the budget is shorter); returns (exit code or None
        when stopped, seconds, its output's tail). `poll()` is called every 50 ms while it runs."""
        limit = min(limit, self.left() - 5)
        if limit < 5:
            raise TimeoutError(f"{name}: no time left in the budget")
        log(f"{name}: {' '.join(command)} (at most {limit:.0f} s)")
        with open(os.path.join(self.work, f"{name}.out"), "w+") as output:
            started = time.perf_counter()
            process = subprocess.Popen(
                command, cwd=ROOT, stdout=output, stderr=subprocess.STDOUT, start_new_session=True
            )
            code = None
            while time.perf_counter() - started < limit:
                if poll is not None:
                    poll()
                code = process.poll()
                if code is not None:
                    break
                time.sleep(0.05)
            seconds = time.perf_counter() - started
            if code is None:  # Ctrl-C first: render-dataset then stops its render processes itself
                os.killpg(process.pid, signal.SIGINT)
                try:
                    process.wait(10)
                except subprocess.TimeoutExpired:
                    os.killpg(process.pid, signal.SIGKILL)
                    process.wait()
            output.seek(0)
            lines = [line.rstrip() for line in output.read().replace("\r", "\n").splitlines() if line.strip()]
        tail = "\n".join(lines[-15:])
        log(f"{name}: exit {code}, {seconds:.1f} s\n{tail}")
        if code is None:
            raise TimeoutError(f"{name}: stopped after {limit:.0f} s")
        return code, seconds, tail

    def step(self, name: str, function) -> None:
        if self.left() < 15:
            self.results["skipped"].append(name)
            log(f"{name}: skipped, {self.left():.0f} s left")
            return
        try:
            function()
        except Exception as error:
            self.results["errors"][name] = f"{type(error).__name__}: {error}"
            log(f"{name} failed: {traceback.format_exc()}")
        self.save()

    def save(self) -> None:
        write_json(os.path.join(self.out, "cuda.json"), self.results)

    def device(self) -> None:
        query = ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"]
        try:
            found = subprocess.run(query, capture_output=True, text=True, timeout=20)
            self.results["gpu"] = found.stdout.strip() or found.stderr.strip()
        except (OSError, subprocess.TimeoutExpired) as error:
            self.results["gpu"] = f"no nvidia-smi: {error}"
        self.results["cpus"] = os.cpu_count()

    def choice(self) -> None:
        code = (
            "import json; from matfit.rendering import engine as render; "
            "variant, notice = render.choose_variant(None); "
            "print(json.dumps({'auto_variant': variant, 'notice': notice, 'cuda_devices': render.cuda_devices(), "
            "'versions': render.versions()}))"
        )
        status, seconds, tail = self.run("choice", [self.python, "-c", code], 60)
        found = json.loads(tail.splitlines()[-1]) if status == 0 else {"error": tail}
        found["seconds"] = round(seconds, 2)
        if found.get("auto_variant") != "cuda_ad_rgb":  # why not, asked in a process whose Mitsuba is still unset
            why = "from matfit.rendering import engine as render; print(render.cuda_problem())"
            found["cuda_problem"] = self.run("cuda-problem", [self.python, "-c", why], 60)[2].splitlines()[-1:]
        picture = os.path.join(self.work, "gold.png")
        command = [self.python, "-m", "matfit", "render", "--preset", "gold", "-o", picture, "--size", "64"]
        status, seconds, tail = self.run("render", [*command, "--spp", "16", *self.variant], 60)
        found["render_command"] = {"exit": status, "seconds": round(seconds, 2), "said": tail.splitlines()[-1:]}
        self.results["choice"] = found

    def compare(self) -> None:
        result = os.path.join(self.work, "compare.json")
        command = [self.python, os.path.abspath(__file__), "compare", result, *self.variant]
        command += ["--count", "2"] if self.rehearse else []
        status, _, tail = self.run("compare", command, 120)
        if status != 0:
            raise RuntimeError(tail)
        with open(result) as file:
            self.results["compare"] = json.load(file)

    def fit(self) -> None:
        target = os.path.join(PREPARED, TARGET_FILE)
        model = os.path.join(PREPARED, MODEL_DIR)
        runs = {}
        for label, extra in (("first", []), ("second", []), ("third", []), ("warm_no_verify", ["--no-verify"])):
            output = os.path.join(self.work, f"fit-{label}.json")
            command = [self.python, "-m", "matfit", "fit", target, "-o", output, "--model", model, *extra]
            status, seconds, tail = self.run(f"fit-{label}", [*command, *self.variant], 150)
            run = {"exit": status, "process_seconds": round(seconds, 2), "said": tail.splitlines()[-1:]}
            if status == 0:
                with open(output) as file:
                    document = json.load(file)
                verification = document.get("verification") or {}
                run.update(
                    mitsuba_variant=document.get("mitsuba_variant"),
                    wall_time_s=document.get("wall_time_s"),
                    fit_seconds=document.get("fit_seconds"),
                    verification_seconds=verification.get("seconds"),
                    mitsuba_rmse=document.get("mitsuba_rmse"),
                    neural_rmse=document.get("neural_rmse"),
                )
            runs[label] = run
            self.results["fit"] = {"model": f".device/{MODEL_DIR} ({', '.join(NETWORKS)})", **runs}
            self.save()

    def datasets(self) -> None:
        grown: dict[int, int] = {}  # resolution -> images its dataset holds so far
        timings = []
        self.results["dataset"] = timings
        runs = REHEARSAL_RUNS if self.rehearse else DATASET_RUNS
        plan = []  # every timing, after a warm-up per resolution
        for resolution, workers, images in runs:
            if all(planned[0] != resolution for planned in plan):  # the scene without its sphere, and one chunk
                plan.append((resolution, 1, WARM_UP, True))
            plan.append((resolution, workers, images, False))
        for resolution, workers, images, warm_up in plan:
            if self.left() < 30:
                self.results["skipped"].append(f"dataset {resolution} px, {workers} workers")
                continue
            path = os.path.join(self.work, f"dataset-{resolution}")
            before = grown.get(resolution, 0)
            total = before + images
            seen: list[tuple[float, int]] = []
            started = time.perf_counter()

            def poll(path=path, seen=seen, started=started):
                try:
                    done = int(np.load(os.path.join(path, "done.npy"), mmap_mode="r").sum())
                except (OSError, ValueError, EOFError):
                    return
                if not seen or done != seen[-1][1]:
                    seen.append((time.perf_counter() - started, done))

            command = [self.python, "-m", "matfit", "render-dataset", path, "--count", str(total)]
            command += ["--resolution", str(resolution), "--spp", str(SPP), "--workers", str(workers), *self.variant]
            timing = {"resolution": resolution, "spp": SPP, "workers": workers, "images": images}
            if warm_up:
                timing["warm_up"] = "the scene without its sphere (4096 spp), then the images"
            try:
                status, seconds, tail = self.run(f"dataset-{resolution}-{workers}", command, 90, poll)
            except TimeoutError as error:
                timing["error"] = str(error)
                timings.append(timing)
                self.save()
                continue
            poll()
            grown[resolution] = total if status == 0 else before
            rendered = [(t, d - before) for t, d in seen if d > before]
            timing.update(exit=status, command_seconds=round(seconds, 2), said=tail.splitlines()[-1:])
            if status == 0 and rendered:
                first_t, first_done = rendered[0]
                last_t, last_done = rendered[-1]
                timing["first_images_after_s"] = round(first_t, 2)
                timing["images_per_second_command"] = round(images / seconds, 1)
                if last_done > first_done and last_t > first_t:
                    timing["images_per_second_steady"] = round((last_done - first_done) / (last_t - first_t), 1)
            timings.append(timing)
            self.save()
        resolution = runs[0][0]
        steady = [t for t in timings if t["resolution"] == resolution and "warm_up" not in t]
        steady = [t for t in steady if "images_per_second_steady" in t]
        if steady:
            best = max(steady, key=lambda t: t["images_per_second_steady"])
            self.results["best_workers"] = {"resolution": resolution, "workers": best["workers"]}


STEPS = ("device", "choice", "compare", "fit", "dataset")


def measure(out: str, rehearse: bool, budget: float, only: list[str]) -> None:
    os.makedirs(out, exist_ok=True)
    work = tempfile.mkdtemp(prefix="matfit-cuda-")
    steps = Steps(out, work, budget, rehearse)
    started = time.perf_counter()
    functions = (steps.device, steps.choice, steps.compare, steps.fit, steps.datasets)
    for name, function in zip(STEPS, functions, strict=True):
        if name in only:
            steps.step(name, function)
    steps.results["elapsed_s"] = round(time.perf_counter() - started, 1)
    steps.save()
    log(summary(steps.results))
    shutil.rmtree(work, ignore_errors=True)


def summary(results: dict) -> str:
    """Returns the figures the docs need, as lines of text."""
    lines = [f"GPU: {results.get('gpu')}"]
    choice = results.get("choice", {})
    lines.append(f"automatic variant: {choice.get('auto_variant')} {choice.get('cuda_problem') or ''}")
    compared = results.get("compare")
    if compared:
        lines.append(
            f"{compared['variant']} vs {compared['llvm_variant']}, {compared['materials']} materials at "
            f"{compared['resolution']} px: RMSE other seeds / LLVM's own seeds = "
            f"{compared['cross_over_llvm_seeds_16']:.3f} (16 spp), {compared['cross_over_llvm_seeds_256']:.3f} "
            f"(256 spp; worst {compared['worst_material_256']} {compared['worst_cross_over_llvm_seeds_256']:.2f}); "
            f"largest mean difference {compared['max_mean_difference_percent']:.2f}% (LLVM seed to seed "
            f"{compared['max_llvm_seed_mean_difference_percent']:.2f}%); mixable: {compared['mixable']}"
        )
    for label, run in (results.get("fit") or {}).items():
        if isinstance(run, dict):
            lines.append(
                f"fit {label}: {run.get('process_seconds')} s process, wall_time_s {run.get('wall_time_s')}, "
                f"verification {run.get('verification_seconds')} s, variant {run.get('mitsuba_variant')}"
            )
    for timing in results.get("dataset") or []:
        lines.append(
            f"render-dataset {timing['resolution']} px {timing['spp']} spp, {timing['workers']} processes"
            f"{' (warm-up)' if 'warm_up' in timing else ''}: "
            f"{timing.get('images_per_second_steady')} img/s steady, {timing.get('images_per_second_command')} img/s "
            f"whole command ({timing.get('command_seconds')} s for {timing['images']}) {timing.get('error') or ''}"
        )
    lines.append(f"best workers: {results.get('best_workers')}")
    lines.append(f"errors: {results['errors']}; skipped: {results['skipped']}; {results.get('elapsed_s')} s")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("prepare")
    measuring = commands.add_parser("measure")
    measuring.add_argument("out")
    measuring.add_argument("--rehearse", action="store_true")
    measuring.add_argument("--budget", type=float, default=BUDGET_S)
    measuring.add_argument("--only", default=",".join(STEPS), help="steps to run, comma-separated")
    comparing = commands.add_parser("compare")
    comparing.add_argument("result")
    comparing.add_argument("--variant")
    comparing.add_argument("--count", type=int)
    arguments = parser.parse_args()
    if arguments.command == "prepare":
        prepare()
    elif arguments.command == "measure":
        measure(arguments.out, arguments.rehearse, arguments.budget, arguments.only.split(","))
    else:
        compare(arguments.result, arguments.variant, arguments.count)


if __name__ == "__main__":
    main()
