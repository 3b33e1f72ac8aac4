"""The false-positive experiment behind ``scripts/verify_fpr.py``.

Trains plain Scaffold-GS models and bit containers of the built-in scenes with several seeds, then
tests every container's key against every other model (unmarked: the null is true) and against
its own container, whole and after random pruning (marked). Reports the false- and true-positive
rates with their counts, the cover's PSNR against the plain model of the same scene and seed, and
a histogram of the statistic for marked and unmarked pairs.
"""
from __future__ import annotations

import copy
import dataclasses
import math

import torch

from ..config import SceneSpec, SecureConfig, TrainConfig
from ..model import AnchorModel
from ..rasterizer import RasterOptions
from ..train import ScaffoldTrainer
from .keyed_bits import KeyedBitDecoder
from .trainer import SecureTrainer
from .verification import DEFAULT_ALPHA, verify_message


@dataclasses.dataclass
class StudyModel:
    """One trained model of the study. decoder: its key's bit decoder (None for a plain model)."""

    name: str
    scene: str
    seed: int
    anchors: AnchorModel
    psnr: float
    decoder: KeyedBitDecoder | None = None


def train_model(scene: SceneSpec, seed: int, iterations: int, raster: RasterOptions,
                secure: SecureConfig | None = None) -> StudyModel:
    """A plain model (``secure`` None) or a container of ``scene`` trained with ``seed``; PSNR on
    the scene's held-out views."""
    data = scene.load()
    config = TrainConfig(iterations=iterations, seed=seed, raster=raster)
    trainer = (ScaffoldTrainer(data, config) if secure is None else SecureTrainer(data, config, secure))
    for _ in range(iterations):
        trainer.step()
    psnr = float(trainer.evaluate(timing_repeats=1)["psnr"])
    kind = "plain" if secure is None else "container"
    decoder = None if secure is None else trainer.model.private.bits
    return StudyModel(f"{scene.source}/{kind}/seed{seed}", scene.source, seed, trainer.model.anchors, psnr, decoder)


def random_prune(anchors: AnchorModel, fraction: float, generator: torch.Generator) -> AnchorModel:
    """A copy of ``anchors`` without a random ``fraction`` of them (``AnchorModel.prune_anchors``)."""
    pruned = copy.deepcopy(anchors)
    n = pruned.num_anchors
    mask = torch.zeros(n, dtype=torch.bool)
    mask[torch.randperm(n, generator=generator)[: round(fraction * n)]] = True
    pruned.prune_anchors(mask)
    return pruned


def verification_rows(models: list[StudyModel], prunings: int, fraction: float, alpha: float = DEFAULT_ALPHA,
                      seed: int = 0) -> list[dict]:
    """One row per (key, model) test: every container's key against every other model (marked
    False) and against its own container, whole and in ``prunings`` random prunings of
    ``fraction`` of its anchors (marked True)."""
    generator = torch.Generator().manual_seed(seed)
    rows = []
    for key in (m for m in models if m.decoder is not None):
        tests = [(other.name, other.anchors, False) for other in models if other is not key]
        tests.append((key.name, key.anchors, True))
        tests += [(f"{key.name} pruned {fraction:.0%} #{i}", random_prune(key.anchors, fraction, generator), True)
                  for i in range(prunings)]
        for name, anchors, marked in tests:
            result = verify_message(key.decoder, anchors.feat.detach(), anchors.xyz, alpha)
            rows.append({"key": key.name, "model": name, "marked": marked, **result.to_json()})
    return rows


def summary(rows: list[dict]) -> dict:
    """False-positive rate (present on unmarked pairs) and true-positive rate (present on marked
    ones), with counts and each side's range of p-values."""
    out = {}
    for side, marked in (("unmarked", False), ("marked", True)):
        group = [r for r in rows if r["marked"] is marked]
        positives = sum(r["present"] for r in group)
        out[side] = {"tests": len(group), "present": positives,
                     "rate": positives / len(group) if group else math.nan,
                     "bit_accuracy_min": min((r["bit_accuracy"] for r in group), default=math.nan),
                     "bit_accuracy_max": max((r["bit_accuracy"] for r in group), default=math.nan),
                     "p_value_min": min((r["p_value"] for r in group), default=math.nan),
                     "p_value_max": max((r["p_value"] for r in group), default=math.nan)}
    return out


def plot_histogram(path, rows: list[dict], bits: int) -> None:
    """PNG: bit accuracy of unmarked and marked pairs, with the exact null distribution
    Binomial(bits, 1/2) / bits scaled to the unmarked count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    unmarked = [r["bit_accuracy"] for r in rows if not r["marked"]]
    marked = [r["bit_accuracy"] for r in rows if r["marked"]]
    edges = [(k - 0.5) / bits for k in range(bits + 2)]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    ax.hist(unmarked, bins=edges, color="tab:blue", alpha=0.7, label=f"unmarked pairs ({len(unmarked)})")
    ax.hist(marked, bins=edges, color="tab:red", alpha=0.7, label=f"marked: containers, pruned ({len(marked)})")
    null = [len(unmarked) * math.comb(bits, k) / 2**bits for k in range(bits + 1)]
    ax.plot([k / bits for k in range(bits + 1)], null, "k--", lw=1, label=f"exact null Binomial({bits}, 1/2)")
    ax.set_xlabel(f"bit accuracy ({bits}-bit messages)")
    ax.set_ylabel("tests")
    ax.set_xlim(0, 1.02)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
