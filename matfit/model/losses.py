"""What training minimises and how it is judged: the decoder's and the encoders' L2 losses (`image_loss`,
`linear_residual`) and the validation figures of a network (`validation_metrics`).

The decoder learns parameters -> sRGB image (L2 on sRGB values, as the paper's RMSE), or with the
"linear" loss the sRGB encoding of the mean linear render (`linear_residual`: the 16-spp
targets' noise no longer darkens what it learns); an encoder learns image -> parameters (L2 on
the unit cube). Pure functions of arrays, compiled inside `train.make_train_step`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from matfit import images, params
from matfit.model import architectures, layers

# What the decoder learns: "srgb" the mean of the sRGB-encoded renders (the paper's L2 on sRGB
# values), "linear" the sRGB encoding of the mean linear render (`linear_residual`).
LOSSES = ("srgb", "linear")


# The linear loss's per-pixel residual is clipped to this many full sRGB scales: a firefly of a
# 16-spp render (linear values far above 1) would otherwise dominate a batch's gradient (docs/training.md#training).
RESIDUAL_CLIP = 1.0


def linear_residual(prediction: jax.Array, linear: jax.Array) -> jax.Array:
    """Returns the decoder's residual against a linear target, in sRGB units and with no gradient.

    (linear - decode(prediction)) times the sRGB curve's slope at the prediction, clipped to
    +-RESIDUAL_CLIP: to first order the sRGB error, but zero on average where the prediction
    encodes the mean linear render. The plain sRGB loss's optimum is the mean of the encoded
    renders instead, which a 16-spp render's noise darkens (the curve is concave and clips at 1):
    most inside media (docs/training.md#training). The slope is
    the prediction's, not the target's, so that the noise does not bias it either.
    """
    prediction = jax.lax.stop_gradient(prediction)
    decoded = layers.srgb_decode(prediction)
    # The curve's own slope, not its clip's: a prediction at 1 is still pulled down.
    return jnp.clip(layers.srgb_slope(decoded) * (linear - decoded), -RESIDUAL_CLIP, RESIDUAL_CLIP)


def image_loss(prediction: jax.Array, target: jax.Array, loss: str = "srgb") -> jax.Array:
    """Returns the L2 loss of predictions against targets; "linear": of decoded images against linear renders.

    "linear"'s value is the mean square of `linear_residual`, its gradient -2 residual / n: an L2
    loss on a target that lies `residual` away from the prediction.
    """
    if loss == "linear":
        residual = linear_residual(prediction, target)
        return jnp.mean((prediction - jax.lax.stop_gradient(prediction + residual)) ** 2)
    return jnp.mean((prediction - target) ** 2)


def validation_metrics(name: str, predictions: np.ndarray, targets: np.ndarray, inputs: np.ndarray) -> dict:
    """Returns the validation figures of a network: image RMSE (0-255 sRGB) or parameter RMSE.

    The decoder's are also given for its transmissive samples alone (spec_trans >= 0.5, `inputs`
    being its unit-cube parameters), so that the third of the space with glass and media is seen.
    """
    targets = np.asarray(targets, np.float64)
    error = predictions.astype(np.float64) - targets
    if name == architectures.DECODER:
        per_image = images.rmse(predictions.astype(np.float64), targets)
        transmissive = np.asarray(inputs)[:, params.INDEX["spec_trans"]] >= 0.5
        return {
            "validation_loss": float(np.mean(error**2)),
            "validation_rmse": float(per_image.mean()),
            "validation_rmse_transmissive": float(per_image[transmissive].mean()) if transmissive.any() else 0.0,
        }
    per_parameter = np.sqrt(np.mean(error**2, axis=0))
    return {
        "validation_loss": float(np.mean(error**2)),
        "validation_parameter_rmse": float(np.sqrt(np.mean(error**2))),
        "validation_parameter_rmse_by_name": dict(zip(params.NAMES, map(float, per_parameter), strict=True)),
    }
