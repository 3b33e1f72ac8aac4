"""False- and true-positive rates of ``securegs verify`` on small CPU models.

Trains plain Scaffold-GS models and bit containers (``bits:48``) of the built-in scenes room and
garden with several seeds, tests every container's key against every other model (unmarked),
against its own container, whole and after random pruning of 20% of its anchors (marked), and
against its own container with the features shuffled among the anchors. Writes
rows.json (one row per test), summary.json, table.md and a histogram of the bit accuracy.

    python scripts/verify_fpr.py --out runs/verify_fpr --plot docs/verify_fpr_cpu.png

The logic is in securegs_warp.secure.verification_study.
"""
import argparse
import json
import time
from pathlib import Path

import torch

from securegs_warp.cli.common import quiet_warp
from securegs_warp.config import BIT_MARGIN, SceneSpec, SecureConfig
from securegs_warp.io.atomic import atomic_write
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.secure.verification_study import KINDS, plot_histogram, summary, train_model, verification_rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/verify_fpr")
    ap.add_argument("--plot", help="histogram PNG (default: OUT/histogram.png)")
    ap.add_argument("--scenes", default="room,garden")
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--height", type=int, default=48)
    ap.add_argument("--train-views", type=int, default=12)
    ap.add_argument("--test-views", type=int, default=2)
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--plain-seeds", type=int, default=8, help="plain models per scene (seeds 0..N-1)")
    ap.add_argument("--container-seeds", type=int, default=6, help="containers per scene (seeds 0..N-1)")
    ap.add_argument("--bits", type=int, default=48)
    ap.add_argument("--bit-margin", type=float, default=BIT_MARGIN)
    ap.add_argument("--prunings", type=int, default=5,
                    help="random prunings and feature shuffles of each container")
    ap.add_argument("--prune-fraction", type=float, default=0.2)
    args = ap.parse_args()
    torch.set_num_threads(1)
    quiet_warp()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    raster = RasterOptions(tile_size=8)
    secure = SecureConfig(payload=f"bits:{args.bits}", bit_margin=args.bit_margin)
    models, t0 = [], time.perf_counter()
    for source in args.scenes.split(","):
        scene = SceneSpec(source=source, width=args.width, height=args.height, n_train=args.train_views,
                          n_test=args.test_views)
        for seed in range(args.plain_seeds):
            models.append(train_model(scene, seed, args.iterations, raster))
            print(f"{models[-1].name}: psnr {models[-1].psnr:.2f}  ({time.perf_counter() - t0:.0f} s)", flush=True)
        for seed in range(args.container_seeds):
            models.append(train_model(scene, seed, args.iterations, raster, secure))
            print(f"{models[-1].name}: psnr {models[-1].psnr:.2f}  ({time.perf_counter() - t0:.0f} s)", flush=True)
    rows = verification_rows(models, args.prunings, args.prune_fraction)
    result = summary(rows)
    psnr = {(m.scene, m.seed, m.decoder is not None): m.psnr for m in models}
    covers = [{"scene": s, "seed": seed, "plain": psnr[(s, seed, False)], "container": p,
               "delta": p - psnr[(s, seed, False)]}
              for (s, seed, marked), p in psnr.items() if marked and (s, seed, False) in psnr]
    result.update(args=vars(args), models=len(models), anchors={m.name: m.anchors.num_anchors for m in models},
                  cover_psnr=covers, seconds=round(time.perf_counter() - t0, 1))
    write(out / "rows.json", json.dumps(rows, indent=1))
    write(out / "summary.json", json.dumps(result, indent=1))
    write(out / "table.md", table(result))
    print(table(result))
    try:
        plot_histogram(args.plot or out / "histogram.png", rows, args.bits)
    except ImportError:
        print("no histogram: matplotlib is not installed (pip install -e \".[plots]\")")


def table(result: dict) -> str:
    lines = ["| tests | count | verified present | rate | bit accuracy | p-value |", "|---|---|---|---|---|---|"]
    for side in KINDS:
        s = result[side]
        lines.append(f"| {side} | {s['tests']} | {s['present']} | {s['rate']:.3f} | "
                     f"{s['bit_accuracy_min']:.3f}–{s['bit_accuracy_max']:.3f} | "
                     f"{s['p_value_min']:.2g}–{s['p_value_max']:.2g} |")
    lines += ["", "| scene | seed | plain PSNR | container PSNR | Δ |", "|---|---|---|---|---|"]
    lines += [f"| {c['scene']} | {c['seed']} | {c['plain']:.2f} | {c['container']:.2f} | {c['delta']:+.2f} |"
              for c in result["cover_psnr"]]
    return "\n".join(lines) + "\n"


def write(path: Path, text: str) -> None:
    atomic_write(path, lambda f: f.write(text.encode()))


if __name__ == "__main__":
    main()
