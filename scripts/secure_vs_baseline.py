"""SecureGS against the plain Scaffold-GS baseline on the same synthetic scene and budget.

Trains, on one scene with a hidden object: the Scaffold-GS baseline (public views only), the SecureGS
container (object + bits, RDO) and, for the security comparison, SecureGS without RDO (Scaffold-GS
densification on both branches). Reports public fidelity against the baseline, hidden fidelity, bit
accuracy, FPS of the public render with and without the hidden path, release size, and how much of
the hidden object's shape each anchor cloud shows; draws the anchor clouds side by side.

    python scripts/secure_vs_baseline.py --out runs/secure_vs_baseline               # CPU default
    python scripts/secure_vs_baseline.py --width 1920 --height 1080 --iterations 3000 # GPU
    python scripts/secure_vs_baseline.py --modes rdo,rdo:lambda=1,rdo:feature-grad=0.3  # what costs fidelity

The anchor-cloud PNG needs matplotlib (``pip install -e ".[plots]"``).

A variant is ``MODE[:OPTION]...``: the density mode (or no-hdger), then any of ``lambda=X`` (λ
overriding the payload's default), ``feature-grad=X`` and ``scaling-grad=X`` (the share of ℓ_hid's
gradient reaching the public anchor features f_v and scalings l_v, 0 to 1:
``SecureTrainer(hidden_feature_grad=, hidden_scaling_grad=)``), ``until=X`` (the f_v share applies for
the first X of the run, then 0: ``feature_grad_until``) and ``FIELD=VALUE`` for a field of
``RegionAwareStrategy`` (``r_down=16``, ``hidden_every=4``, ``hidden_tau_scale=inf``: no Γ_hid,
``hidden_opacity_keeps=false``: prune by the public opacity alone, ``hidden_growth_at=public``: Γ_hid
anchors at the public offsets' positions, this project's placement before 2026-11-22).
"""
import argparse
import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import warp as wp

from securegs_warp.data import make_synthetic_scene
from securegs_warp.io import save_scaffold
from securegs_warp.io.atomic import atomic_write
from securegs_warp.model.neural_gaussians import unit_fraction
from securegs_warp.secure import PayloadSpec, SecureTrainer
from securegs_warp.secure.strategy import RegionAwareStrategy
from securegs_warp.secure.security import exposure, plot_anchor_clouds
from securegs_warp.train import ScaffoldTrainer, TrainConfig, render_fps


COLUMNS = ("psnr_public", "psnr_public_off_hidden", "psnr_public_on_hidden", "ssim_public", "psnr_hidden",
           "ssim_hidden", "hidden_learnt", "bit_accuracy", "bit_accuracy_on_baseline", "fps_public", "fps_public_and_hidden", "size_mb", "anchors",
           "train_seconds", "nonfinite_steps")


def train(trainer, label) -> dict:
    """Run the trainer's whole budget. Returns the columns it yields: ``nonfinite_steps`` (steps
    with a non-finite gradient, skipped by the trainer: see train.trainer.nonfinite_gradient_counts),
    ``nonfinite_at`` ([step, [parameter groups at fault]] of each) and ``train_psnr_per_100`` (the
    mean training-view PSNR of every 100 steps, to see when a run went wrong)."""
    t0 = time.perf_counter()
    nonfinite_at, trace, window = [], [], []
    for _ in range(trainer.config.iterations):
        stats = trainer.step()
        window.append(stats["psnr"])
        if len(window) == 100:
            trace.append(round(float(np.mean(window)), 2))
            window = []
        if "nonfinite_grads" in stats:
            nonfinite_at.append([trainer.step_count, stats["nonfinite_groups"]])
    print(f"{label}: {trainer.config.iterations} steps in {time.perf_counter() - t0:.0f} s, "
          f"{trainer.model.num_anchors} anchors, {len(nonfinite_at)} steps with non-finite gradients "
          f"{nonfinite_at or ''}", flush=True)
    return {"nonfinite_steps": len(nonfinite_at), "nonfinite_at": nonfinite_at, "train_psnr_per_100": trace}


class RegionErrors:
    """Public held-out PSNR outside and inside the hidden object's footprint (its alpha in each test
    view, dilated by 1% of the width): where the cover scene loses fidelity to the hidden branch.
    Fed by ``trainer.evaluate(on_render=...)`` with the renders it makes anyway; PSNR of the squared
    error pooled over all views' pixels of the region. Also each view's PSNR (``per_view``), to tell
    one broken view from a model that is worse everywhere."""

    def __init__(self):
        self.sums = {"off": [0.0, 0], "on": [0.0, 0]}
        self.per_view = []

    def __call__(self, cam, image):
        err = ((image - torch.as_tensor(cam.image, device=image.device)) ** 2).mean(dim=-1)
        self.per_view.append(round(float(-10.0 * torch.log10(err.mean())), 2))
        alpha = torch.as_tensor(cam.hidden_alpha[..., 0], device=image.device)
        r = max(1, cam.width // 100)
        on = torch.nn.functional.max_pool2d((alpha > 0.01).float()[None, None], 2 * r + 1, 1, r)[0, 0] > 0
        for name, mask in (("on", on), ("off", ~on)):
            self.sums[name][0] += float(err[mask].sum())
            self.sums[name][1] += int(mask.sum())

    def psnr(self) -> dict:
        # None: the region is empty (a hidden scene covers every pixel); inf: rendered exactly.
        return {f"psnr_public_{name}_hidden": None if count == 0 else
                (-10.0 * np.log10(total / count) if total > 0 else float("inf"))
                for name, (total, count) in self.sums.items()}


def public_row(trainer, training: dict, scene, radius: float) -> dict:
    """The columns every model has: public held-out metrics (with RegionErrors' PSNR outside/inside
    the hidden footprint and per view), release size, anchors, training time and ``train``'s
    columns, and the anchor cloud's exposure."""
    regions = RegionErrors()
    ev = trainer.evaluate(on_render=regions)
    xyz = trainer.model.xyz.detach().cpu().numpy()
    return {"psnr_public": ev["psnr"], **regions.psnr(), "psnr_public_per_view": regions.per_view,
            "ssim_public": ev["ssim"], "fps_public": ev["fps"], "size_mb": release_mb(trainer),
            "anchors": ev["anchors"], "train_seconds": trainer.train_seconds, **training,
            "exposure": exposure(xyz, scene.hidden_points, scene.points, radius)}


def markdown_row(label, r) -> str:
    cells = [f"{r[c]:.4g}" if isinstance(r.get(c), float) else str(r.get(c, "–")) for c in COLUMNS]
    e = r["exposure"]
    return f"| {label} | " + " | ".join(cells) + f" | {e['surface_fraction']:.3f} | {e['coverage']:.3f} |"


def write_report(out: Path, meta: dict, rows: dict) -> str:
    """secure_vs_baseline.json and .md (atomically, after every model, so a later failure loses
    nothing); returns the markdown table."""
    lines = ["| model | " + " | ".join(COLUMNS) + " | surface fraction | coverage |",
             "|---" * (len(COLUMNS) + 3) + "|"] + [markdown_row(label, r) for label, r in rows.items()]
    table = (f"{meta['device']}, {meta['width']}×{meta['height']}, {meta['iterations']} iterations, hidden "
             f"{meta['hidden']}, payload {meta['payload']}\n\n" + "\n".join(lines))
    atomic_write(out / "secure_vs_baseline.json", lambda f: f.write(json.dumps({"meta": meta, "rows": rows},
                                                                               indent=1).encode()))
    atomic_write(out / "secure_vs_baseline.md", lambda f: f.write((table + "\n").encode()))
    return table


def parse_variant(text: str) -> tuple[str, dict]:
    """``MODE[:OPTION]...`` -> (row label, SecureTrainer keyword arguments); see the module docstring."""
    mode, *opts = text.split(":")
    kwargs = {"mode": "rdo" if mode == "no-hdger" else mode, "hdger": mode != "no-hdger", "strategy_options": {}}
    fields = [f.name for f in dataclasses.fields(RegionAwareStrategy)]
    notes = [] if mode == "rdo" else [mode]
    for opt in opts:
        name, _, value = opt.partition("=")
        if name == "lambda":
            kwargs["hidden_weight"] = float(value)
            notes.append(f"λ={float(value):g}")
        elif name == "until":
            kwargs["feature_grad_until"] = unit_fraction("until", value, "a fraction of the run")
            notes.append(f"f_v grad until {float(value):g} of the run")
        elif name in ("feature-grad", "scaling-grad"):
            kwargs["hidden_" + name.replace("-", "_")] = unit_fraction(name, value)
            notes.append(f"{'f_v' if name == 'feature-grad' else 'l_v'} grad×{float(value):g}")
        elif name in fields and value:
            kind = type(getattr(RegionAwareStrategy(), name))
            kwargs["strategy_options"][name] = value.lower() == "true" if kind is bool else kind(value)
            notes.append(opt)
        else:
            raise ValueError(f"variant {text!r}: unknown option {opt!r} (lambda=X, feature-grad=X, scaling-grad=X, until=X, "
                             f"or a RegionAwareStrategy field=VALUE: {', '.join(fields)})")
    return ("SecureGS" + (f" ({', '.join(notes)})" if notes else "")), kwargs


def release_mb(model) -> float:
    """Size in MB of the public release (point_cloud.ply + MLPs) of a trainer's model."""
    with tempfile.TemporaryDirectory() as d:
        save_scaffold(d, model.model, model.heads)
        return sum(p.stat().st_size for p in Path(d).iterdir()) / 1e6


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--train-views", type=int, default=32)
    ap.add_argument("--test-views", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--hide", default="mug")
    ap.add_argument("--payload", default="object+bits:48")
    ap.add_argument("--modes", default="rdo,scaffold",
                    help="SecureGS variants MODE[:lambda=X][:feature-grad=X][:scaling-grad=X][:until=X][:FIELD=VALUE]: density modes rdo, scaffold (w/o "
                         "RDO), global, shared; no-hdger (RDO with explicit hidden offsets)")
    ap.add_argument("--no-baseline", action="store_true",
                    help="train only the SecureGS variants (e.g. when the baseline of the same scene and budget "
                         "is already measured)")
    ap.add_argument("--seed", type=int, default=0,
                    help="training seed (MLP initialisation, view order, growth draws); the scene stays the same")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", default=os.environ.get("OUT", "runs/secure_vs_baseline"))
    args = ap.parse_args()
    wp.config.quiet = True
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tile = 8 if args.device == "cpu" else 16
    scene = make_synthetic_scene(hidden=args.hide, level="object", width=args.width, height=args.height,
                                 n_train=args.train_views, n_test=args.test_views, device=args.device)
    config = TrainConfig(iterations=args.iterations, tile_size=tile, seed=args.seed)
    radius = 0.03 * float(np.linalg.norm(np.ptp(scene.hidden_points, axis=0)))
    rows, clouds = {}, {}
    device = torch.cuda.get_device_name() if args.device == "cuda" else "cpu"
    meta = {"device": device, "date": time.strftime("%Y-%m-%d"), "width": args.width, "height": args.height,
            "iterations": args.iterations, "seed": args.seed, "hidden": args.hide, "payload": args.payload,
            "exposure_radius": radius}

    variants = [parse_variant(v) for v in args.modes.split(",")]  # a bad variant fails before any training

    base = None
    if not args.no_baseline:
        base = ScaffoldTrainer(scene, config, device=args.device)
        rows["Scaffold-GS baseline"] = public_row(base, train(base, "baseline"), scene, radius)
        clouds["Scaffold-GS baseline"] = base.model.xyz.detach().cpu().numpy()
        print(markdown_row("Scaffold-GS baseline", rows["Scaffold-GS baseline"]), flush=True)
        write_report(out, meta, rows)

    for label, kwargs in variants:
        sec = SecureTrainer(scene, config, PayloadSpec.parse(args.payload), device=args.device, **kwargs)
        training = train(sec, label)
        hid = sec.evaluate_hidden()
        cams = scene.test

        def both(cam):
            return sec.render(cam), sec.render_hidden(cam)

        with torch.no_grad():  # a bit-only payload has no hidden render
            fps_both = render_fps(both, cams, args.device) if sec.private.decoder is not None else None
        rows[label] = {**public_row(sec, training, scene, radius), "fps_public_and_hidden": fps_both,
                       "psnr_hidden": hid.get("psnr_hidden"), "ssim_hidden": hid.get("ssim_hidden"),
                       "bit_accuracy": hid.get("bit_accuracy"), "hidden_learnt": hid.get("hidden_learnt"),
                       "bit_accuracy_on_baseline": sec.bit_accuracy(base.model.feat) if base is not None else None,
                       "hidden_anchors": int(sec.strategy_state["is_hidden"].sum())}
        clouds[label] = sec.model.xyz.detach().cpu().numpy()
        print(markdown_row(label, rows[label]), flush=True)
        write_report(out, meta, rows)

    plot_anchor_clouds(out / "anchor_clouds.png", clouds, scene.hidden_points)
    print(write_report(out, meta, rows))


if __name__ == "__main__":
    main()
