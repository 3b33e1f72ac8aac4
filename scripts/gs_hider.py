"""GS-Hider on the built-in synthetic scene: train, write release + key, reopen them, measure.

One row per payload: a hidden 3D scene (the other built-in scene, seen from every camera) and one
image (the built-in emblem at training view 0). Each row: cover PSNR/SSIM and hidden PSNR/SSIM on
held-out views (the image at its own view), the hidden PSNR the release alone gives (the scene
decoder's output against the hidden target), release size, FPS of the public and hidden renders,
Gaussians and training seconds, all measured on the release reopened from disk with its key.

    python scripts/gs_hider.py                                   # CPU demo scale: 128x96, 600 iterations
    python scripts/gs_hider.py --width 1920 --height 1080 --iterations 4000 --device cuda
"""
import argparse
import json
import os
import time
from pathlib import Path

import torch

from securegs_warp.baselines.gs_hider import (GSHiderModel, evaluate_gs_hider, hidden_payload, release_bytes,
                                              train_gs_hider)
from securegs_warp.cli.common import SCENE_FLAGS, TRAIN_FLAGS, add_config_flags, config_from_args, quiet_warp
from securegs_warp.config import GSHiderConfig, RunConfig, TrainConfig
from securegs_warp.io.atomic import atomic_write

# What the synthetic scene renders as hidden views: by default the other built-in scene, seen from
# every camera (GS-Hider's 3D scene hiding); --hide OBJECT --level scene hides an object inside the
# cover, as SecureGS compares GS-Hider.
HIDDEN_FLAGS = (("--hide", "scene.hidden", "synthetic scenes: 'scene' or an object (mug, lamp, pawn, robot)"),
                ("--level", "scene.level", "for an object: 'scene' (inside the cover) or 'object' (alone)"))
DEFAULTS = {"train.iterations": 600, "scene.hidden": "scene", "scene.level": "scene"}


def progress(step: int, stats: dict) -> None:
    if step % 100 == 0:
        print(f"  step {step}: psnr {stats['psnr']:.2f}, hidden {stats['psnr_hidden']:.2f}, "
              f"{stats['gaussians']} Gaussians", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_config_flags(ap, SCENE_FLAGS + TRAIN_FLAGS + HIDDEN_FLAGS, DEFAULTS)
    ap.add_argument("--payloads", default="scene,image", help="comma-separated payload specs")
    ap.add_argument("--decoder-width", type=int, default=GSHiderConfig.decoder_width)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", default=os.environ.get("OUT", "runs/gs_hider"))
    args = ap.parse_args()
    quiet_warp()
    run = config_from_args(args, RunConfig(train=TrainConfig(model="3dgs")), DEFAULTS, device=args.device)
    out = Path(args.out)
    scene = run.scene.load()
    config = GSHiderConfig(decoder_width=args.decoder_width)
    rows = []
    for spec in args.payloads.split(","):
        payload = hidden_payload(scene, spec, args.device)
        t0 = time.perf_counter()
        model = train_gs_hider(scene, payload, run.train.iterations, run.train.seed, args.device, config,
                               train=run.train, on_step=progress)
        seconds = time.perf_counter() - t0
        public, key = model.save(out / spec.split(":")[0])
        reopened = GSHiderModel.load(public, key, device=args.device)
        metrics = evaluate_gs_hider(reopened, scene, payload)
        rows.append({"payload": spec, **metrics, "release_mb": release_bytes(public) / 1e6, "train_s": seconds})
        print(json.dumps(rows[-1]), flush=True)
    atomic_write(out / "metrics.json", lambda f: f.write(json.dumps(rows, indent=1).encode()))
    spec = run.scene
    print(f"\n{spec.width}x{spec.height}, {spec.n_train}+{spec.n_test} views, {run.train.iterations} iterations, "
          f"decoder width {args.decoder_width}, {args.device}")
    print("| payload | cover PSNR | cover SSIM | hidden PSNR | hidden SSIM | hidden PSNR, release alone | release MB "
          "| FPS public | FPS hidden | Gaussians | train s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['payload']} | {r['psnr_public']:.2f} | {r['ssim_public']:.3f} | {r['psnr_hidden']:.2f} | "
              f"{r['ssim_hidden']:.3f} | {r['psnr_hidden_public']:.2f} | {r['release_mb']:.2f} | "
              f"{r['fps_public']:.1f} | {r['fps_hidden']:.1f} | {r['gaussians']:,} | {r['train_s']:.0f} |")


if __name__ == "__main__":
    main()
