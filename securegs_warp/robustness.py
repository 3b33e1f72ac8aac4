"""What survives an attack: scores of an attacked release against what the key holder got before it,
and the sweep of every attack over its strengths behind ``scripts/robustness.py``.

The key holder does not have the original hidden images, so the hidden targets are the unattacked
release's own hidden renders with the key (``reference_hidden``); with the scene's hidden views the
true images are scored as well (``psnr_hidden_truth``). Bits are scored against the key's message;
the cover against the scene's held-out views.
"""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import torch

from .attacks import Attack, AttackContext, apply_attacks
from .config import TrainConfig
from .data import SceneData
from .evaluation import image_metrics
from .io.atomic import atomic_write, save_figure
from .scaffold_model import ScaffoldModel
from .secure.container import KeyViews
from .secure.model import SecureModel

# The PSNR reported for renders identical to their reference (infinite otherwise, which JSON cannot hold).
PSNR_IDENTICAL = 100.0
SCORE_KEYS = ("psnr_hidden", "ssim_hidden", "psnr_hidden_truth", "ssim_hidden_truth", "bit_accuracy", "psnr_public",
              "ssim_public", "anchors")
SUMMARY_KEYS = ("model", "spec", "draws", "against", "psnr_hidden_mean", "psnr_hidden_worst", "delta_mean",
                "delta_worst", "bit_accuracy_worst")

# Each attack's strengths in the sweep, weakest first.
SWEEP = {
    "prune-random": ["prune-random:0.05", "prune-random:0.1", "prune-random:0.15", "prune-random:0.2",
                     "prune-random:0.3"],
    "prune-opacity": ["prune-opacity:0.05", "prune-opacity:0.1", "prune-opacity:0.15", "prune-opacity:0.2",
                      "prune-opacity:0.3"],
    "purify": ["purify:0.05", "purify:0.1", "purify:0.15", "purify:0.2", "purify:0.3"],
    "sor": ["sor:16:3", "sor:16:2", "sor:16:1.5", "sor:16:1", "sor:16:0.5"],
    "noise-xyz": ["noise-xyz:0.001", "noise-xyz:0.0025", "noise-xyz:0.005", "noise-xyz:0.01"],
    "noise-feat": ["noise-feat:0.05", "noise-feat:0.1", "noise-feat:0.15", "noise-feat:0.25", "noise-feat:0.5"],
    "noise-offset": ["noise-offset:0.05", "noise-offset:0.1", "noise-offset:0.15", "noise-offset:0.25",
                     "noise-offset:0.5"],
    "quantize": ["quantize:12", "quantize:10", "quantize:8", "quantize:6", "quantize:4"],
    "half": ["half"],
    "finetune": ["finetune:25", "finetune:50", "finetune:100", "finetune:200"],
}


@torch.no_grad()
def reference_hidden(model: SecureModel, views: KeyViews) -> list[torch.Tensor]:
    """The hidden renders [H, W, 3] (clamped) of ``views.hidden`` with the key: the targets the key
    holder had before an attack (empty for a bits-only key)."""
    if not model.renders_hidden:
        return []
    return [model.render_hidden(c, views.raster, background=views.hidden_background)["image"].clamp(0, 1)
            for c in views.hidden]


@torch.no_grad()
def score_release(model: SecureModel, views: KeyViews, reference: list[torch.Tensor] | None = None,
                  scene: SceneData | None = None) -> dict:
    """SCORE_KEYS of a release opened with its key; None where a score does not apply.

    reference: hidden targets from ``reference_hidden`` (None: this is the reference itself, so
    ``psnr_hidden``/``ssim_hidden`` are None); identical renders score PSNR_IDENTICAL.
    scene: the cover's data: its held-out views (the training views without them) for
    ``psnr_public``/``ssim_public``, and the hidden images of cameras named as the key's for
    ``psnr_hidden_truth``/``ssim_hidden_truth``.
    """
    device = model.device
    out = dict.fromkeys(SCORE_KEYS)
    out["anchors"] = model.anchors.num_anchors
    renders = reference_hidden(model, views)
    if reference is not None and renders:
        # Capped view by view: one view an attack left identical (inf) must not hide the others' loss.
        metrics = image_metrics(zip(renders, reference), device, with_lpips=False, psnr_cap=PSNR_IDENTICAL)
        out["psnr_hidden"], out["ssim_hidden"] = metrics["psnr"], metrics["ssim"]
    if views.message is not None and model.private is not None and model.private.bits is not None:
        out["bit_accuracy"] = float((model.decode_bits() == views.message).float().mean())
    if scene is not None:
        by_name = {c.name: c for c in scene.train + scene.test}
        truth = [(r, torch.as_tensor(by_name[c.name].hidden, device=device)) for r, c in zip(renders, views.hidden)
                 if views.scene_targets and c.name in by_name and by_name[c.name].hidden is not None]
        if truth:
            metrics = image_metrics(truth, device, with_lpips=False)
            out["psnr_hidden_truth"], out["ssim_hidden_truth"] = metrics["psnr"], metrics["ssim"]
        background = None if scene.background is None else torch.tensor(scene.background, dtype=torch.float32,
                                                                         device=device)
        pairs = [(model.render(c, views.raster, background=background)["image"].clamp(0, 1),
                  torch.as_tensor(c.image, device=device)) for c in scene.evaluation_views]
        metrics = image_metrics(pairs, device, with_lpips=False)
        out["psnr_public"], out["ssim_public"] = metrics["psnr"], metrics["ssim"]
    return out


def attacked_copy(model: SecureModel, attacks: list[Attack], ctx: AttackContext) -> tuple[SecureModel, list[dict]]:
    """A copy of ``model`` with the attacks applied to its public part (the key's heads are shared,
    not attacked: the attacker has no key); returns (the attacked model, the attacks' reports)."""
    public = ScaffoldModel(copy.deepcopy(model.anchors), copy.deepcopy(model.heads))
    reports = apply_attacks(public, attacks, ctx)
    return SecureModel(public.anchors, public.heads, list(model.secrets)), reports


def sweep(models: dict[str, SecureModel], views: dict[str, KeyViews], scene: SceneData | None,
          attacks: dict[str, list[str]] | None = None, seed: int = 0, train: TrainConfig | None = None,
          on_row=None, draws: int = 1) -> list[dict]:
    """Every attack of ``attacks`` (default SWEEP: name -> specs) at each strength on each model
    (label -> SecureModel opened with its key; ``views[label]`` its key's views). One row per
    (model, spec, draw) with SCORE_KEYS, plus a row per model with ``spec`` "none" (the unattacked
    scores, ``psnr_hidden`` None). Each attack starts from the unattacked model. An attack that
    draws randomly (``Attack.draws_randomly``) runs ``draws`` times, draw d with the random source
    seeded by ``seed + d``, so that a goal can be read on the mean or the worst of them
    (``summarize_draws``); the others run once, as draw 0. ``on_row(row)`` sees each row as it is made."""
    if draws < 1:
        raise ValueError(f"draws must be at least 1, got {draws}")
    rows = []
    for label, model in models.items():
        v = views[label]
        reference = reference_hidden(model, v)
        rows.append({"model": label, "attack": "none", "spec": "none", "strength": 0.0, "draw": 0,
                     **score_release(model, v, None, scene)})
        if on_row:
            on_row(rows[-1])
        for name, specs in (attacks or SWEEP).items():
            for spec in specs:
                attack = Attack.parse(spec)
                if attack.needs_scene and scene is None:
                    continue
                for draw in range(draws if attack.draws_randomly else 1):
                    ctx = AttackContext(v.hidden or v.cameras, v.raster, v.background,
                                        torch.Generator().manual_seed(seed + draw), scene, train or TrainConfig())
                    attacked, reports = attacked_copy(model, [attack], ctx)
                    rows.append({"model": label, "attack": name, "spec": spec, "strength": strength_of(attack),
                                 "draw": draw, **score_release(attacked, v, reference, scene),
                                 "applicable": reports[0]["applicable"]})
                    if on_row:
                        on_row(rows[-1])
    return rows


def summarize_draws(rows: list[dict]) -> list[dict]:
    """One row per (model, spec) of ``sweep``'s rows, in their order, with SUMMARY_KEYS: ``draws``
    (the rows), ``against`` (what the hidden PSNR is scored against: "truth", the true hidden views,
    where the model's rows have them, else "unattacked", its unattacked render), that PSNR's mean
    and worst over the draws that have it, their change from the model's unattacked level in dB
    (``delta_mean``, ``delta_worst``: negative is lost; None against "unattacked", whose level is
    the reference itself) and the worst bit accuracy."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["model"], r["spec"]), []).append(r)
    key = {m: "psnr_hidden_truth" if any(r["model"] == m and r.get("psnr_hidden_truth") is not None for r in rows)
           else "psnr_hidden" for m, _ in groups}
    level = {m: these[0][key[m]] for (m, spec), these in groups.items() if spec == "none"}
    out = []
    for (model, spec), these in groups.items():
        psnr = [r[key[model]] for r in these if r[key[model]] is not None]
        bits = [r["bit_accuracy"] for r in these if r["bit_accuracy"] is not None]
        mean, worst = (float(np.mean(psnr)), min(psnr)) if psnr else (None, None)
        base = level.get(model)
        change = lambda v: None if v is None or base is None else v - base  # noqa: E731
        out.append(dict(zip(SUMMARY_KEYS, (model, spec, len(these), "truth" if key[model] == "psnr_hidden_truth"
                                           else "unattacked", mean, worst, change(mean), change(worst),
                                           min(bits) if bits else None))))
    return out


def strength_of(attack: Attack) -> float:
    """The number a sweep plots an attack against: its argument (sor: STD, the smaller the
    stronger; half and export-roundtrip: 1)."""
    return float(attack.args[-1]) if attack.args else 1.0


def write_sweep(out: Path, rows: list[dict], meta: dict) -> str:
    """robustness.csv, robustness.json and robustness.md in ``out`` (atomically); returns the
    markdown: the rows' table, and where an attack ran more than one draw, ``summarize_draws``'s
    table after it (also under ``summary`` in the JSON)."""
    fmt = lambda v: "" if v is None else (f"{v:.4g}" if isinstance(v, float) else str(v))  # noqa: E731

    def markdown(columns, items):
        return "\n".join(["| " + " | ".join(columns) + " |", "|---" * len(columns) + "|"]
                         + ["| " + " | ".join(fmt(r.get(c)) or "–" for c in columns) + " |" for r in items])

    columns = ("model", "spec", "draw", *SCORE_KEYS)
    csv = "\n".join([",".join(columns)] + [",".join(fmt(r.get(c)) for c in columns) for r in rows]) + "\n"
    table = markdown(columns, rows)
    summary = summarize_draws(rows)
    if any(s["draws"] > 1 for s in summary):
        table += "\n\nOver the draws of each attack:\n\n" + markdown(SUMMARY_KEYS, summary)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / "robustness.csv", lambda f: f.write(csv.encode()))
    data = json.dumps({"meta": meta, "rows": rows, "summary": summary}, indent=1).encode()
    atomic_write(out / "robustness.json", lambda f: f.write(data))
    atomic_write(out / "robustness.md", lambda f: f.write((table + "\n").encode()))
    return table


def plot_sweep(path: Path, rows: list[dict]) -> None:
    """One column per attack: hidden PSNR (against the true hidden views where known, else against
    the unattacked render), bit accuracy and cover PSNR against strength, one line per model (the
    mean over an attack's draws, shaded between their worst and best), its unattacked level dashed.
    Needs matplotlib (the ``plots`` extra)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in dict.fromkeys(r["attack"] for r in rows) if n != "none"]
    models = list(dict.fromkeys(r["model"] for r in rows))
    truth = any(r.get("psnr_hidden_truth") is not None for r in rows)
    panels = (("psnr_hidden_truth" if truth else "psnr_hidden", "hidden PSNR (dB)" + (" vs truth" if truth else "")),
              ("bit_accuracy", "bit accuracy (%)"), ("psnr_public", "cover PSNR (dB)"))
    cols = min(5, len(names))
    blocks = (len(names) + cols - 1) // cols
    fig, axes = plt.subplots(3 * blocks, cols, figsize=(3.2 * cols, 6.6 * blocks), squeeze=False)
    for i in range(len(names), blocks * cols):  # empty places of the last block
        for p in range(3):
            axes[3 * (i // cols) + p, i % cols].axis("off")
    for i, name in enumerate(names):
        column = [axes[3 * (i // cols) + p, i % cols] for p in range(3)]
        for j, label in enumerate(models):
            these = [r for r in rows if r["model"] == label and r["attack"] == name]
            base = next((r for r in rows if r["model"] == label and r["attack"] == "none"), None)
            specs = list(dict.fromkeys(r["spec"] for r in these))  # a spec's draws share its strength
            x = [next(r["strength"] for r in these if r["spec"] == spec) for spec in specs]
            for ax, (key, _) in zip(column, panels):
                scale = 100.0 if key == "bit_accuracy" else 1.0
                y = [[scale * r[key] for r in these if r["spec"] == spec and r[key] is not None] or [np.nan]
                     for spec in specs]
                ax.plot(x, [np.mean(v) for v in y], "o-" if len(x) > 1 else "o", color=f"C{j}", label=label)
                if any(len(v) > 1 for v in y):
                    ax.fill_between(x, [min(v) for v in y], [max(v) for v in y], color=f"C{j}", alpha=0.2)
                if base is not None and base[key] is not None:
                    ax.axhline(scale * base[key], color=f"C{j}", ls="--", lw=0.8)
                ax.ticklabel_format(axis="y", useOffset=False)
        column[0].set_title(name)
        column[2].set_xlabel("STD (smaller removes more)" if name == "sor" else "strength")
        column[1].set_ylim(40, 102)
        for ax in (column[0], column[2]):  # at least 2 dB tall, so that noise does not look like a trend
            lo, hi = ax.get_ylim()
            if hi - lo < 2.0:
                ax.set_ylim((lo + hi) / 2 - 1.0, (lo + hi) / 2 + 1.0)
        if i % cols == 0:
            for ax, (_, ylabel) in zip(column, panels):
                ax.set_ylabel(ylabel)
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=100)
