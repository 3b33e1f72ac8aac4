"""Tile intersections per Gaussian with ellipse and with rectangle binning on the benchmark scenes.

For each scene (securegs_warp.benchmark.make_scene, the camera of scripts/bench_rasterizer.py) it
renders once with ``tile_overlap="rectangle"`` (gsplat's binning) and once with ``"ellipse"``, and
prints the intersections per Gaussian and per visible Gaussian of each, their ratio, and whether the
two images are bit-identical. A count, not a timing: the CPU gives the same numbers as the GPU.

    python scripts/count_intersections.py --sizes 100000 --device cpu
"""
import argparse
import json

import torch
import warp as wp

from securegs_warp import benchmark, rasterize


def count_row(kind: str, n: int, width: int, height: int, device: str, tile_size: int) -> dict:
    """Intersections of both binnings of one scene, and whether their images are identical."""
    scene = benchmark.make_scene(kind, n, device)
    viewmat, K = benchmark.camera(width, height, device)
    row = {"scene": kind, "n": n, "width": width, "height": height, "tile_size": tile_size}
    images = {}
    with torch.no_grad():
        for overlap in ("rectangle", "ellipse"):
            image, alpha, info = rasterize(**scene, viewmat=viewmat, K=K, width=width, height=height,
                                           tile_size=tile_size, tile_overlap=overlap)
            visible = int((info["radii"][:, 0] > 0).sum())
            row[f"{overlap}_per_gaussian"] = int(info["n_intersections"]) / max(n, 1)
            row[f"{overlap}_per_visible"] = int(info["n_intersections"]) / max(visible, 1)
            images[overlap] = (image, alpha)
    row["ratio"] = row["ellipse_per_gaussian"] / max(row["rectangle_per_gaussian"], 1e-30)
    row["identical_images"] = all(torch.equal(a, b) for a, b in zip(images["rectangle"], images["ellipse"]))
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    benchmark.add_scene_arguments(parser)
    parser.add_argument("--tile-size", type=int, default=16)
    args = parser.parse_args()
    wp.config.quiet = True
    rows = []
    for kind in args.kinds.split(","):
        for n in (int(s) for s in args.sizes.split(",")):
            rows.append(count_row(kind, n, args.width, args.height, args.device, args.tile_size))
            print(json.dumps(rows[-1]), flush=True)
    print(f"\n{args.width}×{args.height}, tile {args.tile_size}\n")
    print("| scene | N | rectangle / Gaussian | ellipse / Gaussian | rectangle / visible | ellipse / visible "
          "| ellipse ÷ rectangle | same image |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['n']:,} | {r['rectangle_per_gaussian']:.2f} | {r['ellipse_per_gaussian']:.2f} | "
              f"{r['rectangle_per_visible']:.2f} | {r['ellipse_per_visible']:.2f} | {r['ratio']:.3f} | "
              f"{'yes' if r['identical_images'] else 'NO'} |")


if __name__ == "__main__":
    main()
