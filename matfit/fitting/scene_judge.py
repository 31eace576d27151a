"""The judge of a fit in a scene: a material's renders at `JUDGE_SPP` with the seeds `JUDGE_SEED` and
`SECOND_SEED`, which no step uses, and the unbiased estimate of its noise-free error from the two
(`images.noise_free_mse`, as the test scene's verification judges): a render's own RMSE counts its noise, and the
material that renders with less noise would read closer. `scene_fit` chooses between starts, between a descent's
points, off the bounds, between lobes on and off, and accepts its answer by it (docs/scenes.md#the-judge).
"""

from __future__ import annotations

import numpy as np

from matfit import images
from matfit.rendering import scene_file

JUDGE_SPP = 128  # the renders that choose between starts and accept the answer
JUDGE_SEED = 4_000_037  # their common seed: no step uses it (steps use refine.SEED + k)
SECOND_SEED = 5_000_011  # the off-the-bounds stage's second opinion: a move chosen at one seed must hold at another


class Judge:
    """The judge of one fit: a material's sRGB render (`JUDGE_SPP`, a seed), made once however many stages ask for
    it, and its noise-free error over the weights from two such renders (`squared`; `scene_fit` judges the
    descent's answer by `closest`, `off_bounds`, `plain` and the acceptance, at the same seeds).

    Every choice is made on `squared`, not on a render's RMSE: a render's RMSE counts its own noise, and a material
    that renders with less noise reads closer. Under the sun the bench's jade knot ended at roughness 0.02 against
    the truth's 0.15, whose sharper highlight renders with less noise: at two seeds the RMSE read 23.5 for it
    against 31.1 with the truth's roughness, the noise-free estimate 476 against 297 (squared)."""

    def __init__(
        self,
        renderer: scene_file.Renderer,
        target: np.ndarray,
        weights: np.ndarray,
        made: dict[tuple[bytes, int], np.ndarray] | None = None,
    ) -> None:
        self.renderer, self.target, self.weights = renderer, target, weights
        self.made: dict[tuple[bytes, int], np.ndarray] = {} if made is None else made

    def render(self, values: np.ndarray, seed: int = JUDGE_SEED) -> np.ndarray:
        """Returns the sRGB render of physical `values` at `seed` (`JUDGE_SPP`), made once."""
        key = (np.asarray(values, np.float64).tobytes(), seed)
        if key not in self.made:
            self.made[key] = images.srgb_encode(self.renderer.render(values, seed=seed, spp=JUDGE_SPP))
        return self.made[key]

    def weighted(self, weights: np.ndarray) -> Judge:
        """Returns the judge with other weights, sharing the renders made."""
        return Judge(self.renderer, self.target, weights, self.made)

    def squared(self, values: np.ndarray) -> float:
        """Returns the estimate of the squared noise-free error (0-255 squared, negative where under what two
        renders resolve) of physical `values` from its renders at `JUDGE_SEED` and `SECOND_SEED`
        (`images.noise_free_mse`)."""
        return 255.0**2 * images.noise_free_mse(self.renders(values), self.target, self.weights)

    def renders(self, values: np.ndarray) -> np.ndarray:
        """Returns the two sRGB renders (2, h, w, 3) of physical `values` that `squared` judges by."""
        return np.asarray([self.render(values, seed) for seed in (JUDGE_SEED, SECOND_SEED)])

    def behind(self, values: np.ndarray, other: np.ndarray) -> tuple[float, float]:
        """Returns (how much further physical `values` is than `other`, its standard error): the difference of
        their `squared` (0-255 squared, negative where `values` is closer) and its spread over the pixels
        (`images.noise_free_difference`; the two are rendered at the same seeds)."""
        difference, error = images.noise_free_difference(
            self.renders(values), self.renders(other), self.target, self.weights
        )
        return 255.0**2 * difference, 255.0**2 * error


def root(squared: float) -> float:
    """Returns a squared error estimate's root, 0-255: 0 where the estimate is below 0."""
    return float(np.sqrt(max(0.0, squared)))
