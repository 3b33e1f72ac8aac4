"""Detection AUC of ``securegs audit`` (no reference, no key) over runs of plain and hiding models.

Each RUN is an ``anchor_clouds.npz`` written by ``scripts/secure_vs_baseline.py`` (one baseline and
its SecureGS variants trained on one scene with one seed), a ``secure_vs_baseline.py --out``
folder, or a ``securegs train`` / ``securegs hide`` run folder. Folders of one scene, seed and
budget join into one run: ``secure_vs_baseline.py`` folders split over processes with
``--no-baseline``, and a plain run with the containers trained on its views for as long with its
seed (``compare.read_run_anchors``). The audit scores every anchor cloud and the AUC says how well
the score tells each variant from the plain models (0.5: chance).

    python scripts/audit_auc.py runs/seed*/anchor_clouds.npz [--with-reference]
    python scripts/audit_auc.py runs/bunny_*_s* runs/teapot_*_s* --with-reference
    python scripts/audit_auc.py plain_s* hide_s* --with-reference     # securegs train / hide runs
"""
import argparse
import json
from pathlib import Path

import numpy as np

from securegs_warp.compare import BASELINE, SCENE_AND_BUDGET, SCENE_ARRAYS, read_report, read_run_anchors
from securegs_warp.io.atomic import atomic_write
from securegs_warp.runs import RunFolder
from securegs_warp.secure.steganalysis import auc_by_model

# What makes folders one run: the same scene, hidden object and budget, and the same seed.
RUN_KEYS = SCENE_AND_BUDGET + ("seed",)
# What a run's plain model depends on: not the hidden object nor where it stands (a plain model never
# sees them), so runs that differ only there are one cover and never each other's reference.
COVER_KEYS = tuple(k for k in RUN_KEYS if k not in ("hidden", "placement"))


def models(arrays: dict) -> dict:
    """Model label -> anchor positions [N, 3]: the arrays of an anchor_clouds.npz less SCENE_ARRAYS."""
    return {name: xyz for name, xyz in arrays.items() if name not in SCENE_ARRAYS}


def load_runs(paths: list[str]) -> tuple[list[dict], list]:
    """The runs of ``paths`` and their covers (``auc_by_model``): each .npz one run and its own cover;
    secure_vs_baseline.py folders grouped by RUN_KEYS of their reports, their covers by COVER_KEYS;
    run folders grouped by their cover, which is also the run's (one plain model a cover)."""
    runs, covers, groups = [], [], {}
    for path in map(Path, paths):
        if not path.is_dir():
            with np.load(path, allow_pickle=False) as data:  # no pickled objects
                runs.append(models({name: data[name] for name in data.files}))
            covers.append(str(path))
            continue
        if RunFolder(path).config.is_file():
            cover, label, xyz = read_run_anchors(path)
            found = {label: xyz}
            group = groups.setdefault(cover, ({}, cover, {}))
        else:
            report, arrays = read_report(path)
            meta = report["meta"]
            found = models(arrays)
            group = groups.setdefault(tuple(meta[k] for k in RUN_KEYS), ({}, tuple(meta[k] for k in COVER_KEYS), {}))
        for label, xyz in found.items():
            if label in group[0]:
                raise SystemExit(f"{path}: a second {label!r} for one scene, seed and budget (the first from "
                                 f"{group[2][label]}): audit them in separate calls")
            group[0][label] = xyz
            group[2][label] = path
    for group, _, where in groups.values():
        if BASELINE not in group:
            folders = ", ".join(map(str, dict.fromkeys(where.values())))
            raise SystemExit(f"{folders}: no plain model of that scene, seed and budget among the runs (a securegs "
                             "train run, or secure_vs_baseline.py's baseline)")
    return runs + [g for g, _, _ in groups.values()], covers + [c for _, c, _ in groups.values()]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="anchor_clouds.npz files, secure_vs_baseline.py output folders or "
                                            "securegs train / hide run folders")
    ap.add_argument("--with-reference", action="store_true",
                    help="audit each model against the plain model of every other run (an attacker's reference)")
    ap.add_argument("--json", help="also write the scores and AUCs here")
    args = ap.parse_args()
    try:
        runs, covers = load_runs(args.runs)
    except (OSError, KeyError, ValueError) as e:
        raise SystemExit(f"cannot read the runs: {e}") from None
    result = auc_by_model(runs, BASELINE, args.with_reference, covers)
    print("| model | audits | scores | AUC against the plain models |\n|---|---|---|---|")
    for label, r in result.items():
        auc = f"{r['auc']:.2f}" if "auc" in r else "–"
        print(f"| {label} | {len(r['scores'])} | {', '.join(f'{s:.1f}' for s in r['scores'])} | {auc} |")
    if args.json:
        data = json.dumps(result, indent=1).encode()
        atomic_write(args.json, lambda f: f.write(data))


if __name__ == "__main__":
    main()
