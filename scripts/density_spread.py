"""The density ratio's own spread: the ratio between plain Scaffold-GS models of different seeds.

The geometric-security goal compares a container's anchor density near the hidden surface with a
plain model's (``securegs audit --reference --key``: density_ratio). Two plain models trained with
different seeds differ too, although neither hides anything; their ratio, measured on the same
hidden surfaces, is what the goal's 1.1 must be read against. Each KEY_RUN is a ``securegs hide``
run folder of the same scene: its key gives a hidden surface (``steganalysis.hidden_surface``), and
every ordered pair of PLAIN runs is measured on it.

    python scripts/density_spread.py --plain runs/plain_s0 runs/plain_s1 runs/plain_s2 \\
        --keys runs/hide_s0 runs/hide_s1 runs/hide_s2
"""
import argparse
import itertools
import json

import numpy as np

from securegs_warp.io.atomic import atomic_write
from securegs_warp.secure import steganalysis
from securegs_warp.secure.container import open_container


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plain", nargs="+", required=True, help="securegs train run folders (at least two)")
    ap.add_argument("--keys", nargs="+", required=True, help="securegs hide run folders (public/ + key.safetensors)")
    ap.add_argument("--json", help="also write every pair's numbers here")
    args = ap.parse_args()
    if len(args.plain) < 2:
        ap.error("--plain needs at least two runs to compare")
    plains = [steganalysis.release_arrays(open_container(f"{p}/model", device="cpu")[0])["xyz"] for p in args.plain]
    rows = []
    for run in args.keys:
        model, meta = open_container(f"{run}/public", f"{run}/key.safetensors", device="cpu")
        try:
            points, _ = steganalysis.key_surface(model, meta)
        except steganalysis.NoHiddenSurface as why:
            raise SystemExit(f"{run}: {why}") from None
        for a, b in itertools.permutations(range(len(plains)), 2):
            leak = steganalysis.leakage(plains[a], points, plains[b])
            rows.append({"surface_of": run, "model": args.plain[a], "reference": args.plain[b],
                         "density_ratio": leak["density_ratio"], "coverage": leak["coverage"],
                         "reference_coverage": leak["reference_coverage"]})
            ratio = "–" if leak["density_ratio"] is None else f"{leak['density_ratio']:.2f}"
            print(f"{run}'s surface: {args.plain[a]} / {args.plain[b]}: density ratio {ratio}, "
                  f"coverage {leak['coverage']:.3f} ({leak['reference_coverage']:.3f})")
    # A reference without an anchor near the surface leaves the ratio undefined (None): not a pair.
    ratios = np.array([r["density_ratio"] for r in rows if r["density_ratio"] is not None])
    if len(ratios):
        print(f"plain / plain density ratio over {len(ratios)} pairs: {ratios.min():.2f} to {ratios.max():.2f}, "
              f"median {np.median(ratios):.2f}; above 1.1 in {int((ratios > 1.1).sum())}")
    print(f"pairs without a ratio (no anchor of the reference near the surface): {len(rows) - len(ratios)}")
    if args.json:
        text = json.dumps(rows, indent=1).encode()
        atomic_write(args.json, lambda f: f.write(text))


if __name__ == "__main__":
    main()
