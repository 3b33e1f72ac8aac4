"""The paper's methods side by side on one synthetic scene, payload and budget: Scaffold-GS, SecureGS,
plain 3DGS, 3DGS + StegaNeRF and GS-Hider.
Writes compare_methods.md / .csv / .json and compare_methods.png into --out.

    python scripts/compare_methods.py --preset cpu                       # CPU, demo scale
    python scripts/compare_methods.py --preset gpu1080 --out $OUT        # 1920×1080 on one GPU
    python scripts/compare_methods.py --preset cpu --payload object      # 3D object: geometric leakage

The methods (``--methods``): scaffold and 3dgs (the covers, nothing hidden), securegs (the paper's
SecureGS, with its RDO), securegs_cover (SecureGS in the cover mode, this project's default for an
object, with its robust training and finishing phase; objects only), steganerf (3DGS + StegaNeRF:
images only, after 3dgs, whose scene it fine-tunes) and gs_hider.

``--payload image`` hides the builtin emblem (SecureGS at training view 0, as the paper's single-image
hiding; StegaNeRF in every view's render); ``--payload object`` hides the scene's hidden object
(StegaNeRF cannot: it decodes 2D images). Options after the preset override it.
"""
import argparse
import os
import subprocess
import time
from pathlib import Path

import torch

from securegs_warp import benchmark
from securegs_warp.baselines.comparison import DEFAULT_ATTACKS, METHODS, PAYLOADS, make_setup, plot, run_all, write_report
from securegs_warp.cli.common import quiet_warp
from securegs_warp.data import make_synthetic_scene
from securegs_warp.rasterizer import RasterOptions

PRESETS = {
    # Demo scale on a shared 2-core CPU: a few minutes per method.
    "cpu": {"width": 96, "height": 72, "train_views": 16, "test_views": 4, "iterations": 400, "finetune": 200,
            "device": "cpu"},
    # 1080p on one H100, all methods in under 9 minutes together (progress printed per method).
    "gpu1080": {"width": 1920, "height": 1080, "train_views": 24, "test_views": 4, "iterations": 1500,
                "finetune": 500, "device": "cuda"},
}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", choices=sorted(PRESETS), default="cpu")
    for name in ("width", "height", "train_views", "test_views", "iterations", "finetune"):
        ap.add_argument("--" + name.replace("_", "-"), type=int, help=f"override the preset's {name}")
    ap.add_argument("--device", help="override the preset's device")
    ap.add_argument("--payload", choices=PAYLOADS, default="image")
    ap.add_argument("--hide", default="mug", help="the synthetic scene's hidden object (object payload)")
    ap.add_argument("--methods", default="scaffold,securegs,3dgs,steganerf,gs_hider",
                    help=f"comma-separated, in order, of {', '.join(METHODS)} (steganerf after 3dgs: it "
                         "fine-tunes that cover)")
    ap.add_argument("--attacks", default=",".join(DEFAULT_ATTACKS), help="attack specs, comma-separated ('' for none)")
    ap.add_argument("--seed", type=int, default=0, help="training seed of every method (the scene stays the same)")
    ap.add_argument("--steganerf-tune", choices=("color", "dc", "all"), default="color",
                    help="what StegaNeRF's fine-tuning moves (StegaNeRFConfig.tune; color: the authors')")
    ap.add_argument("--steganerf-antialias", action="store_true",
                    help="StegaNeRF's decoder shrinks the render by averaging, not by bilinear sampling "
                         "(StegaNeRFConfig.decoder_antialias)")
    ap.add_argument("--out", default=os.environ.get("OUT", "runs/compare_methods"))
    args = ap.parse_args()
    p = dict(PRESETS[args.preset])
    p.update({k: v for k, v in vars(args).items() if k in p and v is not None})
    if benchmark.on_cuda(p["device"]) and not torch.cuda.is_available():
        ap.error("the preset wants CUDA and this torch has none; pass --device cpu")
    if p["device"] == "cpu":
        torch.set_num_threads(max(1, (os.cpu_count() or 2) // 2))
    quiet_warp()
    t0 = time.perf_counter()
    scene = make_synthetic_scene(hidden=args.hide, level="object", width=p["width"], height=p["height"],
                                 n_train=p["train_views"], n_test=p["test_views"], device=p["device"])
    print(f"scene {p['width']}×{p['height']}, {p['train_views']} + {p['test_views']} views, "
          f"{len(scene.points)} points, {time.perf_counter() - t0:.0f} s", flush=True)
    setup = make_setup(scene, args.payload, p["iterations"], p["finetune"], RasterOptions.for_device(p["device"]),
                       torch.device(p["device"]), [a for a in args.attacks.split(",") if a],
                       log=lambda line: print(line, flush=True), seed=args.seed,
                       steganerf={"tune": args.steganerf_tune, "decoder_antialias": args.steganerf_antialias})
    try:
        # "-dirty" when the tree is not the commit's (a copy with a stale .git, uncommitted edits)
        commit = subprocess.run(["git", "describe", "--always", "--dirty"], capture_output=True, text=True,
                                check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    device = benchmark.device_label(p["device"])
    meta = {**p, "device": device, "payload": args.payload, "hide": args.hide, "preset": args.preset,
            "date": time.strftime("%Y-%m-%d", time.gmtime()), "commit": commit, "attacks": setup.attacks,
            "seed": args.seed, "steganerf_tune": args.steganerf_tune,
            "steganerf_antialias": args.steganerf_antialias}
    out = Path(args.out)
    rows = run_all(setup, [m for m in args.methods.split(",") if m],
                   on_row=lambda rows: write_report(out, rows, meta))
    table = write_report(out, rows, meta)
    try:
        plot(out / "compare_methods.png", rows)
    except ImportError:
        print("no plot: matplotlib is not installed")
    print(f"\ntotal {time.perf_counter() - t0:.0f} s\n\n{table}")


if __name__ == "__main__":
    main()
