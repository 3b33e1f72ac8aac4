"""One training step's time by section, SecureGS beside plain Scaffold-GS, on the built-in
synthetic scene (securegs_warp.step_profile has the sections and how they are timed).

    python scripts/profile_step.py                       # GPU: 1920×1080
    python scripts/profile_step.py --device cpu --width 64 --height 48 --steps 2 --warmup 1
    python scripts/profile_step.py --device cpu --width 64 --height 48 --mode rdo,cover --count-ops --no-timing
    python scripts/profile_step.py --mode cover --phase finish    # the finishing phase's step

Every trainer (Scaffold-GS, then SecureGS in each --mode; with --phase finish the SecureGS ones
alone, their schedules scaled to a joint run of --warmup steps instead of --iterations, and 10
finishing steps more) first runs --warmup steps untimed (kernel compilation, allocator warm-up),
then --steps steps with the section timers and --steps without;
with --count-ops, --steps more under torch.profiler, counting per section what a step launches
(step_profile.count_ops: aten ops, autograd nodes, host reads, and on CUDA kernel launches and
copies, and Warp launches); with --syncs (CUDA), --steps more with torch's synchronisation warnings and
--steps under torch.profiler, naming where a step waits for the device (step_profile.census_syncs).
Writes profile_step.json and .md to --out (default $OUT) when given.
"""
import argparse
import dataclasses
import functools
import json
import os

import torch

from securegs_warp import benchmark, compare, step_profile
from securegs_warp.cli.common import quiet_warp
from securegs_warp.config import SecureConfig, TrainConfig
from securegs_warp.data import make_synthetic_scene
from securegs_warp.io.atomic import atomic_write
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.secure.trainer import SecureTrainer
from securegs_warp.train import ScaffoldTrainer

# Finishing steps before a --phase finish profile: the replayed phase captures its graphs after
# secure.hidden_graph.WARMUP of them.
PHASE_WARMUP = 10


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--train-views", type=int, default=4)
    parser.add_argument("--iterations", type=int, default=4000, help="the run the schedules are scaled to")
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--hide", default="mug", help="the hidden object of the scene")
    parser.add_argument("--payload", default=SecureConfig().payload)
    parser.add_argument("--mode", default="rdo", help="the SecureGS trainers, comma-separated, each a density mode "
                                                      "with options MODE[:FIELD=VALUE]... (rdo: the paper's, as in "
                                                      "docs/results.md's profiles; cover: an object's default, with "
                                                      "its robust training; e.g. cover:hidden_capture=false, or "
                                                      "without robust training: cover:robust=none)")
    parser.add_argument("--count-ops", action="store_true", help="also count what a step launches, by section")
    parser.add_argument("--syncs", action="store_true", help="also name where a step waits for the device (CUDA)")
    parser.add_argument("--no-timing", dest="timing", action="store_false", help="skip the timed steps")
    parser.add_argument("--options", default="", help="rasterizer options on top of the device's, e.g. capture=true")
    parser.add_argument("--phase", choices=("joint", "finish"), default="joint",
                        help="the steps profiled: the joint run's (default), or the finishing phase's after a joint "
                             "run of --warmup steps (SecureGS trainers only)")
    parser.add_argument("--out", default=os.environ.get("OUT"), help="folder for profile_step.json and .md")
    args = parser.parse_args()
    try:
        raster = benchmark.parse_options(args.options, RasterOptions.for_device(args.device))
    except ValueError as e:
        parser.error(str(e))
    if args.phase == "finish" and args.warmup < 1:
        parser.error("--phase finish needs a joint run before its phase: --warmup 1 or more")
    if args.syncs and not benchmark.on_cuda(args.device):
        parser.error("--syncs names CUDA synchronisations: it needs --device cuda")
    quiet_warp()
    scene = make_synthetic_scene(hidden=args.hide, level="object", width=args.width, height=args.height,
                                 n_train=args.train_views, n_test=1, device=args.device)
    finish = args.phase == "finish"
    # The finishing phase's steps: a joint run of --warmup steps, then a phase long enough for every
    # measurement after PHASE_WARMUP steps of it (plain Scaffold-GS has no phase).
    config = TrainConfig(iterations=args.warmup if finish else args.iterations, raster=raster)
    phase_steps = PHASE_WARMUP + args.steps * (2 + args.count_ops + 2 * args.syncs) + 1
    modes = [m.strip() for m in args.mode.split(",") if m.strip()]
    trainers = {} if finish else {"Scaffold-GS": lambda: ScaffoldTrainer(scene, config, device=args.device)}
    for mode in modes:
        try:
            label, secure = compare.parse_variant(mode, SecureConfig(payload=args.payload))
        except ValueError as e:
            parser.error(str(e))
        if finish:
            secure = dataclasses.replace(secure, hidden_finish=phase_steps / args.warmup)
        trainers[label] = functools.partial(SecureTrainer, scene, config, secure, device=args.device)
    results, counts, syncs = {}, {}, {}
    for label, make in trainers.items():
        trainer = make()  # one at a time: a 1080p trainer holds its targets and buffers on the device
        if finish and not trainer.finish_steps:
            parser.error(f"{label} has no finishing phase (it needs a hidden render)")
        for _ in range(args.warmup + (PHASE_WARMUP if finish else 0)):
            trainer.step()
        if args.timing:
            results[label] = step_profile.profile_steps(trainer, args.steps)
            results[label]["anchors"] = trainer.model.anchors.num_anchors
            print(label, json.dumps(results[label]), flush=True)
        if args.count_ops:
            counts[label] = step_profile.count_ops(trainer, args.steps)
            print(label, "counts", json.dumps(counts[label]["total"]), flush=True)
        if args.syncs:
            syncs[label] = step_profile.census_syncs(trainer, args.steps)
        del trainer
    device = benchmark.device_label(args.device)
    after = f"{PHASE_WARMUP} finishing steps after a joint run of {args.warmup}" if finish else str(args.warmup)
    setup = (f"{device}, synthetic {args.width}×{args.height}, payload {args.payload}, mean of {args.steps} "
             f"steps after {after}, raster {benchmark.options_text(raster) or 'default options'}")
    tables = []
    if results:
        table = step_profile.profile_table(results, setup)
        for label in list(results)[1:] if not finish else []:
            ratio = results[label]["step_ms"] / results["Scaffold-GS"]["step_ms"]
            table += f"\n\n{label} step / Scaffold-GS step (no timers): {ratio:.2f}"
        tables.append(table)
    if counts:
        kinds = step_profile.COUNTS if benchmark.on_cuda(args.device) else step_profile.HOST_COUNTS
        tables.append(step_profile.count_table(counts, f"What a step launches, per step: {setup}", kinds))
    if syncs:
        tables.append(step_profile.census_table(syncs, f"Where a step waits for the device: {setup}"))
    text = "\n\n".join(tables)
    print(text)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        data = json.dumps({"device": device, "args": vars(args), "results": results, "counts": counts,
                           "syncs": syncs}, indent=1).encode()
        atomic_write(os.path.join(args.out, "profile_step.json"), lambda f: f.write(data))
        atomic_write(os.path.join(args.out, "profile_step.md"), lambda f: f.write((text + "\n").encode()))


if __name__ == "__main__":
    main()
