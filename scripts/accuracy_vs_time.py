"""Accuracy against time: what each accuracy knob costs, measured on the same scenes in one run.

    python scripts/accuracy_vs_time.py --sections raster           # CPU: 2k Gaussians vs the float64
                                                                   # reference, 20k for timing
    python scripts/accuracy_vs_time.py --sections raster --large   # GPU: 1M at 1920×1080 for timing

A sweep *section* is a function ``(args) -> rows`` (one dict per point and scene) registered in
``SECTIONS`` with the columns its plot draws: ``x`` a time (lower is better) and ``y`` an accuracy
(higher is better). Rows share ``section``, ``scene`` and ``point``; other keys are the section's own
columns. The rasterizer section moves one knob at a time away from the default (alpha_min,
transmittance_min, radius_rule, tile_size, fast_math, color_storage, gather) and measures, per point:

- error on a small scene (``--small``) against the float64 dense reference (securegs_warp/reference.py)
  rendered with the *default* options, so that a knob's error is its departure from the exact
  default render: image PSNR and the largest relative gradient error over the inputs (as
  securegs_warp/raster_cases.py computes it), for the same random cotangents;
- error on the timing scene (``--large`` or ``--timing``), too big for the dense reference, against
  the default configuration's own float32 render: image PSNR and relative gradient error;
- time on both: median forward and forward+backward over ``--rounds`` rounds that visit every point
  in turn (so that load from other processes falls on all points alike); CUDA events on the GPU,
  perf_counter on the CPU (securegs_warp.benchmark.timed).

Scenes are securegs_warp.benchmark.make_scene's (bench_rasterizer.py's), with the scales multiplied
by 1920/width so that the Gaussians cover as many pixels as in the 1080p benchmark (1M at 1920×1080
is its scene unchanged).

The model section trains Scaffold-GS (ScaffoldTrainer, RasterOptions.for_device's tile size) on the
built-in synthetic scene (--width × --height, --train-views/--test-views) for --iterations from
scratch, moving one knob at a time from TrainConfig's defaults: Gaussians per anchor k (n_offsets
5/10/20), feat_dim (16/32/64; also the MLPs' hidden width) and the feature bank on; the default
model is also evaluated with its anchor features rounded to float16 (half-precision storage). Per point:
held-out PSNR and SSIM (trainer.evaluate), render_ms (ms per held-out frame, from evaluate's
render_fps over --rounds passes), train_s and step_ms (step() wall time only), anchors and
gaussians (those the first held-out view keeps after culling). Its plot draws render_ms, not train
time: k and the MLP width are paid at every frame a viewer draws, training once.

The training section trains the default configuration once and evaluates at 10/25/50/100% of
--iterations: held-out PSNR against train_s (trainer.train_seconds, which counts step() only, so
evaluation does not pollute it). Both sections warm up a throwaway trainer first so that kernel
compilation is not timed.

    python scripts/accuracy_vs_time.py --sections model,training           # CPU: 64×48, 150 iterations
    python scripts/accuracy_vs_time.py --sections model,training --large   # GPU: 1920×1080, 2000 iterations

Writes accuracy_vs_time.csv, accuracy_vs_time.md and accuracy_vs_time.png (time against PSNR per
section and scene, Pareto front marked) to --out and prints the markdown table last. The sections
and outputs are securegs_warp.benchmark's (SECTIONS, write); this script parses the arguments.
"""
import argparse
import datetime
import os

import torch
import warp as wp

from securegs_warp import benchmark
from securegs_warp.benchmark import SCENE_KINDS, SECTIONS, write


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated, of {list(SECTIONS)}")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--kind", default="realistic", choices=SCENE_KINDS, help="raster: scene kind")
    parser.add_argument("--small", type=int, nargs=3, default=[2000, 160, 120], metavar=("N", "W", "H"),
                        help="scene compared with the float64 dense reference (its memory grows as N·W·H)")
    parser.add_argument("--timing", type=int, nargs=3, default=[20000, 320, 240], metavar=("N", "W", "H"),
                        help="larger scene, compared with the default configuration")
    parser.add_argument("--large", action="store_true",
                        help="GPU preset: raster timing scene of 1M Gaussians at 1920×1080; model/training "
                             "at 1920×1080 for 2000 iterations")
    parser.add_argument("--iterations", type=int, default=None,
                        help="model/training: iterations per run (default 150, --large 2000)")
    parser.add_argument("--width", type=int, default=None, help="model/training: synthetic scene width "
                                                                "(default 64, --large 1920)")
    parser.add_argument("--height", type=int, default=None, help="model/training: synthetic scene height "
                                                                 "(default 48, --large 1080)")
    parser.add_argument("--train-views", type=int, default=16, help="model/training: synthetic training views")
    parser.add_argument("--test-views", type=int, default=4, help="model/training: synthetic held-out views")
    parser.add_argument("--points", type=int, default=None,
                        help="model/training: initial points, one anchor per voxel (default 1000, --large 4000)")
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds over all points")
    parser.add_argument("--out", default=os.environ.get("OUT") or "runs/accuracy_vs_time")
    args = parser.parse_args()
    unknown = set(args.sections.split(",")) - set(SECTIONS)
    if unknown:
        parser.error(f"unknown sections {sorted(unknown)}; known: {list(SECTIONS)}")
    preset = (2000, 1920, 1080, 4000) if args.large else (150, 64, 48, 1000)
    for name, value in zip(("iterations", "width", "height", "points"), preset):
        if getattr(args, name) is None:
            setattr(args, name, value)
    wp.config.quiet = True
    wp.init()

    rows = [row for name in args.sections.split(",") for row in SECTIONS[name].run(args)]
    device = benchmark.device_label(args.device) if benchmark.on_cuda(args.device) else f"CPU ({os.cpu_count()} cores)"
    title = (f"{device}, warp {wp.__version__}, torch {torch.__version__}, {datetime.date.today()}; "
             f"times: median of {args.rounds} interleaved rounds, ms")
    print(write(rows, args.out, title))


if __name__ == "__main__":
    main()
