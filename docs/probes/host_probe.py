"""Probe: host microseconds of each step of a captured render's call (no profiler):
functions wrapped with perf_counter timers; median over calls of each step's total per call.

    N=1000000 PYTHONPATH=. python docs/probes/host_probe.py     # a CUDA machine; on the CPU 2000 at 320x180
"""
import os, statistics, time, collections, functools
import torch, warp as wp
wp.config.quiet = True
wp.init()
from securegs_warp import benchmark, rasterizer, raster_graph, warp_scope
from securegs_warp.rasterizer import RasterOptions

acc = collections.defaultdict(float)
T0 = [0.0]
launches = []
def wrap(owner, name, label=None):
    f = getattr(owner, name)
    label = label or f"{getattr(owner, '__name__', owner)}.{name}"
    @functools.wraps(f)
    def g(*a, **k):
        t = time.perf_counter()
        if name in ("capture_launch", "_foreach_copy_"):
            launches.append((name, (t - T0[0]) * 1e6))
        try:
            return f(*a, **k)
        finally:
            acc[label] += (time.perf_counter() - t) * 1e6
    setattr(owner, name, g)

dev = "cuda" if torch.cuda.is_available() else "cpu"
W, H = (1920, 1080) if dev == "cuda" else (320, 180)
n = int(os.environ.get("N", "1000000" if dev == "cuda" else "2000"))
scene = benchmark.make_scene("random", n, dev)
for t in scene.values(): t.requires_grad_(True)
viewmat, K = benchmark.camera(W, H, dev)
grads = benchmark.cotangents(W, H, dev)
opts = RasterOptions(capture=True)
call = lambda: benchmark.ours(scene, viewmat, K, W, H, opts)

for owner, names in ((rasterizer, ["resolve_options", "_validated"]),
                     (raster_graph, ["_acquire", "copies", "rasterize_captured"]),
                     (raster_graph._Captured, ["check_pending", "_run", "forward", "backward"]),
                     (warp_scope.WarpScope, ["__init__", "__enter__", "__exit__"]),
                     (torch, ["_foreach_copy_", "zeros"]), (wp, ["capture_launch", "init"])):
    for nm in names:
        if hasattr(owner, nm):
            wrap(owner, nm)
# benchmark.ours calls rasterize by its module-level name.
wrap(benchmark, "rasterize", "rasterize (total)")

for mode in ("fwd", "fwd+bwd"):
    per = collections.defaultdict(list)
    for i in range(60):
        if dev == "cuda": torch.cuda.synchronize()
        acc.clear(); launches.clear()
        t = T0[0] = time.perf_counter()
        with torch.set_grad_enabled(mode != "fwd"):
            image, alpha = call()
            t1 = time.perf_counter()
            if mode != "fwd":
                (image * grads[0]).sum().add_((alpha * grads[1]).sum()).backward()
        total = (time.perf_counter() - t) * 1e6
        if i >= 10:
            per["call total"].append(total); per["render() returns"].append((t1 - t) * 1e6)
            for k, v in acc.items(): per[k].append(v)
            for j, (nm, at) in enumerate(launches): per[f"+at: {nm} #{j}"].append(at)
    print(f"== {mode}, N={n}, {dev}")
    for k, v in sorted(per.items(), key=lambda kv: -statistics.median(kv[1])):
        print(f"   {statistics.median(v):8.1f} us  {k}")
