"""Progress of long work (rendering, training, sequences): a rich bar on a terminal, plain lines otherwise."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rich.progress import TaskID


class Progress:
    """Shows how far a task is: a bar on a terminal, a line every 10% when standard error is a file or pipe.

    `start(label, total)` begins a task (a new bar, or a new series of lines); `update(done, stats)`
    moves it; `note(line)` prints a line that stays (an epoch's figures). Use as a context manager so
    the bar is stopped, leaving its last state on screen, whatever ends the work.
    """

    def __init__(self, label: str = "", total: int = 0):
        self.bar = None
        self.task: TaskID | None = None
        self.label, self.total, self.next_report = label, total, 0.0
        if sys.stderr.isatty():
            from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn
            from rich.progress import Progress as RichProgress

            self.bar = RichProgress(
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[stats]}"),
                TimeRemainingColumn(),
            )
            self.bar.start()
        if total:
            self.start(label, total)

    def start(self, label: str, total: int, done: int = 0) -> None:
        """Begins a task of `total` steps."""
        self.label, self.total, self.next_report = label, total, 0.0
        if self.bar is not None:
            self.task = self.bar.add_task(label, total=total, completed=done, stats="")

    def update(self, done: int, stats: str = "") -> None:
        """Moves the current task to `done` steps; `stats` is a short text such as a rate."""
        if self.bar is not None:
            if self.task is None:
                self.start(self.label, self.total, done)
            assert self.task is not None  # start made it, the bar being there
            self.bar.update(self.task, completed=done, stats=stats)
        elif self.total and (done / self.total >= self.next_report or done == self.total):
            print(
                f"{self.label}: {done}/{self.total} ({100 * done / self.total:.0f}%) {stats}".rstrip(), file=sys.stderr
            )
            self.next_report = min(1.0, done / self.total + 0.1)

    def note(self, line: str) -> None:
        """Shows a line that stays: replaces the bar's label on a terminal, printed otherwise."""
        if self.bar is not None and self.task is not None:
            self.bar.update(self.task, description=line, stats="")
        else:
            print(line, file=sys.stderr)

    def close(self) -> None:
        """Stops the bar, leaving its last state on screen."""
        if self.bar is not None:
            self.bar.stop()
            self.bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exception) -> None:
        self.close()

    def counter(self, unit: str = "img/s"):
        """Returns a callback `(done, total, rate)` for work that reports a count and a rate (rendering, frames)."""

        def report(done: int, total: int, rate: float) -> None:
            if total != self.total:
                self.start(self.label, total, done)
            rate_text = f"{rate:.1f} {unit}" if rate > 0 else ""
            eta = f", {(total - done) / rate:.0f} s left" if rate > 0 and self.bar is None else ""
            self.update(done, rate_text + eta)

        return report

    def steps(self) -> Callable[[str, int, int, float], None]:
        """Returns a callback `(stage, step, steps, loss)` for an optimisation that reports each step's loss; a step
        under the last one heard begins the count again (the next of several fits)."""

        began, last = time.perf_counter(), 0

        def report(stage: str, step: int, steps: int, loss: float) -> None:
            nonlocal began, last
            if step < last:
                began = time.perf_counter()
            if steps != self.total or step < last:
                self.start(self.label, steps, step)
            last = step
            elapsed = time.perf_counter() - began
            left = f", {elapsed / step * (steps - step):.0f} s left" if self.bar is None and 0 < step < steps else ""
            self.update(step, f"{stage}, RMSE {loss:.2f}{left}")

        return report


class TrainingProgress(Progress):
    """Shows training (the `train.Reporter` protocol): a bar per epoch with loss and throughput, a line per epoch."""

    def start_epoch(self, name: str, epoch: int, epochs: int, steps: int) -> None:
        """Called before each epoch."""
        self.start(f"{name} epoch {epoch}/{epochs}", steps)
        self.next_report = 2.0  # no 10% lines inside an epoch when not on a terminal: one line per epoch

    def step(self, step: int, loss: float, samples_per_second: float) -> None:
        """Called after training steps."""
        self.update(step, f"loss {loss:.5f}  {samples_per_second:.0f} samples/s")

    def rendering(self, done: int, total: int) -> None:
        """Called after each render of one of the decoder's bases (clear glass, scattering)."""
        if done == 1:
            self.start("rendering a basis of the decoder", total)
        self.update(done, "")

    def end_epoch(self, record: dict) -> None:
        """Called after each epoch with its history record."""
        figures = "  ".join(f"{key} {value:.5g}" for key, value in record.items() if key not in ("epoch", "seconds"))
        self.note(f"{self.label}: {figures}  ({record['seconds']:.1f} s)")
