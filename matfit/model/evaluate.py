"""How good a trained model is, measured against clean references, and its model card.

`evaluate(model, references)` takes a model directory's networks and a reference dataset (held-out
parameter vectors rendered clean, e.g. `matfit render-dataset ref --spp 2048 --seed 1`) and
returns:

- decoder fidelity: per-image RMSE (0-255 sRGB) between phi(x) and the reference render of x,
  over every reference and, separately, over each `SUBSETS` third: a mean over all of them
  cannot hide a failing third (transmissive materials were 4.5 where opaque ones were 2.5);
- the decoder on every preset against a clean render of it (`PRESET_SPP`), rendered once and
  kept beside the references (`PRESET_FILE`);
- for each encoder i: the parameter RMSE of phi^-1_i(t) on the unit cube, and the image RMSE of
  phi(phi^-1_i(t)) against t;
- best-of-n: per target the encoder whose decoded guess is closest to t (what `matfit fit` starts
  from), its mean image RMSE, and how often each encoder wins.
"""

from __future__ import annotations

import os

import numpy as np

from matfit import documents, files, images, params
from matfit.errors import DatasetError
from matfit.model import architectures, models, pipeline, weight_files
from matfit.model.dataset import Dataset
from matfit.rendering import presets

PRESET_SPP = 4096
PRESET_FILE = "presets.npz"
# What the targets ask of the decoder (0-255 sRGB RMSE against clean renders).
TARGETS = {
    "preset": 4.0,
    "transmissive_presets_mean": 3.0,
    "opaque_presets": 2.8,
    "mean": 2.5,
    "transmissive_mean": 3.0,
    "p95": 5.0,
}


def subsets(values: np.ndarray) -> dict[str, np.ndarray]:
    """Returns boolean masks over physical parameter vectors (N, 19) of each third of the parameter space.

    transmissive: spec_trans >= 0.5 (the sphere is seen through); scattering: transmissive with
    scattering >= 0.5 and density >= 1 (jade, milk, wax); opaque: the rest (spec_trans < 0.5).
    """
    values = np.asarray(values).reshape(-1, params.COUNT)
    transmissive = values[:, params.INDEX["spec_trans"]] >= 0.5
    scattering = (
        transmissive & (values[:, params.INDEX["scattering"]] >= 0.5) & (values[:, params.INDEX["density"]] >= 1.0)
    )
    return {"transmissive": transmissive, "scattering": scattering, "opaque": ~transmissive}


def preset_references(references: Dataset, spp: int = PRESET_SPP) -> dict[str, np.ndarray]:
    """Returns clean linear renders (R, R, 3) of every preset at the references' resolution and variant.

    Rendered once (Mitsuba, `spp` samples, seed i for preset i) and kept in the references'
    directory as `PRESET_FILE`; rendered again when the presets, the spp or the resolution changed.
    """
    path = os.path.join(references.path, PRESET_FILE)
    names = list(presets.PRESETS)
    if os.path.isfile(path):
        with np.load(path) as stored:
            if (
                list(stored["names"]) == names
                and int(stored["spp"]) == spp
                and stored["images"].shape[1] == references.resolution
            ):
                return dict(zip(names, stored["images"].astype(np.float32), strict=True))
    from matfit.rendering.engine import Renderer

    renderer = Renderer(references.resolution, spp, references.meta.get("variant"))
    rendered = np.stack([renderer.render(presets.preset(name), seed=i) for i, name in enumerate(names)])
    with files.atomic_path(path) as temporary, open(temporary, "wb") as file:
        np.savez(file, names=np.array(names), spp=np.array(spp), images=rendered)
    return dict(zip(names, rendered, strict=True))


def summary(values: np.ndarray) -> dict:
    """Returns mean, median and 95th percentile of a set of per-image figures."""
    return {"mean": float(np.mean(values)), "median": float(np.median(values)), "p95": float(np.percentile(values, 95))}


def evaluate(model: models.Model, references: Dataset, preset_spp: int = PRESET_SPP) -> dict:
    """Returns the decoder's fidelity (all, each third, each preset), each encoder's errors, the best-of-n figures."""
    pipeline.check_finished(references)
    if references.resolution != model.resolution:
        raise DatasetError(
            f"{references.path} has {references.resolution} px images, the model's decoder makes {model.resolution} "
            f"px: render references at {model.resolution} px"
        )
    unit = references.unit_params()
    targets = pipeline.srgb_targets(references).astype(np.float32)
    masks = subsets(references.params)
    decoder_error = images.rmse(model.decode(unit), targets)
    result = {
        "references": {
            "path": references.path,
            "count": references.count,
            "spp": int(references.meta["spp"]),
            "integrator": references.meta.get("integrator"),
            **{f"{name}_count": int(mask.sum()) for name, mask in masks.items()},
        },
        "decoder_rmse": summary(decoder_error),
        **{
            f"decoder_rmse_{name}": summary(decoder_error[mask]) if mask.any() else None for name, mask in masks.items()
        },
        "presets": preset_figures(model, references, preset_spp),
    }
    return {**result, **encoder_figures(model, references, unit, targets)}


def preset_figures(model: models.Model, references: Dataset, preset_spp: int) -> dict:
    """Returns the decoder's RMSE on each named material against its clean render, their means per third, the
    largest."""
    clean = preset_references(references, preset_spp)
    preset_values = np.stack([presets.preset(name) for name in clean])
    preset_error = images.rmse(
        model.decode(params.to_unit(preset_values).astype(np.float32)),
        images.srgb_encode(np.stack(list(clean.values()))),
    )
    preset_masks = subsets(preset_values)
    return {
        "spp": preset_spp,
        "rmse": {name: float(error) for name, error in zip(clean, preset_error, strict=True)},
        **{
            f"{name}_mean": float(preset_error[mask].mean()) if mask.any() else None
            for name, mask in preset_masks.items()
        },
        "max": float(preset_error.max()),
    }


def encoder_figures(model: models.Model, references: Dataset, unit: np.ndarray, targets: np.ndarray) -> dict:
    """Returns {"encoders": each encoder's parameter and image RMSE, "best_of_n": the figures of keeping, per
    reference, the encoder whose guess the decoder draws closest}."""
    encoder_inputs = pipeline.encoder_inputs(references)
    encoders, image_errors = {}, []
    for arch, network in model.encoders.items():
        guess = models.apply_in_batches(network.module, network.variables, encoder_inputs)
        error = images.rmse(model.decode(guess), targets)
        image_errors.append(error)
        encoders[str(arch)] = {
            "parameter_rmse": float(np.sqrt(np.mean((guess - unit) ** 2))),
            "image_rmse": float(error.mean()),
        }
    errors = np.stack(image_errors)  # (encoders, N)
    best_single = min(encoders.values(), key=lambda entry: entry["image_rmse"])
    winners = np.argmin(errors, axis=0)
    archs = list(model.encoders)
    best_of_n = {
        "n": len(archs),
        "image_rmse": float(errors.min(axis=0).mean()),
        "best_single_image_rmse": best_single["image_rmse"],
        "wins": {str(arch): int(np.sum(winners == k)) for k, arch in enumerate(archs)},
    }
    return {"encoders": encoders, "best_of_n": best_of_n}


def describe_decoder(description: dict) -> str:
    """Returns a sentence saying how the decoder draws: its layers and the Mitsuba bases of its glass and media."""
    stages = ", ".join(str(channels) for channels in description.get("stage_channels", []))
    sentence = (
        f"Decoder: two dense layers of {description.get('hidden')} to a 4 x 4 x {description.get('base_channels')} "
        f"map, upsampling stages of {stages} filters, a sub-pixel output convolution and a learned background"
    )
    grid = description.get("glass_grid") or []
    if grid:
        sentence += (
            f"; it draws refraction from a {grid[0]} x {grid[1]} basis of clear-glass Mitsuba renders (specular x "
            "roughness), tinted per pixel by a predicted transmittance"
        )
    if description.get("absorption"):
        sentence += (
            "; the transmittance of its medium is Beer-Lambert's, exp(-L tau) per colour, tau known from the "
            "parameters, L a predicted path length per pixel"
        )
    if description.get("coarse_absorption"):
        sentence += (
            "; each colour's transmittance is dimmed by its medium's extinction along a predicted path length "
            "per 2 x 2 pixels (Beer-Lambert)"
        )
    grid = description.get("medium_grid") or []
    if grid:
        sentence += (
            f"; it draws the light media scatter from a {grid[0]} x {grid[1]} basis of grey-medium Mitsuba renders "
            "(optical thickness x albedo, read per colour channel), weighted per pixel"
        )
    if description.get("medium_inputs"):
        sentence += "; its dense layers also see 10 physical features of the medium"
    return sentence + "."


def training_sets(metrics: dict) -> list[dict]:
    """Returns the identities of the datasets a network trained on (one, or a list of them)."""
    datasets = metrics.get("dataset", {})
    return datasets if isinstance(datasets, list) else [datasets]


def describe_training(decoder: dict) -> str:
    """Returns the model card's sentence on what the decoder (and the encoders) trained on, from its metrics."""
    datasets = training_sets(decoder)
    data = datasets[0]
    sentence = (
        f"Trained on {data.get('count', '?')} Mitsuba renders ({data.get('resolution', '?')} px, "
        f"{data.get('spp', '?')} spp, {data.get('variant', '?')}, sampling seed {data.get('seed', '?')})"
    )
    extras = [
        f"{extra.get('count', '?')} drawn by the {extra.get('sampler', '?')} sampler (seed {extra.get('seed', '?')})"
        for extra in datasets[1:]
    ]
    if extras:
        listed = extras[0] if len(extras) == 1 else ", ".join(extras[:-1]) + " and " + extras[-1]
        sentence += f", the decoder also on {listed}, the encoders on the first set alone"
    config = decoder.get("config", {})
    fraction = config.get("validation_fraction", 0.05)
    held_out = decoder.get("validation_samples", "?")
    sentence += f"; the last {100 * fraction:.0f}% of each set ({held_out} renders) were held out for validation."
    if config.get("start_from"):
        start = decoder.get("start_sha256") or "?"
        sentence += (
            f" The decoder's last {decoder.get('epochs', '?')} epochs started from trained weights (SHA-256 "
            f"{start[:12]}...) at a peak learning rate of {config.get('learning_rate', '?')}."
        )
    if config.get("loss") == "linear":
        sentence += (
            " The decoder learned the encoding of the mean linear render (`--loss linear`), not the mean of the "
            "encoded noisy renders, which is darker."
        )
    return sentence


def card(model: models.Model, evaluation: dict) -> str:
    """Returns the model card (Markdown) from the networks' training metrics and an evaluation."""
    decoder = model.decoder.info.get("metrics", {})
    data = training_sets(decoder)[0]
    lines = [
        "# matfit model card",
        "",
        f"{describe_training(decoder)} Weights are stored as float16 ({weights_megabytes(model.path):.1f} MB for "
        "all networks).",
        "",
        describe_decoder(model.decoder.description),
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
            f"| {network.name} | {metrics.get('parameter_count', 0):,} | {metrics.get('epochs', '?')} | "
            f"{config.get('batch_size', '?')} | {metrics.get('wall_time_s', 0) / 60:.1f} min | {figure} |"
        )
    total = sum(
        network.info.get("metrics", {}).get("wall_time_s", 0) for network in [model.decoder, *model.encoders.values()]
    )
    lines += ["", f"Training all {1 + len(model.encoders)} networks took {total / 60:.0f} min on this machine's CPU."]
    lines += decoder_tables(evaluation)
    lines += [
        "",
        "| encoder | parameter RMSE (unit cube) | image RMSE of phi(encoder(t)) vs t | wins in best-of-n |",
        "|---|---|---|---|",
    ]
    best = evaluation["best_of_n"]
    for arch, entry in evaluation["encoders"].items():
        lines.append(f"| {arch} | {entry['parameter_rmse']:.4f} | {entry['image_rmse']:.2f} | {best['wins'][arch]} |")
    lines += [
        f"| best-of-{best['n']} | | {best['image_rmse']:.2f} | |",
        "",
        f"Best-of-{best['n']} image RMSE {best['image_rmse']:.2f} against {best['best_single_image_rmse']:.2f} for the "
        "best single encoder.",
        "",
    ]
    return "\n".join(lines)


def decoder_tables(evaluation: dict) -> list[str]:
    """Returns the model card's decoder section: every preset, then every third of the references, against targets."""
    references, preset_figures = evaluation["references"], evaluation["presets"]
    preset_thirds = subsets(np.stack([presets.preset(name) for name in preset_figures["rmse"]]))
    lines = [
        "",
        "## The decoder against clean renders",
        "",
        f"RMSE on 0-255 sRGB values per image. Presets against a {preset_figures['spp']}-spp render each; "
        "transmissive: spec_trans >= 0.5,",
        "scattering: transmissive with scattering >= 0.5 and density >= 1, opaque: the rest.",
        "",
        "| preset | third | decoder phi(x) vs Mitsuba | target |",
        "|---|---|---|---|",
    ]
    for k, (name, error) in enumerate(preset_figures["rmse"].items()):
        third = (
            "scattering"
            if preset_thirds["scattering"][k]
            else "transmissive"
            if preset_thirds["transmissive"][k]
            else "opaque"
        )
        lines.append(f"| {name} | {third} | {error:.2f} | <= {TARGETS['preset']:.1f} |")
    if preset_figures.get("transmissive_mean") is not None:
        lines.append(
            f"| transmissive presets, mean | | {preset_figures['transmissive_mean']:.2f} | <= "
            f"{TARGETS['transmissive_presets_mean']:.1f} |"
        )
    opaque = [error for k, error in enumerate(preset_figures["rmse"].values()) if preset_thirds["opaque"][k]]
    if opaque:
        lines.append(f"| opaque presets, worst | | {max(opaque):.2f} | <= {TARGETS['opaque_presets']:.1f} |")
    spp = references["spp"]
    lines += [
        "",
        f"Against {references['count']} held-out random materials rendered at {spp} spp "
        f"({references.get('integrator') or 'volpath'}); their own",
        f"noise is part of every figure (about {2.3 * (256 / spp) ** 0.5:.1f} on opaque materials at this spp, more "
        "in media:",
        "docs/method.md#the-renderers-noise).",
        "",
        "| references | count | mean | median | p95 | target |",
        "|---|---|---|---|---|---|",
    ]
    targets = {
        "all": f"mean <= {TARGETS['mean']:.1f}, p95 <= {TARGETS['p95']:.1f}",
        "transmissive": f"mean <= {TARGETS['transmissive_mean']:.1f}",
    }
    for name in ("all", "transmissive", "scattering", "opaque"):
        figures = evaluation.get("decoder_rmse" if name == "all" else f"decoder_rmse_{name}")
        if figures:
            count = references["count"] if name == "all" else references[f"{name}_count"]
            lines.append(
                f"| {name} | {count} | {figures['mean']:.2f} | {figures['median']:.2f} | {figures['p95']:.2f} | "
                f"{targets.get(name, '')} |"
            )
    return lines


def weights_megabytes(directory: str) -> float:
    """Returns the size of the weight files in a model directory, in MB (10^6 bytes)."""
    return (
        sum(
            os.path.getsize(weight_files.weights_path(directory, name))
            for name in architectures.NETWORKS
            if os.path.exists(weight_files.weights_path(directory, name))
        )
        / 1e6
    )


def write_report(model: models.Model, evaluation: dict) -> tuple[str, str]:
    """Writes evaluation.json and MODEL.md into the model directory; returns their paths."""
    report = os.path.join(model.path, "evaluation.json")
    card_path = os.path.join(model.path, "MODEL.md")
    files.write_text(report, documents.dumps(evaluation))
    files.write_text(card_path, card(model, evaluation))
    return report, card_path
