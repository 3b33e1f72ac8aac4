"""Robustness sweep: every attack of ``securegs attack`` at 4–5 strengths on one or more containers.

Each RUN is a ``securegs hide`` run folder (its release, key and config.json, from which the scene
is rebuilt for the cover's views and the true hidden views). Without a RUN, a small container is
trained first (the demo's budget: object + 48 bits, 400 iterations, on the built-in scene). Writes
robustness.csv / .json / .md and robustness.png (one panel per attack: hidden PSNR and bit accuracy
against strength, a line per container, its unattacked level dashed) into --out.

    python scripts/robustness.py runs/demo runs/norobust --labels default,no-robust --out runs/robustness
        (runs/norobust: the demo's command with --robust none, the default before robust training)
    python scripts/robustness.py --out runs/robustness          # trains runs/robustness/container first
    python scripts/robustness.py RUN --attacks prune-random,noise-feat
    python scripts/robustness.py RUN --attacks prune-random --draws 3   # three random prunings per strength
    python scripts/robustness.py RUN --attacks quantize,noise-xyz --without-record
        (each container also as RUN-bare: its key without the record of its serving anchors'
        positions, decoding the positions it is given, as a key written before the record did)

The PNG needs matplotlib (``pip install -e ".[plots]"``).
"""
import argparse
import copy
import time
from pathlib import Path

import torch

from securegs_warp.cli import main as securegs
from securegs_warp.cli.common import quiet_warp, resolve_device
from securegs_warp.config import RunConfig, from_dict
from securegs_warp.robustness import SWEEP, plot_sweep, sweep, write_sweep
from securegs_warp.runs import RunFolder
from securegs_warp.secure.container import PLAIN_KEY, KeyViews, open_container
from securegs_warp.secure.model import SecureModel


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="*", help="securegs hide run folders (default: train one into OUT/container)")
    ap.add_argument("--labels", help="comma-separated names of the runs (default: the folder names)")
    ap.add_argument("--attacks", default=",".join(SWEEP), help=f"attacks to sweep (default: all: {','.join(SWEEP)})")
    ap.add_argument("--seed", type=int, default=0, help="random source of the attacks")
    ap.add_argument("--draws", type=int, default=1,
                    help="runs of each attack that draws randomly (pruning at random, noise, purify), "
                         "seeded --seed, --seed+1, ...; the tables add the mean and worst over them. Each "
                         "purify draw renders every view again: the sweep's slowest attack after finetune")
    ap.add_argument("--out", default="runs/robustness")
    ap.add_argument("--device", help="where to render and attack (default: CUDA when present, else the CPU)")
    ap.add_argument("--without-record", action="store_true",
                    help="sweep each container a second time as LABEL-bare, its key without the record of its "
                         "serving anchors' positions (what the record buys against moved anchors)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    quiet_warp()
    out = Path(args.out)
    runs = [Path(r) for r in args.runs]
    if not runs:
        runs = [out / "container"]
        if securegs(["hide", "--payload", "object+bits:48", "--iterations", "400", "--out", str(runs[0]), "--quiet",
                     "--device", str(device), *(["--resume"] if (runs[0] / "config.json").is_file() else [])]) != 0:
            raise SystemExit("training the container failed")
    labels = args.labels.split(",") if args.labels else [r.name for r in runs]
    if len(labels) != len(runs):
        raise SystemExit(f"--labels names {len(labels)} runs, {len(runs)} given")
    if args.draws < 1:
        raise SystemExit(f"--draws must be at least 1, got {args.draws}")
    unknown = sorted(set(args.attacks.split(",")) - set(SWEEP))
    if unknown:
        raise SystemExit(f"unknown attacks {unknown}; known: {', '.join(SWEEP)}")
    configs = [from_dict(RunConfig, RunFolder(r).read_config()) for r in runs]
    if len({c.scene for c in configs}) != 1:
        raise SystemExit("the runs were trained on different scenes; sweep them separately")
    scene = configs[0].scene.load()
    models, views = {}, {}
    for label, run in zip(labels, runs):
        models[label], meta = open_container(run / "public", run / PLAIN_KEY, device=device)
        views[label] = KeyViews.from_metadata(meta, device)
        if args.without_record:
            models[f"{label}-bare"], views[f"{label}-bare"] = without_record(models[label]), views[label]
    meta = {"runs": [str(r) for r in runs], "labels": labels, "seed": args.seed, "draws": args.draws,
            "date": time.strftime("%Y-%m-%d"), "device": str(device)}
    rows = []

    def report(row):
        rows.append(row)
        print(row["model"], row["spec"], {k: v for k, v in row.items() if k in ("psnr_hidden", "psnr_hidden_truth",
                                                                             "bit_accuracy", "psnr_public")},
              flush=True)
        write_sweep(out, rows, meta)

    sweep(models, views, scene, {name: SWEEP[name] for name in args.attacks.split(",")}, seed=args.seed,
          train=configs[0].train, on_row=report, draws=args.draws)
    print(write_sweep(out, rows, meta))
    try:
        plot_sweep(out / "robustness.png", rows)
    except ImportError:
        print("no plot: matplotlib is not installed (pip install -e \".[plots]\")")
        return
    print(f"wrote {out / 'robustness.png'}")


def without_record(model: SecureModel) -> SecureModel:
    """``model`` with a copy of its key's heads that holds no anchor record (the release shared)."""
    bare = copy.deepcopy(model.private)
    if getattr(bare, "anchor_record", None) is None:
        raise SystemExit("--without-record: this key holds no anchor record (a box-frame key written since "
                         "the record exists has one)")
    delattr(bare, "anchor_record")
    return SecureModel(model.anchors, model.heads, [bare])


if __name__ == "__main__":
    main()
