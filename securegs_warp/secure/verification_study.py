"""The false-positive experiment behind ``scripts/verify_fpr.py``.

Trains plain Scaffold-GS models and bit containers of the built-in scenes with several seeds, then
tests every container's key against every other model (unmarked: the null is true), against its own
container, whole and after random pruning (marked), and against its own container with the features
shuffled among the anchors. Reports the false- and true-positive
rates with their counts, the cover's PSNR against the plain model of the same scene and seed, and
a histogram of the statistic for marked and unmarked pairs.
"""
from __future__ import annotations

import copy
import dataclasses
import math

import torch

from ..config import SceneSpec, SecureConfig, TrainConfig
from ..io.atomic import save_figure
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
    while trainer.step_count < trainer.total_steps:
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
    pruned.prune_anchors(mask, max_log_gaussian_scale=None)  # an attack removes anchors, nothing else
    return pruned


KINDS = ("unmarked", "marked", "shuffled")


def verification_rows(models: list[StudyModel], prunings: int, fraction: float, alpha: float = DEFAULT_ALPHA,
                      seed: int = 0) -> list[dict]:
    """One row per (key, model) test, by kind: every container's key against every other model
    ("unmarked": the null is true), against its own container, whole and in ``prunings`` random
    prunings of ``fraction`` of its anchors ("marked"), and against ``prunings`` copies of its own
    container with the features shuffled among the anchors ("shuffled": not a null, since the
    features were trained with the key; it shows what shuffling leaves of the mark)."""
    generator = torch.Generator().manual_seed(seed)
    rows = []
    for key in (m for m in models if m.decoder is not None):
        feat, xyz = key.anchors.feat.detach(), key.anchors.xyz
        tests = [(other.name, other.anchors.feat.detach(), other.anchors.xyz, "unmarked")
                 for other in models if other is not key]
        tests.append((key.name, feat, xyz, "marked"))
        for i in range(prunings):
            pruned = random_prune(key.anchors, fraction, generator)
            tests.append((f"{key.name} pruned {fraction:.0%} #{i}", pruned.feat.detach(), pruned.xyz, "marked"))
            shuffled = feat[torch.randperm(len(feat), generator=generator)]
            tests.append((f"{key.name} shuffled #{i}", shuffled, xyz, "shuffled"))
        for name, test_feat, test_xyz, kind in tests:
            result = verify_message(key.decoder, test_feat, test_xyz, alpha)
            rows.append({"key": key.name, "model": name, "kind": kind, **result.to_json()})
    return rows


def summary(rows: list[dict]) -> dict:
    """Per kind: tests, how many verified present and the rate (the false-positive rate for
    "unmarked", the true-positive rate for "marked"), each side's range of bit accuracy and p-value."""
    out = {}
    for kind in KINDS:
        group = [r for r in rows if r["kind"] == kind]
        positives = sum(r["present"] for r in group)
        out[kind] = {"tests": len(group), "present": positives,
                     "rate": positives / len(group) if group else math.nan,
                     "bit_accuracy_min": min((r["bit_accuracy"] for r in group), default=math.nan),
                     "bit_accuracy_max": max((r["bit_accuracy"] for r in group), default=math.nan),
                     "p_value_min": min((r["p_value"] for r in group), default=math.nan),
                     "p_value_max": max((r["p_value"] for r in group), default=math.nan)}
    return out


def plot_histogram(path, rows: list[dict], bits: int) -> None:
    """PNG: bit accuracy of each kind of test, with the exact null distribution Binomial(bits, 1/2)
    / bits scaled to the unmarked count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    edges = [(k - 0.5) / bits for k in range(bits + 2)]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    labels = {"unmarked": "unmarked: other models", "marked": "marked: containers, whole and 20% pruned",
              "shuffled": "containers, features shuffled"}
    for kind, colour in zip(KINDS, ("tab:blue", "tab:red", "tab:orange")):
        values = [r["bit_accuracy"] for r in rows if r["kind"] == kind]
        ax.hist(values, bins=edges, color=colour, alpha=0.6, label=f"{labels[kind]} ({len(values)})")
    unmarked = sum(r["kind"] == "unmarked" for r in rows)
    null = [unmarked * math.comb(bits, k) / 2**bits for k in range(bits + 1)]
    ax.plot([k / bits for k in range(bits + 1)], null, "k--", lw=1, label=f"exact null Binomial({bits}, 1/2)")
    ax.set_xlabel(f"bit accuracy ({bits}-bit messages)")
    ax.set_ylabel("tests")
    ax.set_xlim(0, 1.02)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
