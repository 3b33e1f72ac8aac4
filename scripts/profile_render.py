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

CUDA only.
"""
import argparse
import collections
import json
import os
import statistics
import tempfile
import time

import torch
import warp as wp

from securegs_warp import benchmark

GPU_CATEGORIES = ("kernel", "gpu_memcpy", "gpu_memset")
LAUNCHER_CATEGORIES = ("cuda_runtime", "cuda_driver")
# Gaps shorter than this are a launch's own latency, not the host holding the GPU back.
GAP_US = 5.0


def host_ms(once, runs: int) -> float:
    """Median host milliseconds of ``once()``, each call started on an idle GPU and not waited for."""
    times = []
    for _ in range(runs):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        once()
        times.append(1000 * (time.perf_counter() - t0))
    torch.cuda.synchronize()
    return statistics.median(times)


def trace(once, runs: int) -> list:
    """The chrome-trace events of ``runs`` calls of ``once()``, each in a "call" annotation
    started on an idle GPU."""
    from torch.profiler import ProfilerActivity, profile, record_function

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA], with_stack=True) as prof:
        for _ in range(runs):
            torch.cuda.synchronize()
            with record_function("call"):
                once()
        torch.cuda.synchronize()
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "trace.json")
        prof.export_chrome_trace(path)
        with open(path) as f:
            return [e for e in json.load(f)["traceEvents"] if e.get("ph") == "X"]


def _label(launcher: dict, python: dict) -> str:
    """The innermost frame of this project's or gsplat's code around a launch (else the launch's
    own name): 'file.py(line): function'."""
    best = None
    for e in python.get(launcher["tid"], ()):
        if e["ts"] <= launcher["ts"] <= e["ts"] + e["dur"] and ("securegs_warp" in e["name"] or "gsplat" in e["name"]
                                                                 or "scripts/" in e["name"]):
            if best is None or e["ts"] >= best["ts"]:
                best = e
    if best is None:
        return launcher["name"]
    name = best["name"]
    return name.rsplit("/", 1)[-1]


def timeline(events: list) -> dict:
    """Per-call means (ms) of busy, lead and gap time on the GPU, host launches per call,
    {label: gap ms per call} and {GPU operation: ms per call} (the largest)."""
    calls = sorted((e for e in events if e.get("cat") == "user_annotation" and e["name"] == "call"),
                   key=lambda e: e["ts"])
    gpu = sorted((e for e in events if e.get("cat") in GPU_CATEGORIES), key=lambda e: e["ts"])
    launchers = {e["args"]["correlation"]: e for e in events
                 if e.get("cat") in LAUNCHER_CATEGORIES and "correlation" in e.get("args", {})}
    python = collections.defaultdict(list)
    for e in events:
        if e.get("cat") == "python_function":
            python[e["tid"]].append(e)
    n_launches = sum(1 for e in launchers.values() if "aunch" in e["name"] or "emcpy" in e["name"]
                     or "emset" in e["name"])
    totals = collections.Counter()
    gaps = collections.Counter()
    kernels = collections.Counter()
    for k, call in enumerate(calls):
        stop = calls[k + 1]["ts"] if k + 1 < len(calls) else float("inf")
        ops = [e for e in gpu if call["ts"] <= e["ts"] < stop]
        if not ops:
            continue
        cursor = call["ts"]
        for e in ops:
            kernels[e["name"][:64]] += e["dur"]
        for i, e in enumerate(ops):
            idle = e["ts"] - cursor
            if idle > 0:
                if i == 0:
                    totals["lead"] += idle
                else:
                    totals["gaps"] += idle
                    if idle > GAP_US:
                        launcher = launchers.get(e.get("args", {}).get("correlation"))
                        gaps[_label(launcher, python) if launcher else e["name"][:40]] += idle
                cursor = e["ts"]
            end = e["ts"] + e["dur"]
            if end > cursor:
                totals["busy"] += end - cursor
                cursor = end
    n = max(len(calls), 1)
    return {"gpu_busy_ms": totals["busy"] / 1000 / n, "lead_ms": totals["lead"] / 1000 / n,
            "gaps_ms": totals["gaps"] / 1000 / n, "launches": n_launches / n,
            "gaps_by_launcher_ms": {k: v / 1000 / n for k, v in gaps.most_common(8)},
            "kernels_ms": {k: v / 1000 / n for k, v in kernels.most_common(16)}}


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
        with open(os.path.join(args.out, "profile_render.json"), "w") as f:
            json.dump({"device": benchmark.device_label(args.device), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
