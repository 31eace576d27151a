"""How good a trained model is, measured against clean references, and its model card.

`evaluate(model, references)` takes a model directory's networks and a reference dataset (held-out
parameter vectors rendered at high spp, e.g. `matfit render-dataset ref --spp 256 --seed 1`) and
returns:

- decoder fidelity: per-image RMSE (0-255 sRGB) between phi(x) and the reference render of x,
  averaged over every reference and over the glass/medium subset (spec_trans >= 0.5, where the
  medium is seen) and the opaque rest;
- for each encoder i: the parameter RMSE of phi^-1_i(t) on the unit cube, and the image RMSE of
  phi(phi^-1_i(t)) against t;
- best-of-n: per target the encoder whose decoded guess is closest to t (what `matfit fit` starts
  from), its mean image RMSE, and how often each encoder wins.
"""

from __future__ import annotations

import json
import os

import numpy as np

from matfit import files, images, models, params, pipeline
from matfit.dataset import Dataset
from matfit.errors import DatasetError

GLASS_THRESHOLD = 0.5


def summary(values: np.ndarray) -> dict:
    """Returns mean, median and 95th percentile of a set of per-image figures."""
    return {"mean": float(np.mean(values)), "median": float(np.median(values)), "p95": float(np.percentile(values, 95))}


def evaluate(model: models.Model, references: Dataset) -> dict:
    """Returns the decoder's fidelity, each encoder's errors and the best-of-n figures."""
    pipeline.check_finished(references)
    if references.resolution != model.resolution:
        raise DatasetError(
            f"{references.path} has {references.resolution} px images, the model's decoder makes {model.resolution} px: "
            f"render references at {model.resolution} px"
        )
    unit = references.unit_params()
    targets = pipeline.srgb_targets(references).astype(np.float32)
    glass = references.params[:, params.INDEX["spec_trans"]] >= GLASS_THRESHOLD

    decoder_error = images.rmse(model.decode(unit), targets)
    result = {
        "references": {
            "path": references.path,
            "count": references.count,
            "spp": int(references.meta["spp"]),
            "glass_count": int(glass.sum()),
        },
        "decoder_rmse": summary(decoder_error),
        "decoder_rmse_glass_medium": summary(decoder_error[glass]) if glass.any() else None,
        "decoder_rmse_opaque": summary(decoder_error[~glass]) if (~glass).any() else None,
        "encoders": {},
    }
    encoder_inputs = pipeline.encoder_inputs(references)
    image_errors = []
    for arch, network in model.encoders.items():
        guess = models.apply_in_batches(network.module, network.variables, encoder_inputs)
        error = images.rmse(model.decode(guess), targets)
        image_errors.append(error)
        result["encoders"][str(arch)] = {
            "parameter_rmse": float(np.sqrt(np.mean((guess - unit) ** 2))),
            "image_rmse": float(error.mean()),
        }
    errors = np.stack(image_errors)  # (encoders, N)
    best_single = min(result["encoders"].values(), key=lambda entry: entry["image_rmse"])
    winners = np.argmin(errors, axis=0)
    archs = list(model.encoders)
    result["best_of_n"] = {
        "n": len(archs),
        "image_rmse": float(errors.min(axis=0).mean()),
        "best_single_image_rmse": best_single["image_rmse"],
        "wins": {str(arch): int(np.sum(winners == k)) for k, arch in enumerate(archs)},
    }
    return result


def card(model: models.Model, evaluation: dict) -> str:
    """Returns the model card (Markdown) from the networks' training metrics and an evaluation."""
    decoder = model.decoder.info.get("metrics", {})
    data = decoder.get("dataset", {})
    lines = [
        "# matfit model card",
        "",
        f"Trained on {data.get('count', '?')} Mitsuba renders ({data.get('resolution', '?')} px, {data.get('spp', '?')} spp, "
        f"{data.get('variant', '?')}, sampling seed {data.get('seed', '?')}); the last "
        f"{decoder.get('validation_samples', '?')} were held out for validation. "
        f"Weights are stored as float16 ({weights_megabytes(model.path):.1f} MB for all networks).",
        "",
        "## Training",
        "",
        "| network | weights | epochs | batch | training time | validation |",
        "|---|---|---|---|---|---|",
    ]
    for network in [model.decoder, *model.encoders.values()]:
        metrics = network.info.get("metrics", {})
        if "validation_rmse" in metrics:
            figure = f"image RMSE {metrics['validation_rmse']:.2f} (vs {data.get('spp', '?')}-spp renders)"
        else:
            figure = f"parameter RMSE {metrics.get('validation_parameter_rmse', float('nan')):.4f}"
        config = metrics.get("config", {})
        lines.append(
            f"| {network.name} | {metrics.get('parameter_count', 0):,} | {metrics.get('epochs', '?')} | {config.get('batch_size', '?')} "
            f"| {metrics.get('wall_time_s', 0) / 60:.1f} min | {figure} |"
        )
    total = sum(network.info.get("metrics", {}).get("wall_time_s", 0) for network in [model.decoder, *model.encoders.values()])
    lines += ["", f"Training all {1 + len(model.encoders)} networks took {total / 60:.0f} min on this machine's CPU."]
    references = evaluation["references"]
    lines += [
        "",
        f"## Against {references['count']} held-out references at {references['spp']} spp",
        "",
        "RMSE on 0-255 sRGB values per image; mean, median and 95th percentile over the references. The references",
        "carry Monte Carlo noise of about 2.2 themselves (256 spp), part of every figure below.",
        "",
        "| decoder phi(x) vs Mitsuba | mean | median | p95 |",
        "|---|---|---|---|",
    ]
    for label, key in (
        ("all references", "decoder_rmse"),
        (f"glass/medium subset ({references['glass_count']})", "decoder_rmse_glass_medium"),
        ("opaque rest", "decoder_rmse_opaque"),
    ):
        if evaluation.get(key):
            figures = evaluation[key]
            lines.append(f"| {label} | {figures['mean']:.2f} | {figures['median']:.2f} | {figures['p95']:.2f} |")
    lines += ["", "| encoder | parameter RMSE (unit cube) | image RMSE of phi(encoder(t)) vs t | wins in best-of-n |", "|---|---|---|---|"]
    best = evaluation["best_of_n"]
    for arch, entry in evaluation["encoders"].items():
        lines.append(f"| {arch} | {entry['parameter_rmse']:.4f} | {entry['image_rmse']:.2f} | {best['wins'][arch]} |")
    lines += [
        f"| best-of-{best['n']} | | {best['image_rmse']:.2f} | |",
        "",
        f"Best-of-{best['n']} image RMSE {best['image_rmse']:.2f} against {best['best_single_image_rmse']:.2f} for the best single encoder.",
        "",
    ]
    return "\n".join(lines)


def weights_megabytes(directory: str) -> float:
    """Returns the size of the weight files in a model directory, in MB (10^6 bytes)."""
    return (
        sum(
            os.path.getsize(models.weights_path(directory, name))
            for name in models.NETWORKS
            if os.path.exists(models.weights_path(directory, name))
        )
        / 1e6
    )


def write_report(model: models.Model, evaluation: dict) -> tuple[str, str]:
    """Writes evaluation.json and MODEL.md into the model directory; returns their paths."""
    report = os.path.join(model.path, "evaluation.json")
    card_path = os.path.join(model.path, "MODEL.md")
    files.write_text(report, json.dumps(evaluation, indent=2) + "\n")
    files.write_text(card_path, card(model, evaluation))
    return report, card_path
