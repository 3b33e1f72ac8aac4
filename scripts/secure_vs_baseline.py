"""SecureGS against the plain Scaffold-GS baseline on the same synthetic scene and budget.

Trains, on one scene with a hidden object: the Scaffold-GS baseline (public views only), the SecureGS
container (object + bits, RDO) and, for the security comparison, SecureGS without RDO (Scaffold-GS
densification on both branches). Reports public fidelity against the baseline, hidden fidelity, bit
accuracy, FPS of the public render with and without the hidden path, release size, and how much of
the hidden object's shape each anchor cloud shows; draws the anchor clouds side by side.

    python scripts/secure_vs_baseline.py --out runs/secure_vs_baseline               # CPU default
    python scripts/secure_vs_baseline.py --width 1920 --height 1080 --iterations 3000 # GPU
    python scripts/secure_vs_baseline.py --modes rdo,rdo:lambda=1,rdo:fixed-scaling  # what costs fidelity

A variant is ``MODE[:lambda=X][:fixed-scaling]``: the density mode (or no-hdger), λ overriding the
payload's default, and ``fixed-scaling`` to keep ℓ_hid from moving the public anchor scalings l_v
(``SecureTrainer(hidden_scaling_grad=False)``).
"""
import argparse
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
from securegs_warp.secure import PayloadSpec, SecureTrainer
from securegs_warp.secure.security import exposure, plot_anchor_clouds
from securegs_warp.train import ScaffoldTrainer, TrainConfig, render_fps


def train(trainer, label):
    t0 = time.perf_counter()
    for _ in range(trainer.config.iterations):
        trainer.step()
    print(f"{label}: {trainer.config.iterations} steps in {time.perf_counter() - t0:.0f} s, "
          f"{trainer.model.num_anchors} anchors", flush=True)
    return trainer


def parse_variant(text: str) -> tuple[str, dict]:
    """``MODE[:lambda=X][:fixed-scaling]`` -> (row label, SecureTrainer keyword arguments)."""
    mode, *opts = text.split(":")
    kwargs = {"mode": "rdo" if mode == "no-hdger" else mode, "hdger": mode != "no-hdger"}
    notes = [] if mode == "rdo" else [mode]
    for opt in opts:
        if opt.startswith("lambda="):
            kwargs["hidden_weight"] = float(opt.removeprefix("lambda="))
            notes.append(f"λ={kwargs['hidden_weight']:g}")
        elif opt == "fixed-scaling":
            kwargs["hidden_scaling_grad"] = False
            notes.append("l_v public only")
        else:
            raise ValueError(f"variant {text!r}: unknown option {opt!r} (lambda=X, fixed-scaling)")
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
                    help="SecureGS variants MODE[:lambda=X][:fixed-scaling]: density modes rdo, scaffold (w/o "
                         "RDO), global, shared; no-hdger (RDO with explicit hidden offsets)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", default=os.environ.get("OUT", "runs/secure_vs_baseline"))
    args = ap.parse_args()
    wp.config.quiet = True
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tile = 8 if args.device == "cpu" else 16
    scene = make_synthetic_scene(hidden=args.hide, level="object", width=args.width, height=args.height,
                                 n_train=args.train_views, n_test=args.test_views, device=args.device)
    config = TrainConfig(iterations=args.iterations, tile_size=tile)
    radius = 0.03 * float(np.linalg.norm(np.ptp(scene.hidden_points, axis=0)))
    rows, clouds = {}, {}

    base = train(ScaffoldTrainer(scene, config, device=args.device), "baseline")
    ev = base.evaluate()
    xyz = base.model.xyz.detach().cpu().numpy()
    rows["Scaffold-GS baseline"] = {"psnr_public": ev["psnr"], "ssim_public": ev["ssim"], "fps_public": ev["fps"],
                                    "size_mb": release_mb(base), "anchors": ev["anchors"],
                                    "train_seconds": base.train_seconds,
                                    "exposure": exposure(xyz, scene.hidden_points, scene.points, radius)}
    clouds["Scaffold-GS baseline"] = xyz

    for variant in args.modes.split(","):
        label, kwargs = parse_variant(variant)
        sec = train(SecureTrainer(scene, config, PayloadSpec.parse(args.payload), device=args.device, **kwargs),
                    label)
        ev, hid = sec.evaluate(), sec.evaluate_hidden()
        cams = scene.test

        def both(cam):
            return sec.render(cam), sec.render_hidden(cam)

        with torch.no_grad():
            fps_both = render_fps(both, cams, args.device)
        xyz = sec.model.xyz.detach().cpu().numpy()
        rows[label] = {"psnr_public": ev["psnr"], "ssim_public": ev["ssim"], "fps_public": ev["fps"],
                       "fps_public_and_hidden": fps_both, "psnr_hidden": hid.get("psnr_hidden"),
                       "ssim_hidden": hid.get("ssim_hidden"), "bit_accuracy": hid.get("bit_accuracy"),
                       "size_mb": release_mb(sec), "anchors": ev["anchors"], "train_seconds": sec.train_seconds,
                       "hidden_anchors": int(sec.strategy_state["is_hidden"].sum()),
                       "exposure": exposure(xyz, scene.hidden_points, scene.points, radius)}
        clouds[label] = xyz

    plot_anchor_clouds(out / "anchor_clouds.png", clouds, scene.hidden_points)
    device = torch.cuda.get_device_name() if args.device == "cuda" else "cpu"
    meta = {"device": device, "date": time.strftime("%Y-%m-%d"), "width": args.width, "height": args.height,
            "iterations": args.iterations, "hidden": args.hide, "payload": args.payload, "exposure_radius": radius}
    (out / "secure_vs_baseline.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    cols = ("psnr_public", "ssim_public", "psnr_hidden", "ssim_hidden", "bit_accuracy", "fps_public",
            "fps_public_and_hidden", "size_mb", "anchors", "train_seconds")
    lines = ["| model | " + " | ".join(cols) + " | surface fraction | coverage |",
             "|---" * (len(cols) + 3) + "|"]
    for label, r in rows.items():
        cells = [f"{r[c]:.4g}" if isinstance(r.get(c), float) else str(r.get(c, "–")) for c in cols]
        e = r["exposure"]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {e['surface_fraction']:.3f} | {e['coverage']:.3f} |")
    table = (f"{device}, {args.width}×{args.height}, {args.iterations} iterations, hidden {args.hide}, "
             f"payload {args.payload}\n\n" + "\n".join(lines))
    (out / "secure_vs_baseline.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
