"""The attack suite of ``securegs_warp.attacks`` on an explicit-Gaussian release (plain 3DGS, 3DGS +
StegaNeRF, GS-Hider's feature PLY), with the same syntax and the same primitives.

Counterparts: ``prune-random:F`` and ``prune-opacity:F`` remove Gaussians (the lowest opacities
first) instead of anchors; ``noise-xyz:S`` perturbs the means; ``noise-feat:S`` the colour
coefficients (``features_dc`` and ``features_rest``, what an explicit Gaussian has in place of an
anchor feature); ``sor:K:STD`` removes outlying means; ``quantize:B`` and ``half`` act on every
stored attribute; ``export-roundtrip`` writes the release as its PLY and reads it back (the release
already is that PLY: only the quaternions' normalisation changes). ``noise-offset``, ``purify`` and
``finetune`` are anchor- or Scaffold-GS-specific: reported as not applicable, the model unchanged.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import torch

from ..attacks import Attack, column_noise, lowest_mask, quantize_columns, random_prune_mask, sor_mask
from .model import GAUSSIAN_PARAM_NAMES, GaussianModel

NOT_APPLICABLE = {
    "noise-offset": "explicit Gaussians have no anchor offsets",
    "purify": "purify scores anchors by their decoded Gaussians; an explicit release has no anchors",
    "finetune": "finetune trains a Scaffold-GS release with its heads; not implemented for explicit Gaussians",
}


def _prune(model: GaussianModel, mask: torch.Tensor) -> None:
    if bool(mask.all()):
        raise ValueError("the attack would remove every Gaussian")
    model.keep_rows(~mask)


@torch.no_grad()
def attack_gaussians(model: GaussianModel, attack: Attack, generator: torch.Generator) -> dict:
    """Apply one attack to ``model`` in place; returns its report (attack, gaussians before and
    after, ``applicable`` and, when it is not, ``reason``)."""
    before = model.num_gaussians
    report = {"attack": attack.text, "gaussians_before": before, "applicable": True}
    name, args = attack.name, attack.args
    if name == "prune-random":
        _prune(model, random_prune_mask(before, args[0], generator, model.device))
    elif name == "prune-opacity":
        _prune(model, lowest_mask(torch.sigmoid(model.opacity_logits), args[0]))
    elif name == "noise-xyz":
        model.means.add_(column_noise(model.means, args[0], generator))
    elif name == "noise-feat":
        for attribute in ("features_dc", "features_rest"):
            values = getattr(model, attribute)
            values.add_(column_noise(values, args[0], generator))
    elif name == "sor":
        _prune(model, sor_mask(model.means, *args))
    elif name in ("quantize", "half"):
        for attribute in GAUSSIAN_PARAM_NAMES:
            values = getattr(model, attribute)
            if values.numel():
                values.copy_(quantize_columns(values, args[0]) if name == "quantize" else values.half().float())
    elif name == "export-roundtrip":
        with tempfile.TemporaryDirectory() as d:
            model.save_ply(Path(d) / "release.ply")
            read = GaussianModel.load(Path(d) / "release.ply", device=model.device, sh=model.sh_degree is not None)
        for attribute in GAUSSIAN_PARAM_NAMES:
            getattr(model, attribute).copy_(getattr(read, attribute))
    else:
        report.update(applicable=False, reason=NOT_APPLICABLE[name])
    report["gaussians_after"] = model.num_gaussians
    return report
