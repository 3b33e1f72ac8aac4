"""Rasterizer speed, side by side with gsplat when it is installed.

For each scene it renders the same inputs with ``securegs_warp.rasterize`` and ``gsplat.rasterization``
(classic, packed=False, same defaults), printing the forward and forward+backward medians, the
ratio ours/gsplat, the largest image difference, and a per-kernel breakdown of our render.

    python scripts/bench_rasterizer.py                       # GPU: 100k, 1M, 3M at 1920×1080
    python scripts/bench_rasterizer.py --device cpu --sizes 2000 --width 320 --height 180 --runs 3

Absolute times mean something only on the GPU; the ratios are measured in one run, interleaved.
"""
import argparse
import json
import math
import os
import statistics
import time

import torch
import warp as wp

from securegs_warp import rasterize


def make_scene(kind: str, n: int, device: str, seed: int = 0):
    """Gaussians in an 8×4.5×4 box 6 units in front of the camera (gsplat's benchmark set-up).

    kind "random": scales uniform in [0.002, 0.022]. kind "realistic": log-normal scales (median
    0.006, a long tail up to ~0.3), like a trained scene: many small Gaussians, few large ones.
    """
    g = torch.Generator(device="cpu").manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([8.0, 4.5, 4.0]) + torch.tensor([0.0, 0.0, 6.0])
    quats = torch.randn(n, 4, generator=g)
    if kind == "random":
        scales = torch.rand(n, 3, generator=g) * 0.02 + 0.002
        opacities = torch.rand(n, generator=g)
    elif kind == "realistic":
        scales = torch.exp(torch.randn(n, 3, generator=g) * 0.8 + math.log(0.006)).clamp(max=0.3)
        opacities = torch.sigmoid(torch.randn(n, generator=g) * 2.0)
    else:
        raise ValueError(f"unknown scene kind {kind!r}")
    colors = torch.rand(n, 3, generator=g)
    return {k: v.to(device) for k, v in dict(means=means, quats=quats, scales=scales, opacities=opacities,
                                             colors=colors).items()}


def camera(width, height, device):
    f = 1100.0 * width / 1920.0
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float32, device=device)
    return torch.eye(4, device=device), K


def ours(scene, viewmat, K, width, height, **options):
    image, alpha, _ = rasterize(**scene, viewmat=viewmat, K=K, width=width, height=height, **options)
    return image, alpha


def parse_variant(text: str):
    """"NAME:key=value,key=value" → (NAME, {key: value}) with ints, floats and booleans parsed."""
    name, _, spec = text.partition(":")
    options = {}
    for item in filter(None, spec.split(",")):
        key, _, value = item.partition("=")
        for cast in (int, float):
            try:
                value = cast(value)
                break
            except ValueError:
                continue
        options[key] = {"True": True, "False": False}.get(value, value) if isinstance(value, str) else value
    return name, options


def gsplat_render(scene, viewmat, K, width, height):
    import gsplat

    image, alpha, _ = gsplat.rasterization(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                           scene["colors"], viewmat[None], K[None], width, height, packed=False)
    return image[0], alpha[0]


def timed(fn, backward: bool, device: str, warmup: int, runs: int, grads):
    """Median milliseconds of fn() (and of a backward through it)."""
    def once():
        image, alpha = fn()
        if backward:
            (image * grads[0]).sum().add_((alpha * grads[1]).sum()).backward()

    for _ in range(warmup):
        once()
    times = []
    for _ in range(runs):
        if device == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            once()
            end.record()
            torch.cuda.synchronize()
            times.append(start.elapsed_time(end))
        else:
            t0 = time.perf_counter()
            once()
            times.append(1000 * (time.perf_counter() - t0))
    return statistics.median(times)


def kernel_breakdown(scene, viewmat, K, width, height):
    """Per-kernel GPU milliseconds of one forward+backward of ours (Warp's CUDA activity timer)."""
    with wp.ScopedTimer("render", cuda_filter=wp.TIMING_ALL, synchronize=True, print=False) as timer:
        image, alpha = ours(scene, viewmat, K, width, height)
        (image.sum() + alpha.sum()).backward()
        torch.cuda.synchronize()
    totals = {}
    for r in timer.timing_results:
        totals[r.name[:48]] = totals.get(r.name[:48], 0.0) + r.elapsed
    return dict(sorted(totals.items(), key=lambda kv: -kv[1]))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--sizes", default="100000,1000000,3000000", help="comma-separated Gaussian counts")
    parser.add_argument("--kinds", default="random,realistic")
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--out", default=os.environ.get("OUT"), help="folder for results.json and results.md")
    parser.add_argument("--options", default="", help="options of ours, e.g. tile_size=8,fast_math=True "
                                                          "(default: gsplat's defaults)")
    parser.add_argument("--variant", action="append", default=[],
                        help="extra configuration of ours timed alongside, e.g. b64:backward_block=64")
    args = parser.parse_args()
    wp.config.quiet = True
    wp.init()
    try:
        import gsplat  # noqa: F401
        have_gsplat = args.device == "cuda"
    except ImportError:
        have_gsplat = False

    device = args.device
    viewmat, K = camera(args.width, args.height, device)
    rows = []
    for kind in args.kinds.split(","):
        for n in (int(s) for s in args.sizes.split(",")):
            scene = make_scene(kind, n, device)
            for t in scene.values():
                t.requires_grad_(True)
            g = torch.Generator(device="cpu").manual_seed(1)
            grads = (torch.rand(args.height, args.width, 3, generator=g).to(device),
                     torch.rand(args.height, args.width, 1, generator=g).to(device))
            _, ours_options = parse_variant(":" + args.options)
            renderers = {"ours": lambda *a: ours(*a, **ours_options)}
            for name, options in map(parse_variant, args.variant):
                renderers[name] = lambda *a, options=options: ours(*a, **options)
            if have_gsplat:
                renderers["gsplat"] = gsplat_render
            row = {"scene": kind, "n": n, "width": args.width, "height": args.height}
            for name, fn in renderers.items():
                call = lambda fn=fn, scene=scene: fn(scene, viewmat, K, args.width, args.height)  # noqa: E731
                with torch.no_grad():
                    row[f"{name}_fwd_ms"] = timed(call, False, device, args.warmup, args.runs, grads)
                row[f"{name}_fwdbwd_ms"] = timed(call, True, device, args.warmup, args.runs, grads)
            with torch.no_grad():
                img, alpha = renderers["ours"](scene, viewmat, K, args.width, args.height)
                _, _, info = rasterize(**scene, viewmat=viewmat, K=K, width=args.width, height=args.height,
                                       **ours_options)
                row["intersections"] = int(info["n_intersections"])
                row["visible"] = int((info["radii"][:, 0] > 0).sum())
                if have_gsplat:
                    ref, ref_alpha = gsplat_render(scene, viewmat, K, args.width, args.height)
                    diff = (img - ref).abs()
                    row["max_image_diff"] = float(diff.max())
                    row["pixels_over_1e-4"] = int((diff.amax(-1) > 1e-4).sum())
                    row["max_alpha_diff"] = float((alpha - ref_alpha).abs().max())
                    row["fwd_ratio"] = row["ours_fwd_ms"] / row["gsplat_fwd_ms"]
                    row["fwdbwd_ratio"] = row["ours_fwdbwd_ms"] / row["gsplat_fwdbwd_ms"]
            if device == "cuda" and n == 1000000:
                row["breakdown_ms"] = kernel_breakdown(scene, viewmat, K, args.width, args.height)
            rows.append(row)
            print(json.dumps(row), flush=True)
            del scene, grads

    header = "| scene | N | ours fwd ms | ours fwd+bwd ms |" + (
        " gsplat fwd ms | gsplat fwd+bwd ms | fwd ratio | fwd+bwd ratio | max |Δimage| |" if have_gsplat else "")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in rows:
        line = f"| {r['scene']} | {r['n']:,} | {r['ours_fwd_ms']:.2f} | {r['ours_fwdbwd_ms']:.2f} |"
        if have_gsplat:
            line += (f" {r['gsplat_fwd_ms']:.2f} | {r['gsplat_fwdbwd_ms']:.2f} | {r['fwd_ratio']:.2f} |"
                     f" {r['fwdbwd_ratio']:.2f} | {r['max_image_diff']:.1e} |")
        lines.append(line)
    device_name = torch.cuda.get_device_name() if device == "cuda" else "cpu"
    table = (f"{device_name}, {args.width}×{args.height}, median of {args.runs} runs, ours with "
             f"{args.options or 'default options'}\n\n" + "\n".join(lines))
    print(table)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, "bench_rasterizer.json"), "w") as f:
            json.dump({"device": device_name, "rows": rows}, f, indent=1)
        with open(os.path.join(args.out, "bench_rasterizer.md"), "w") as f:
            f.write(table + "\n")


if __name__ == "__main__":
    main()
