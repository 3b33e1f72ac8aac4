"""Side by side: SecureGS variants against the plain Scaffold-GS baseline on the same scene and budget.

What ``scripts/secure_vs_baseline.py`` reports and the README's fidelity and leakage conclusions rest
on: the variant syntax, the training loop that records what went wrong, the public PSNR outside and
inside the hidden object's footprint, the release size, and the report tables.

A variant is ``MODE[:FIELD=VALUE]...``: the density mode (``strategies.MODES``: ``cover``, ``rdo``,
``scaffold``, ``global``, ``shared``), then any ``SecureConfig`` field by name, or by dotted path
when a name is not unique (``hidden_weight=1``, ``hidden_feature_grad=0.3``, ``feature_grad_until=0.5``, ``hdger=false``,
``r_down=16``, ``hidden_tau_scale=inf``, ``strategy.hidden_growth_at=public``).
"""
from __future__ import annotations

import json
import re
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from .config import SecureConfig, apply_overrides
from .io.atomic import atomic_write
from .io.gs_ply import read_vertex_ply, vertex_columns
from .runs import RunFolder
from .secure.security import exposure
from .strategies import MODES
from .train.base import psnr_label

BASELINE = "Scaffold-GS baseline"
# What a secure_vs_baseline.py report's meta says of its scene and budget: runs that agree on all
# of them were trained on the same views for as long (the seed may differ).
SCENE_AND_BUDGET = ("hidden", "placement", "width", "height", "iterations")
# anchor_clouds.npz holds the scene's points beside the models' anchors (for the plots); not models.
SCENE_ARRAYS = ("hidden_points", "scene_points")
# The SceneSpec fields that say what is hidden and where: a plain model never sees them.
HIDDEN_SCENE_FIELDS = ("hidden", "level", "hidden_position", "hidden_size", "hidden_yaw", "hidden_up",
                       "hidden_placement")
COLUMNS = ("psnr_public", "psnr_public_off_hidden", "psnr_public_on_hidden", "ssim_public", "psnr_hidden",
           "ssim_hidden", "hidden_learnt", "bit_accuracy", "bit_accuracy_on_baseline", "fps_public",
           "fps_public_and_hidden", "size_mb", "anchors", "train_seconds", "nonfinite_steps", "incomplete_steps")


def parse_variant(text: str, base: SecureConfig) -> tuple[str, SecureConfig]:
    """``MODE[:FIELD=VALUE]...`` -> (row label, ``base`` with the mode and fields set). A value may
    hold colons (``cover:robust=prune-random:0.3+noise-feat:0.3``): options part only at a colon
    that starts ``FIELD=``.

    Raises ValueError naming an unknown mode, a malformed option or an unknown field."""
    mode, colon, rest = text.partition(":")
    options = re.split(r":(?=[\w.]+=)", rest) if colon else []
    if mode not in MODES:
        raise ValueError(f"variant {text!r}: mode must be one of {', '.join(MODES)}, got {mode!r}")
    overrides = {"strategy.mode": mode}
    for option in options:
        name, sep, value = option.partition("=")
        if not sep or not name or not value:
            raise ValueError(f"variant {text!r}: option {option!r} is not FIELD=VALUE")
        overrides[name] = value
    return variant_label(mode, options), apply_overrides(base, overrides)


def variant_label(mode: str, options=()) -> str:
    """A SecureGS model's row label: its density mode (none for the paper's rdo) and options."""
    notes = ([] if mode == "rdo" else [mode]) + list(options)
    return "SecureGS" + (f" ({', '.join(notes)})" if notes else "")


def train(trainer, label: str) -> dict:
    """Run the trainer's whole budget. Returns ``nonfinite_steps`` (steps with a non-finite gradient,
    skipped by the trainer), ``nonfinite_at`` ([step, [parameter groups at fault]] of each),
    ``incomplete_steps`` (steps skipped because a captured render overflowed its intersection
    capacity), ``train_psnr_per_100`` (the mean training-view PSNR of every 100 steps, to see when
    a run went wrong) and, for SecureGS, the ``robust`` training, ``bit_margin``, ``hidden_finish``
    and ``finish_robust`` it resolved."""
    t0 = time.perf_counter()
    nonfinite_at, trace, window = [], [], []
    incomplete = 0
    while trainer.step_count < trainer.total_steps:
        stats = trainer.step()
        if psnr_label(stats) == "psnr":  # the trace follows the public render
            window.append(stats["psnr"])
        if len(window) == 100:
            trace.append(round(float(np.mean(window)), 2))
            window = []
        if "nonfinite_grads" in stats:
            nonfinite_at.append([trainer.step_count, stats["nonfinite_groups"]])
        incomplete += "incomplete_renders" in stats
    print(f"{label}: {trainer.step_count} steps in {time.perf_counter() - t0:.0f} s, "
          f"{trainer.model.anchors.num_anchors} anchors, {len(nonfinite_at)} steps with non-finite gradients "
          f"{nonfinite_at or ''}, {incomplete} with an incomplete captured render", flush=True)
    out = {"nonfinite_steps": len(nonfinite_at), "nonfinite_at": nonfinite_at, "incomplete_steps": incomplete,
           "train_psnr_per_100": trace}
    secure = getattr(trainer, "secure", None)
    if secure is not None:  # a variant's label leaves the defaults it resolved unsaid
        out.update(robust=secure.robust, bit_margin=secure.bit_margin, hidden_finish=secure.hidden_finish,
                   finish_robust=secure.finish_robust)
    return out


class RegionErrors:
    """Public held-out PSNR outside and inside the hidden object's footprint (its alpha in each test
    view, dilated by 1% of the width): where the cover scene loses fidelity to the hidden branch.
    Fed by ``evaluate(on_render=...)`` with the renders it makes anyway; PSNR of the squared error
    pooled over all views' pixels of the region. Also each view's PSNR (``per_view``), to tell one
    broken view from a model that is worse everywhere."""

    def __init__(self):
        self.sums = {"off": [0.0, 0], "on": [0.0, 0]}
        self.per_view = []

    def __call__(self, cam, image: torch.Tensor) -> None:
        """cam: a Camera with ``image`` and ``hidden_alpha``; image: the render [H, W, 3]."""
        err = ((image - torch.as_tensor(cam.image, device=image.device)) ** 2).mean(dim=-1)
        self.per_view.append(round(float(-10.0 * torch.log10(err.mean())), 2))
        alpha = torch.as_tensor(cam.hidden_alpha[..., 0], device=image.device)
        r = max(1, cam.width // 100)
        on = torch.nn.functional.max_pool2d((alpha > 0.01).float()[None, None], 2 * r + 1, 1, r)[0, 0] > 0
        for name, mask in (("on", on), ("off", ~on)):
            self.sums[name][0] += float(err[mask].sum())
            self.sums[name][1] += int(mask.sum())

    def psnr(self) -> dict:
        """``psnr_public_off_hidden`` / ``_on_hidden``: None for an empty region (a hidden scene
        covers every pixel), inf for a region rendered exactly."""
        return {f"psnr_public_{name}_hidden": None if count == 0 else
                (-10.0 * np.log10(total / count) if total > 0 else float("inf"))
                for name, (total, count) in self.sums.items()}


def release_mb(model) -> float:
    """Size in MB of the public release (point_cloud.ply + MLPs) of a ``ScaffoldModel``."""
    with tempfile.TemporaryDirectory() as d:
        model.save(d)
        return sum(p.stat().st_size for p in Path(d).iterdir()) / 1e6


def public_row(trainer, training: dict, scene, radius: float) -> dict:
    """The columns every model has: public held-out metrics (with RegionErrors' PSNR outside/inside
    the hidden footprint and per view), release size, anchors, training time and ``train``'s
    columns, and the anchor cloud's exposure."""
    regions = RegionErrors()
    ev = trainer.evaluate(on_render=regions)
    xyz = trainer.model.anchors.xyz.detach().cpu().numpy()
    return {"psnr_public": ev["psnr"], **regions.psnr(), "psnr_public_per_view": regions.per_view,
            "ssim_public": ev["ssim"], "fps_public": ev["fps"], "size_mb": release_mb(trainer.model),
            "anchors": ev["anchors"], "train_seconds": trainer.train_seconds, **training,
            "exposure": exposure(xyz, scene.hidden_points, scene.points, radius)}


def markdown_row(label: str, row: dict, baseline: dict | None = None) -> str:
    """One table row; ``baseline``: the plain model's row, for the density ratio (the anchors
    within r of the hidden-only surface, over the baseline's)."""
    cells = [f"{row[c]:.4g}" if isinstance(row.get(c), float) else str(row.get(c, "–")) for c in COLUMNS]
    e = row["exposure"]
    ratio = density_ratio(e, baseline["exposure"]) if baseline is not None else None
    return (f"| {label} | " + " | ".join(cells) + f" | {e['surface_fraction']:.3f} | {e['coverage']:.3f} | "
            + ("–" if ratio is None else f"{ratio:.2f}") + " |")


def density_ratio(exposed: dict, baseline: dict) -> float | None:
    """Anchors within r of the hidden-only surface in one model over those in the baseline (two
    ``exposure`` dicts); None when the baseline has none there."""
    return exposed["surface_density"] / baseline["surface_density"] if baseline["surface_density"] > 0 else None


def read_report(folder: Path) -> tuple[dict, dict]:
    """({"meta", "rows"} of secure_vs_baseline.json, the arrays of anchor_clouds.npz: model label ->
    anchor positions [N, 3], plus SCENE_ARRAYS) of one ``scripts/secure_vs_baseline.py --out`` folder;
    ValueError naming the folder when either is missing or unreadable (no pickled objects are read)."""
    folder = Path(folder)
    try:
        report = json.loads((folder / "secure_vs_baseline.json").read_text())
        with np.load(folder / "anchor_clouds.npz", allow_pickle=False) as arrays:
            clouds = {name: arrays[name] for name in arrays.files}
        if not isinstance(report, dict) or not {"meta", "rows"} <= set(report):
            raise ValueError("no meta or rows in the report")
    except (OSError, ValueError) as e:
        raise ValueError(f"{folder}: not a secure_vs_baseline.py output folder ({e})") from None
    missing = [label for label in report["rows"] if label not in clouds]
    if missing:
        raise ValueError(f"{folder}: anchor_clouds.npz lacks the anchors of {', '.join(missing)}")
    return report, clouds


def read_run_anchors(folder) -> tuple[str, str, np.ndarray]:
    """(cover, label, anchor positions [N, 3] float64) of a ``securegs train`` or ``securegs hide``
    run folder. cover: what a plain model's training depends on, as sorted JSON (the scene less
    HIDDEN_SCENE_FIELDS, and the training config with its seed), so that a plain run and a container
    trained on the same views for as long with the same seed share it; label: BASELINE for a plain
    run, ``variant_label`` of its density mode for a container. ValueError naming the folder when it
    is no run folder or its point cloud is unreadable."""
    run = RunFolder(folder)
    try:
        config = run.read_config()
        scene = {k: v for k, v in config["scene"].items() if k not in HIDDEN_SCENE_FIELDS}
        cover = json.dumps({"scene": scene, "train": config["train"]}, sort_keys=True)
        secure = config.get("secure")
        label = BASELINE if secure is None else variant_label(secure["strategy"]["mode"])
        path = run.model / "point_cloud.ply"
        xyz = vertex_columns(path, read_vertex_ply(path), ("x", "y", "z")).astype(np.float64)
    except (OSError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{folder}: not a readable securegs train / hide run ({e})") from None
    return cover, label, xyz


def write_report(out: Path, meta: dict, rows: dict) -> str:
    """secure_vs_baseline.json and .md (atomically, after every model, so a later failure loses
    nothing); returns the markdown table."""
    baseline = rows.get(BASELINE)
    lines = ["| model | " + " | ".join(COLUMNS) + " | surface fraction | coverage | density ratio |",
             "|---" * (len(COLUMNS) + 4) + "|"] + [markdown_row(label, r, baseline) for label, r in rows.items()]
    table = (f"{meta['device']}, {meta['width']}×{meta['height']}, {meta['iterations']} iterations, hidden "
             f"{meta['hidden']}, payload {meta['payload']}\n\n" + "\n".join(lines))
    atomic_write(out / "secure_vs_baseline.json", lambda f: f.write(json.dumps({"meta": meta, "rows": rows},
                                                                               indent=1).encode()))
    atomic_write(out / "secure_vs_baseline.md", lambda f: f.write((table + "\n").encode()))
    return table
