"""SecureGS against the plain Scaffold-GS baseline on the same synthetic scene and budget.

Trains, on one scene with a hidden object: the Scaffold-GS baseline (public views only), the SecureGS
container (object + bits, RDO) and, for the security comparison, SecureGS without RDO (Scaffold-GS
densification on both branches). Reports public fidelity against the baseline, hidden fidelity, bit
accuracy, FPS of the public render with and without the hidden path, release size, and how much of
the hidden object's shape each anchor cloud shows; draws the anchor clouds side by side.

    python scripts/secure_vs_baseline.py --out runs/secure_vs_baseline               # CPU default
    python scripts/secure_vs_baseline.py --width 1920 --height 1080 --iterations 3000 # GPU
    python scripts/secure_vs_baseline.py --modes rdo,rdo:hidden_weight=1,rdo:hidden_feature_grad=0.3  # what costs fidelity

The anchor-cloud PNG needs matplotlib (``pip install -e ".[plots]"``).

A variant is ``MODE[:FIELD=VALUE]...`` (securegs_warp.compare.parse_variant): the density mode, then
any SecureConfig field by name (``hidden_weight=1``, ``hidden_feature_grad=0.3``, ``hdger=false``,
``r_down=16``, ``hidden_tau_scale=inf``, ``strategy.hidden_growth_at=public``).
"""
import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

from securegs_warp import benchmark
from securegs_warp.cli.common import quiet_warp
from securegs_warp.compare import BASELINE, markdown_row, parse_variant, public_row, train, write_report
from securegs_warp.config import SecureConfig, TrainConfig
from securegs_warp.data import make_synthetic_scene
from securegs_warp.evaluation import render_fps
from securegs_warp.io.atomic import atomic_write
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.secure import SecureTrainer
from securegs_warp.secure.security import plot_anchor_clouds
from securegs_warp.train import ScaffoldTrainer


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--train-views", type=int, default=32)
    ap.add_argument("--test-views", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--hide", default="mug")
    ap.add_argument("--placement", default="stand", help="stand (mostly in empty space), sink (half inside the "
                                                         "host object) or float")
    ap.add_argument("--payload", default="object+bits:48")
    ap.add_argument("--modes", default="rdo,scaffold",
                    help="SecureGS variants MODE[:FIELD=VALUE]...: density modes rdo, cover, scaffold (w/o RDO), "
                         "global, shared; FIELD any SecureConfig field (hidden_weight, hidden_feature_grad, hdger, "
                         "r_down, hidden_anchors, ...); empty: the baseline alone")
    ap.add_argument("--no-baseline", action="store_true",
                    help="train only the SecureGS variants (e.g. when the baseline of the same scene and budget "
                         "is already measured)")
    ap.add_argument("--seed", type=int, default=0,
                    help="training seed (MLP initialisation, view order, growth draws); the scene stays the same")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", default=os.environ.get("OUT", "runs/secure_vs_baseline"))
    args = ap.parse_args()
    quiet_warp()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = make_synthetic_scene(hidden=args.hide, level="object", width=args.width, height=args.height,
                                 n_train=args.train_views, n_test=args.test_views, device=args.device,
                                 hidden_placement=args.placement)
    config = TrainConfig(iterations=args.iterations, seed=args.seed, raster=RasterOptions.for_device(args.device))
    radius = 0.03 * float(np.linalg.norm(np.ptp(scene.hidden_points, axis=0)))
    rows, clouds = {}, {}
    device = benchmark.device_label(args.device)
    meta = {"device": device, "date": time.strftime("%Y-%m-%d"), "width": args.width, "height": args.height,
            "iterations": args.iterations, "seed": args.seed, "hidden": args.hide, "payload": args.payload,
            "placement": args.placement,
            "exposure_radius": radius}

    # A bad variant fails before any training.
    variants = [parse_variant(v, SecureConfig(payload=args.payload)) for v in args.modes.split(",") if v]

    base = None
    if not args.no_baseline:
        base = ScaffoldTrainer(scene, config, device=args.device)
        rows[BASELINE] = public_row(base, train(base, "baseline"), scene, radius)
        clouds[BASELINE] = base.model.anchors.xyz.detach().cpu().numpy()
        print(markdown_row(BASELINE, rows[BASELINE]), flush=True)
        write_report(out, meta, rows)

    for label, secure in variants:
        sec = SecureTrainer(scene, config, secure, device=args.device)
        training = train(sec, label)
        hid = sec.evaluate_hidden()
        cams = scene.test

        def both(cam):
            return sec.render(cam), sec.render_hidden(cam)

        with torch.no_grad():  # a bit-only payload has no hidden render
            fps_both = render_fps(both, cams, args.device) if sec.model.renders_hidden else None
        rows[label] = {**public_row(sec, training, scene, radius), "fps_public_and_hidden": fps_both,
                       "psnr_hidden": hid.get("psnr_hidden"), "ssim_hidden": hid.get("ssim_hidden"),
                       "bit_accuracy": hid.get("bit_accuracy"), "hidden_learnt": hid.get("hidden_learnt"),
                       "bit_accuracy_on_baseline": sec.bit_accuracy(base.model.anchors) if base is not None else None,
                       "hidden_anchors": int(sec.strategy_state["is_hidden"].sum())}
        clouds[label] = sec.model.anchors.xyz.detach().cpu().numpy()
        print(markdown_row(label, rows[label], rows.get(BASELINE)), flush=True)
        write_report(out, meta, rows)

    # The anchors themselves, so that runs of one scene made apart can be drawn and audited together.
    arrays = {"hidden_points": scene.hidden_points, "scene_points": scene.points, **clouds}
    atomic_write(out / "anchor_clouds.npz", lambda f: np.savez_compressed(f, **arrays))
    plot_anchor_clouds(out / "anchor_clouds.png", clouds, scene.hidden_points)
    print(write_report(out, meta, rows))


if __name__ == "__main__":
    main()
