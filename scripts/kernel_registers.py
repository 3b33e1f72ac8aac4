"""Registers and local-memory frame per thread of the blending kernels compiled for a CUDA
architecture (default sm_90, the H100), for each backward variant of RasterOptions: read from the
cubins Warp's NVRTC produces, so it runs without a GPU. With the block barriers of each kernel's
PTX: in all, and per batch of Gaussians (those of its walk over the batches), and the backward's
warp shuffle and global atomic instructions.

    python scripts/kernel_registers.py                 # 3 channels, tiles of 16, blocks of 256
    python scripts/kernel_registers.py --channels 16 --arch 80
"""
import argparse

import warp as wp

from securegs_warp.cuda_resources import kernel_ptx, kernel_resources, ptx_barriers, ptx_warp_traffic
from securegs_warp.rasterizer import RasterOptions, blend_kernels_for

# (label, RasterOptions fields): the variants scripts/bench_rasterizer.py times on the GPU. Each names
# its gather, fast_math and backward_pixels, so the rows keep their meaning whatever the defaults are.
_FIELDS = {"gather": "fields", "fast_math": False, "backward_pixels": 1}
_PACKED = {"gather": "packed", "fast_math": False, "backward_pixels": 1}
VARIANTS = [
    ("gather=fields", _FIELDS),
    ("gather=fields, backward_walk=warp", {**_FIELDS, "backward_walk": "warp"}),
    ("+ backward_max_registers=80", {**_FIELDS, "backward_walk": "warp", "backward_max_registers": 80}),
    ("+ backward_max_registers=64", {**_FIELDS, "backward_walk": "warp", "backward_max_registers": 64}),
    ("+ fast_math", {**_FIELDS, "backward_walk": "warp", "fast_math": True}),
    ("+ fast_math, backward_max_registers=64",
     {**_FIELDS, "backward_walk": "warp", "fast_math": True, "backward_max_registers": 64}),
    ("gather=fields, color_storage=float16", {**_FIELDS, "color_storage": "float16"}),
    ("gather=packed", _PACKED),
    ("gather=packed, fast_math", {**_PACKED, "fast_math": True}),
    ("gather=packed, color_storage=float16", {**_PACKED, "color_storage": "float16"}),
    ("gather=packed, fast_math, backward_pixels=2 (the defaults)", {**_PACKED, "fast_math": True, "backward_pixels": 2}),
    ("the defaults, backward_walk=warp", {**_PACKED, "fast_math": True, "backward_pixels": 2, "backward_walk": "warp"}),
    ("gather=packed, fast_math, backward_pixels=4", {**_PACKED, "fast_math": True, "backward_pixels": 4}),
]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--channels", type=int, default=3)
    parser.add_argument("--arch", type=int, default=90)
    args = parser.parse_args()
    wp.config.quiet = True
    wp.init()
    print(f"sm_{args.arch}, {args.channels} channels, tiles of 16, blocks of 256, no depth\n")
    print("| options | forward registers | forward frame bytes | backward registers | backward frame bytes "
          "| forward barriers (per batch) | backward barriers (per batch) | backward shuffles | backward atomics |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, fields in VARIANTS:
        forward, backward = blend_kernels_for(RasterOptions(**fields), args.channels, False, True)
        f, b = kernel_resources(forward, args.arch), kernel_resources(backward, args.arch)
        forward_ptx, backward_ptx = kernel_ptx(forward, args.arch), kernel_ptx(backward, args.arch)
        fb, bb = ptx_barriers(forward_ptx), ptx_barriers(backward_ptx)
        traffic = ptx_warp_traffic(backward_ptx)
        print(f"| {label} | {f['registers']} | {f['frame_bytes']} | {b['registers']} | {b['frame_bytes']} "
              f"| {fb['barriers']} ({fb['loop_barriers']}) | {bb['barriers']} ({bb['loop_barriers']}) "
              f"| {traffic['shuffles']} | {traffic['atomics']} |", flush=True)


if __name__ == "__main__":
    main()
