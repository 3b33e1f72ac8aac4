"""Does 3DGS + StegaNeRF learn its hidden image? A tiny synthetic scene, a short 3DGS run, then
StegaNeRF's fine-tuning, printing the training hidden MSE (and its PSNR) against the PSNR of a flat
image of the hidden image's mean colour (what a decoder that learnt nothing scores), then the
held-out evaluation. CPU-sized; one process.

    python scripts/steganerf_diagnose.py --size 64 48 --steps 1000 --decoder-levels 3 --decoder-size 0
"""
import argparse
import math

import torch

from securegs_warp.baselines.steganerf import StegaNeRF, hidden_image_for
from securegs_warp.config import StegaNeRFConfig, TrainConfig
from securegs_warp.data import make_synthetic_scene
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.train import GaussianTrainer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, nargs=2, default=(64, 48), metavar=("W", "H"))
    parser.add_argument("--cover-steps", type=int, default=60)
    parser.add_argument("--steps", type=int, default=1000, help="fine-tuning steps")
    defaults = StegaNeRFConfig()
    parser.add_argument("--decoder-levels", type=int, default=defaults.decoder_levels)
    parser.add_argument("--decoder-size", type=int, default=defaults.decoder_size)
    parser.add_argument("--decoder-antialias", action="store_true",
                        help="shrink the render to the decoder's size by averaging (StegaNeRFConfig.decoder_antialias)")
    parser.add_argument("--classifier-lr", type=float, default=defaults.classifier_lr)
    parser.add_argument("--tune", choices=("color", "dc", "all"), default=defaults.tune)
    parser.add_argument("--no-gradient-masking", dest="gradient_masking", action="store_false")
    parser.add_argument("--seed", type=int, default=0, help="the scene's cameras and the networks' initialisation")
    args = parser.parse_args()

    torch.manual_seed(args.seed)
    raster = RasterOptions(tile_size=8)
    scene = make_synthetic_scene(hidden="mug", level="object", width=args.size[0], height=args.size[1],
                                 n_train=6, n_test=2, n_points=600, seed=args.seed)
    cover = GaussianTrainer(scene, TrainConfig(iterations=args.cover_steps, raster=raster, model="3dgs"))
    for _ in range(args.cover_steps):
        cover.step()
    hidden = torch.as_tensor(hidden_image_for(scene))
    flat = ((hidden - hidden.mean(dim=(0, 1))) ** 2).mean().item()
    print(f"flat image of the hidden image's mean colour: {-10 * math.log10(flat):.2f} dB")
    config = StegaNeRFConfig(iterations=args.steps, decoder_levels=args.decoder_levels,
                             decoder_size=args.decoder_size, decoder_antialias=args.decoder_antialias,
                             classifier_lr=args.classifier_lr, tune=args.tune,
                             gradient_masking=args.gradient_masking)
    stega = StegaNeRF(cover.model, scene, hidden, config, raster=raster, background=cover.background, seed=args.seed)

    def report(step: int, stats: dict) -> None:
        if step == 1 or step % max(1, args.steps // 10) == 0:
            print(f"step {step:5d}  hidden mse {stats['hidden']:.4f} ({-10 * math.log10(stats['hidden']):.2f} dB)  "
                  f"clean {stats['clean']:.4f}  classifier {stats['classifier']:.3f}  rgb {stats['rgb']:.2e}", flush=True)

    stega.train(report)
    result = stega.evaluate(timing_repeats=1)
    print("held-out: " + "  ".join(f"{k} {v:.2f}" for k, v in result.items()
                                    if not k.startswith("fps") and v is not None))
    # The same reading on the training views, and the classifier's belief on each view's fine-tuned
    # render: a gap between training and held-out views is what fitting each view separately gives.
    with torch.no_grad():
        renders = {split: [stega.render(c)["image"] for c in getattr(scene, split)] for split in ("train", "test")}
        for split, images in renders.items():
            mse = torch.stack([((stega.reveal(i) - stega.hidden) ** 2).mean() for i in images])
            belief = stega.classifier(torch.stack([i.permute(2, 0, 1) for i in images]))
            print(f"{split} views: hidden {(-10 * torch.log10(mse)).mean().item():.2f} dB  "
                  f"classifier belief {' '.join(f'{b:.2f}' for b in belief.tolist())}")


if __name__ == "__main__":
    main()
