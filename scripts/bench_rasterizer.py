"""Rasterizer speed, side by side with gsplat when it is installed.

For each scene it renders the same inputs with ``securegs_warp.rasterize`` (eager, and "captured":
the same options with ``capture=true``, replayed from Warp graphs) and ``gsplat.rasterization``
(classic, packed=False, same defaults), printing the forward and forward+backward medians, the
ratios to gsplat, the largest image differences, and, on CUDA at 1M Gaussians, a per-kernel
breakdown (torch.profiler) of every renderer's forward+backward, each with its own options.

    python scripts/bench_rasterizer.py                       # GPU: 100k, 1M, 3M at 1920×1080
    python scripts/bench_rasterizer.py --device cpu --sizes 2000 --width 320 --height 180 --runs 3

Absolute times mean something only on the GPU; the ratios are measured in one run (each renderer's
runs one after the other, so drift between them enters the ratios).
The scenes, timing and comparisons are securegs_warp.benchmark's.
"""
import argparse
import json
import os

import torch
import warp as wp

from securegs_warp import benchmark
from securegs_warp.io.atomic import atomic_write


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    benchmark.add_scene_arguments(parser)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--out", default=os.environ.get("OUT"), help="folder for bench_rasterizer.json and .md")
    parser.add_argument("--options", default="", help="options of ours, e.g. tile_size=8,fast_math=true "
                                                          "(default: gsplat's defaults)")
    parser.add_argument("--variant", action="append", default=[],
                        help="extra configuration of ours timed alongside, e.g. b64:backward_block=64")
    parser.add_argument("--no-captured", action="store_true",
                        help="leave out the captured variant (--options with capture=true)")
    args = parser.parse_args()
    try:
        options = benchmark.parse_options(args.options)
        variants = [benchmark.parse_variant(text) for text in args.variant]
        if not args.no_captured and not options.capture:
            variants.insert(0, benchmark.parse_variant("captured:capture=true", options))
        sizes = [int(s) for s in args.sizes.split(",")]
    except ValueError as e:
        parser.error(str(e))
    kinds = args.kinds.split(",")
    if set(kinds) - set(benchmark.SCENE_KINDS):
        parser.error(f"unknown --kinds {sorted(set(kinds) - set(benchmark.SCENE_KINDS))}; "
                     f"known: {', '.join(benchmark.SCENE_KINDS)}")
    wp.config.quiet = True
    wp.init()

    with_gsplat = benchmark.gsplat_available(args.device)
    rows = []
    for kind in kinds:
        for n in sizes:
            row = benchmark.benchmark_scene(kind, n, args.width, args.height, args.device, options, variants,
                                            with_gsplat=with_gsplat, warmup=args.warmup, runs=args.runs,
                                            breakdown=benchmark.on_cuda(args.device) and n == 1_000_000)
            rows.append(row)
            print(json.dumps(row), flush=True)

    device_name = benchmark.device_label(args.device)
    table = benchmark.benchmark_table(rows, f"{device_name}, {args.width}×{args.height}, median of {args.runs} "
                                            f"runs, ours with {benchmark.options_text(options) or 'default options'}")
    print(table)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        data = json.dumps({"device": device_name, "rows": rows}, indent=1).encode()
        atomic_write(os.path.join(args.out, "bench_rasterizer.json"), lambda f: f.write(data))
        atomic_write(os.path.join(args.out, "bench_rasterizer.md"), lambda f: f.write((table + "\n").encode()))


if __name__ == "__main__":
    main()
