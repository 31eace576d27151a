"""Two versions of matfit timed by turns: the same picture fitted warm by each, one fit at a time, the order
alternating (docs/decisions.md#speed-the-edit-comes-back-at-once).

Each version runs in a process of its own with a warm `matfit.Fitter` (the model loaded, the render processes
running), its code taken from a folder put first on PYTHONPATH (a git worktree; a second folder after a colon, such
as an older `ml_dtypes`, goes with it). A pair of fits lies seconds apart, so the machine's drift between hours
touches both alike; the median of the pairs' ratios is printed with each fit's seconds and the first answer's.

    git worktree add /tmp/old fd0efe7
    python scripts/speed_turns.py matfit/data/examples/recoloured.png --old /tmp/old --new . --pairs 8

Time only on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

SERVE = """
import json, sys, time
import matfit
with matfit.Fitter() as fitter:
    print("ready", flush=True)
    for line in sys.stdin:
        if not line.strip():
            break
        marks = []
        started = time.perf_counter()
        try:
            fitter.fit(line.strip(), answers=lambda answer: marks.append(time.perf_counter() - started))
        except TypeError:  # a version without answers=
            fitter.fit(line.strip())
        print(json.dumps({"seconds": time.perf_counter() - started, "first": marks[0] if marks else None}), flush=True)
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("picture")
    parser.add_argument("--old", required=True, help="the old code's folder (PYTHONPATH), e.g. a git worktree")
    parser.add_argument("--new", required=True, help="the new code's folder (PYTHONPATH)")
    parser.add_argument("--pairs", type=int, default=8)
    arguments = parser.parse_args()
    picture = os.path.abspath(arguments.picture)
    folder = tempfile.mkdtemp(prefix="matfit-turns-")  # run outside either checkout, so PYTHONPATH decides
    processes = {}
    for name in ("old", "new"):
        paths = ":".join(os.path.abspath(path) for path in getattr(arguments, name).split(":"))
        process = subprocess.Popen(
            [sys.executable, "-c", SERVE],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONPATH": paths},
            cwd=folder,
        )
        assert process.stdout is not None and process.stdout.readline().strip() == "ready"
        processes[name] = process

    def fit(name: str) -> dict:
        process = processes[name]
        assert process.stdin is not None and process.stdout is not None
        process.stdin.write(picture + "\n")
        process.stdin.flush()
        return json.loads(process.stdout.readline())

    for name in processes:  # not timed: the first fits load and compile
        fit(name)
        fit(name)
    seconds: dict[str, list[float]] = {"old": [], "new": []}
    firsts: dict[str, list[float]] = {"old": [], "new": []}
    for pair in range(arguments.pairs):
        for name in ("old", "new") if pair % 2 == 0 else ("new", "old"):
            figures = fit(name)
            seconds[name].append(figures["seconds"])
            if figures["first"] is not None:
                firsts[name].append(figures["first"])
    ratios = [new / old for old, new in zip(seconds["old"], seconds["new"], strict=True)]
    for name, process in processes.items():
        assert process.stdin is not None
        process.stdin.write("\n")
        process.stdin.flush()
        process.wait()
        first = f", first answer {statistics.median(firsts[name]):.3f} s" if firsts[name] else ""
        each = " ".join(f"{value:.2f}" for value in seconds[name])
        print(f"{name}: median {statistics.median(seconds[name]):.3f} s{first}; {each}")
    spread = f"{min(ratios):.2f}-{max(ratios):.2f}"
    print(f"new / old, median of {len(ratios)} pairs: {statistics.median(ratios):.3f} ({spread})")


if __name__ == "__main__":
    main()
