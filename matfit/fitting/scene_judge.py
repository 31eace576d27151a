"""The judge of a fit in a scene: a material's renders at `JUDGE_SPP` with the seeds `JUDGE_SEED` and
`SECOND_SEED`, which no step uses, and the unbiased estimate of its noise-free error from the two
(`images.noise_free_mse`, as the test scene's verification judges): a render's own RMSE counts its noise, and the
material that renders with less noise would read closer. `scene_fit` chooses between starts, between a descent's
points, off the bounds, between lobes on and off, and accepts its answer by it (docs/scenes.md#the-judge). Where a
material's renders have heavy-tailed noise, an opaque fit's judge looks past the target's outlying pixels once its
descent has ended (`Judge.robust`).
"""

from __future__ import annotations

import numpy as np

from matfit import images
from matfit.fitting import refine
from matfit.rendering import scene_file

JUDGE_SPP = 128  # the renders that choose between starts and accept the answer
JUDGE_SEED = 4_000_037  # their common seed: no step uses it (steps use refine.SEED + k)
SECOND_SEED = 5_000_011  # the off-the-bounds stage's second opinion: a move chosen at one seed must hold at another
# Tukey's biweight on the target's residual from a reference material's renders (`Judge.robust`): a pixel this many
# robust spreads away weighs nothing, one at half of it 0.56
OUTLIER_SPREADS = 5.0
# ... where the renders' noise is heavy-tailed, its kurtosis over this (a Gaussian's is 3; `Judge.tails`): the
# bench's gold knot under the sun 29-46, the red one 8-24, its other opaque cases 5-7 (docs/scenes.md#the-robust-judge)
HEAVY_TAILED = 15.0


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

    def robust(self, reference: np.ndarray) -> Judge:
        """Returns the judge whose weights also fall with the target's residual from the mean of physical
        `reference`'s two renders, by Tukey's biweight: (1 - (r / c)^2)^2 where r, the residual's largest channel, is
        under c, `OUTLIER_SPREADS` robust spreads (`refine.huber_corner`: 1.4826 times its median over the weighted
        pixels), else 0; where the reference's renders' noise is light-tailed (`tails` up to `HEAVY_TAILED`), the
        judge itself. One set of weights for every material it then judges.

        A target at a few hundred samples can be heavy-tailed: the gold knot under the sun's residual from the truth
        has a kurtosis of 39, its top 1% of pixels 45% of the squares. The squares then measure the target's noise:
        over 43 answers of that case, their error against its target ranked them against their error against the
        truth with a Spearman correlation of 0.13 at this judge's samples (32 read closer than the truth; 0.14 and
        14 at 1024 samples); reweighted so from one of them, 0.81 (9; 0.91 and none at 1024). Where the noise is
        light-tailed the weights cut the pixels a material misfits instead, and the squares judge better
        (docs/scenes.md#the-robust-judge)."""
        if self.tails(reference) <= HEAVY_TAILED:  # the squares are the judge for light tails
            return self
        residual = np.abs(self.residual(reference)).max(axis=2)
        corner = refine.huber_corner(residual[..., None], self.weights, OUTLIER_SPREADS)
        if corner <= 0:  # a target the reference renders exactly over half its pixels: nothing stands out
            return self
        kept = np.square(1.0 - np.square(np.minimum(residual / corner, 1.0)))
        return self.weighted((self.weights * kept).astype(np.float32))

    def residual(self, values: np.ndarray) -> np.ndarray:
        """Returns the target less the mean of physical `values`' two renders (h, w, 3), sRGB."""
        return np.asarray(self.target, np.float64) - self.renders(values).mean(axis=0)

    def tails(self, values: np.ndarray) -> float:
        """Returns the kurtosis of the noise of physical `values`' renders, the difference of its two over the weighted
        pixels (`kurtosis`): 3 where the noise is Gaussian, more where fireflies hold much of it. A target rendered
        by a path tracer of the same scene has noise of the same kind; a target's residual does not tell it, as a
        material's misfit in a few highlights is heavy-tailed too (the bench's red knot under the studio light:
        residual 6.5-12.5, noise 6.0-7.1)."""
        renders = self.renders(values)
        return kurtosis(renders[0] - renders[1], self.weights)

    def darkening(self, values: np.ndarray, spp: int) -> float:
        """Returns how much darker than its mean (0-255 sRGB, over the weights) a render of physical `values` at
        `spp` samples a pixel reads once encoded, from its two judged renders: the sRGB curve is concave, so a noisy
        pixel's encoding is below its mean's by about half the curve's bend times the noise's variance. The two
        renders' encodings less the encoding of their mean (both clipped to [0, 1], as a step's image is) is a
        quarter of that bend times a judged render's variance; a render at `spp` samples has `JUDGE_SPP / spp` times
        that variance, so the figure is scaled by 2 `JUDGE_SPP / spp`."""
        encoded = np.asarray(self.renders(values), np.float64)
        mean = images.srgb_encode(images.srgb_decode(encoded).mean(axis=0)).astype(np.float64)
        darker = (mean - encoded.mean(axis=0)).mean(axis=2)
        weights = np.asarray(self.weights, np.float64)
        share = float((weights * darker).sum() / max(weights.sum(), 1e-12))
        return 255.0 * 2.0 * JUDGE_SPP / spp * share

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


def kurtosis(residual: np.ndarray, weights: np.ndarray) -> float:
    """Returns the weighted kurtosis of a residual (h, w, 3) over its channels, each pixel by `weights` (h, w): 3 for
    Gaussian noise, more where a few pixels hold much of the squares; 0 where it does not vary."""
    w = np.repeat(np.asarray(weights, np.float64)[..., None], 3, axis=2).ravel()
    r = np.asarray(residual, np.float64).ravel()
    if w.sum() <= 0:
        return 0.0
    centred = r - (w * r).sum() / w.sum()
    variance = (w * centred**2).sum() / w.sum()
    return float((w * centred**4).sum() / w.sum() / variance**2) if variance > 0 else 0.0
