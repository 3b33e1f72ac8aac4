"""Probe: GPU time of each stage of an eager forward at 1080p (CUDA events, median of 30), random and
realistic scenes; it times count_tiles with either launch (one thread a Gaussian, or the block-shared
probe of count_tiles_block_shared.patch).

    SIZES=1000000,3000000 PYTHONPATH=. python docs/probes/stage_probe.py
"""
import os, statistics
import torch, warp as wp
from securegs_warp.benchmark import make_scene, camera
from securegs_warp.rasterizer import RasterOptions, RenderPlan
from securegs_warp.kernels import binning

wp.config.quiet = True
wp.init()
dev = os.environ.get("DEV", "cuda")
SIZES = [int(x) for x in os.environ.get("SIZES", "1000000,3000000").split(",")]
W, H = 1920, 1080

def ev_time(fn, runs=30):
    for _ in range(3): fn()
    if dev == "cpu":
        import time; t0 = time.perf_counter(); fn(); return 1000 * (time.perf_counter() - t0)
    ts = []
    for _ in range(runs):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record(); fn(); b.record(); torch.cuda.synchronize(); ts.append(a.elapsed_time(b))
    return statistics.median(ts)

for kind in ("random", "realistic"):
  for n in SIZES:
    sc = make_scene(kind, n, dev)
    viewmat, K = camera(W, H, dev)
    inputs = dict(means=sc["means"], quats=sc["quats"], scales=sc["scales"], opacities=sc["opacities"],
                  colors=sc["colors"], color_table=sc["colors"], background=torch.zeros(3, device=dev),
                  viewmat=viewmat.reshape(-1).contiguous(), K=K.reshape(-1).contiguous())
    opts = RasterOptions()
    plan = RenderPlan(inputs, W, H, opts, with_grads=True)
    w = plan.w
    spans = w.get("tile_spans", w.get("tile_masks"))
    with plan.scoped():
        t = {"projection": ev_time(lambda: wp.launch(**plan._projection))}
        if hasattr(binning, "COUNT_BLOCK"):
            nb = -(-plan.n // binning.COUNT_BLOCK) * binning.COUNT_BLOCK
            t["count_tiles"] = ev_time(lambda: wp.launch(binning.count_tiles, dim=nb, block_dim=binning.COUNT_BLOCK,
                      inputs=[w["means2d"], w["radii"], *plan._overlap(), opts.tile_size, plan.tiles_x, plan.tiles_y, plan.n],
                      outputs=[w["tile_counts"], spans]))
        else:
            t["count_tiles"] = ev_time(lambda: wp.launch(binning.count_tiles, dim=plan.n,
                      inputs=[w["means2d"], w["radii"], *plan._overlap(), opts.tile_size, plan.tiles_x, plan.tiles_y],
                      outputs=[w["tile_counts"], spans]))
        plan.project_and_count()
        t["project_and_count"] = ev_time(plan.project_and_count)
        cnt = int(plan.ends[-1]); plan.allocate_intersections(cnt)
        t["emit+sort+ranges"] = ev_time(lambda: plan.sort_intersections(cnt, padded=False))
        t["blend"] = ev_time(plan.blend)
        img = plan.out["image"].clone()
    print(f"{kind} {n}: isect {cnt} ({cnt/n:.2f}/G) image sum {float(img.double().sum()):.6f}; " + ", ".join(f"{k} {v:.3f}" for k, v in t.items()), flush=True)
    del plan, sc
    torch.cuda.empty_cache()
