"""What a training run is asked for: its settings (`Config`, checked before anything is written), the default
number of epochs of each network, the held-out share, and the networks `--arch` names (`parse_arch`).

Resuming a run needs the same settings: they are part of its checkpoint (`checkpoints`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from matfit.errors import TrainingError
from matfit.model import architectures
from matfit.model.architectures import NETWORKS
from matfit.model.losses import LOSSES

# The paper trains the isomorphic encoders 6, 7 and 9 for different numbers of epochs.
# Sized so that `make model` trains them on a CPU in less time than the decoder (docs/training.md#training).
DEFAULT_EPOCHS = {
    architectures.DECODER: 20,
    **{name: 10 for name in architectures.ENCODER_NAMES},
    "encoder-4": 8,
    "encoder-5": 8,
    "encoder-7": 5,
    "encoder-9": 20,
}


MAX_EPOCHS = 10000


@dataclass(frozen=True)
class Config:
    """What defines a training run: resuming needs the same values."""

    epochs: int | None = None  # None: the network's default (DEFAULT_EPOCHS)
    batch_size: int = 64
    learning_rate: float = 1e-3
    validation_fraction: float = 0.05
    seed: int = 0
    start_from: str | None = None  # a model directory: its weights of the network start the run
    loss: str = "srgb"  # the decoder's: one of LOSSES

    def for_network(self, name: str) -> Config:
        """Returns this configuration with the network's default number of epochs where none is set."""
        return self if self.epochs is not None else replace(self, epochs=DEFAULT_EPOCHS[name])

    def check(self, samples: int) -> None:
        """Raises TrainingError for values that cannot train on `samples` samples."""
        if self.loss not in LOSSES:
            raise TrainingError(f"loss {self.loss!r} is unknown: use {' or '.join(LOSSES)}", field="loss")
        if self.epochs is None or not 1 <= self.epochs <= MAX_EPOCHS:
            raise TrainingError(f"epochs {self.epochs} is out of range: use 1 to {MAX_EPOCHS}", field="epochs")
        if not 0.0 < self.learning_rate <= 1.0:
            raise TrainingError(
                f"learning rate {self.learning_rate} is out of range: use a value in (0, 1]", field="learning_rate"
            )
        if not 0.0 < self.validation_fraction < 0.5:
            raise TrainingError(
                f"validation fraction {self.validation_fraction} is out of range: use a value in (0, 0.5)"
            )
        training = samples - validation_count(samples, self.validation_fraction)
        if not 1 <= self.batch_size <= training:
            raise TrainingError(
                f"batch size {self.batch_size} does not fit {training} training samples: use 1 to {training}",
                field="batch_size",
            )


def validation_count(samples: int, fraction: float) -> int:
    """Returns how many of the last samples are held out for validation (at least one)."""
    return max(1, round(samples * fraction))


def parse_arch(text: str) -> list[str]:
    """Returns the networks named by --arch: "decoder", "N" (1..9), "A..B", "all" or a comma list."""
    names: list[str] = []
    for part in text.split(","):
        part = part.strip().lower()
        if part == "decoder":
            names.append(architectures.DECODER)
        elif part == "all":
            names.extend(NETWORKS)
        elif ".." in part:
            low, high = (_arch_number(end) for end in part.split("..", 1))
            if low > high:
                raise TrainingError(
                    f"arch {part} is an empty range: give it from low to high ({high}..{low})", field="arch"
                )
            names.extend(f"encoder-{arch}" for arch in range(low, high + 1))
        else:
            names.append(f"encoder-{_arch_number(part)}")
    return list(dict.fromkeys(names))


def _arch_number(text: str) -> int:
    try:
        arch = int(text)
    except ValueError:
        raise TrainingError(
            f"arch {text!r} is not an architecture: use decoder, 1 to 9, 1..9 or all", field="arch"
        ) from None
    if arch not in architectures.ENCODERS:
        raise TrainingError(
            f"arch {arch} does not exist: the paper's encoders are 1 to 9 (or use decoder)", field="arch"
        )
    return arch
