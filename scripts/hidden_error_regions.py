"""Where a container's hidden object is lost: its hidden renders against the true hidden views,
the squared error split between the object's interior, a band around its silhouette and the
background (``evaluation.error_by_region``).

Each RUN is a ``securegs hide`` run folder hiding an object in a synthetic scene (the scene is
rebuilt from its config.json for the true views and the object's coverage).

    python scripts/hidden_error_regions.py runs/demo runs/study/mug_stand_s9/hide [--band 2] [--device cuda]
"""
import argparse
from pathlib import Path

import torch

from securegs_warp.cli.common import quiet_warp, resolve_device
from securegs_warp.config import RunConfig, from_dict
from securegs_warp.evaluation import REGIONS, error_by_region
from securegs_warp.robustness import reference_hidden
from securegs_warp.runs import RunFolder
from securegs_warp.secure.container import PLAIN_KEY, KeyViews, open_container


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="securegs hide run folders")
    ap.add_argument("--band", type=int, default=2, help="half-width of the silhouette band, pixels")
    ap.add_argument("--device", help="where to render the hidden views (default: CUDA when present, else the CPU)")
    args = ap.parse_args()
    device = resolve_device(args.device)
    quiet_warp()
    columns = ["run", "PSNR, all pixels pooled"] + [f"{r}: error share / pixel share / PSNR" for r in REGIONS]
    print("| " + " | ".join(columns) + " |")
    print("|---" * (2 + len(REGIONS)) + "|")
    for run in map(Path, args.runs):
        try:
            scene = from_dict(RunConfig, RunFolder(run).read_config()).scene.load()
            model, meta = open_container(run / "public", run / PLAIN_KEY, device=device)
        except (OSError, ValueError) as e:
            raise SystemExit(f"{run}: cannot open the run ({e})") from None
        views = KeyViews.from_metadata(meta, device)
        by_name = {c.name: c for c in scene.train + scene.test}
        truth = [by_name.get(c.name) for c in views.hidden]
        # The split is summed on the CPU, where the true views are.
        pairs = [(render.cpu(), torch.as_tensor(t.hidden), torch.as_tensor(t.hidden_alpha[..., 0]))
                 for render, t in zip(reference_hidden(model, views), truth)
                 if t is not None and t.hidden_alpha is not None]
        if not pairs:
            raise SystemExit(f"{run}: no hidden view with the object's coverage (a hidden object in a synthetic scene)")
        regions = error_by_region(pairs, args.band)
        print(f"| {run} | {regions['all']['psnr']:.2f} | " + " | ".join(
            f"{100 * g['error_share']:.0f}% / {100 * g['pixel_share']:.1f}% / "
            + ("–" if g["psnr"] is None else f"{g['psnr']:.1f}") for g in map(regions.get, REGIONS)) + " |")


if __name__ == "__main__":
    main()
