"""Where a render's measured time goes on the GPU: the host's time, the GPU's busy time and the
GPU's idle time inside each measured call, for ours (eager and captured) and gsplat side by side.

For each renderer and pass (forward; forward+backward of the loss ``benchmark.timed`` uses) it
prints: the measured time (CUDA events, median), the host time of the call (perf_counter, without
waiting for the GPU), the GPU's busy time (the union of its kernels, copies and memsets in a
torch.profiler trace of a few calls, each started on an idle GPU), the GPU's idle time (measured −
busy) and the host launches per call. The JSON rows add, from the trace, the idle time before the
first launch ("lead") and after it ("gaps"), and the gaps by the code that launched the work that
ended them: the profiler (with Python stacks) slows the host, so these are larger than in an
unprofiled call and tell where, not how much.

    python scripts/profile_render.py                       # 1M random Gaussians, 1920×1080
    python scripts/profile_render.py --sizes 100000,1000000 --kinds random,realistic --out OUT

CUDA only. The trace's analysis is securegs_warp.render_profile's.
"""
import argparse
import json
import os

import torch
import warp as wp

from securegs_warp import benchmark
from securegs_warp.io.atomic import atomic_write
from securegs_warp.render_profile import host_ms, timeline, trace


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    benchmark.add_scene_arguments(parser)
    parser.set_defaults(sizes="1000000", kinds="random")
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--traced", type=int, default=5, help="calls in each profiler trace")
    parser.add_argument("--out", default=os.environ.get("OUT"), help="folder for profile_render.json")
    args = parser.parse_args()
    if not benchmark.on_cuda(args.device):
        parser.error("CUDA only: the GPU's idle time is what this measures")
    wp.config.quiet = True
    wp.init()
    renderers = {"ours": benchmark.parse_options(""), "captured": benchmark.parse_options("capture=true")}
    calls = {name: (lambda s, v, k, w, h, o=opts: benchmark.ours(s, v, k, w, h, o)) for name, opts in renderers.items()}
    if benchmark.gsplat_available(args.device):
        calls["gsplat"] = benchmark.gsplat_render
    rows = []
    for kind in args.kinds.split(","):
        for n in map(int, args.sizes.split(",")):
            scene = benchmark.make_scene(kind, n, args.device)
            for t in scene.values():
                t.requires_grad_(True)
            viewmat, K = benchmark.camera(args.width, args.height, args.device)
            grads = benchmark.cotangents(args.width, args.height, args.device)
            for name, fn in calls.items():
                for backward in (False, True):
                    call = lambda fn=fn: fn(scene, viewmat, K, args.width, args.height)  # noqa: E731
                    once = benchmark.render_call(call, backward, grads)
                    row = {"scene": kind, "n": n, "renderer": name, "pass": "fwd+bwd" if backward else "fwd"}
                    # The forward alone as bench_rasterizer times it: without autograd.
                    with torch.set_grad_enabled(backward):
                        row["measured_ms"] = benchmark.timed(call, backward, args.device, 3, args.runs, grads)
                        row["host_ms"] = host_ms(once, args.runs)
                        row.update(timeline(trace(once, args.traced)))
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    print(f"\n{benchmark.device_label(args.device)}, {args.width}×{args.height}; ms per call\n")
    print("| scene | N | renderer | pass | measured | host | GPU busy | GPU idle | launches |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['n']:,} | {r['renderer']} | {r['pass']} | {r['measured_ms']:.3f} | {r['host_ms']:.3f} "
              f"| {r['gpu_busy_ms']:.3f} | {r['measured_ms'] - r['gpu_busy_ms']:.3f} | {r['launches']:.0f} |")
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        data = json.dumps({"device": benchmark.device_label(args.device), "rows": rows}, indent=1).encode()
        atomic_write(os.path.join(args.out, "profile_render.json"), lambda f: f.write(data))


if __name__ == "__main__":
    main()
