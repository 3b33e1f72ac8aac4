"""Detection AUC of ``securegs audit`` (no reference, no key) over runs of plain and hiding models.

Each RUN is an ``anchor_clouds.npz`` written by ``scripts/secure_vs_baseline.py`` (one baseline and
its SecureGS variants trained on one scene with one seed); the audit scores every anchor cloud and
the AUC says how well the score tells each variant from the plain models (0.5: chance).

    python scripts/audit_auc.py runs/seed*/anchor_clouds.npz [--with-reference]
"""
import argparse
import json

import numpy as np

from securegs_warp.compare import BASELINE
from securegs_warp.secure.steganalysis import auc_by_model

SCENE_ARRAYS = ("hidden_points", "scene_points")  # stored beside the clouds for the plots, not models


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="anchor_clouds.npz files")
    ap.add_argument("--with-reference", action="store_true",
                    help="audit each model against the plain model of every other run (an attacker's reference)")
    ap.add_argument("--json", help="also write the scores and AUCs here")
    args = ap.parse_args()
    runs = []
    for path in args.runs:
        with np.load(path, allow_pickle=False) as data:
            runs.append({name: data[name] for name in data.files if name not in SCENE_ARRAYS})
    result = auc_by_model(runs, BASELINE, args.with_reference)
    print("| model | audits | scores | AUC against the plain models |\n|---|---|---|---|")
    for label, r in result.items():
        auc = f"{r['auc']:.2f}" if "auc" in r else "–"
        print(f"| {label} | {len(r['scores'])} | {', '.join(f'{s:.1f}' for s in r['scores'])} | {auc} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
