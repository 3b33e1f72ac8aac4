"""Score SecureGS runs trained in other processes than their baseline (``secure_vs_baseline.py
--no-baseline``) against the baseline's run of the same scene, seed and budget.

Each argument is a ``secure_vs_baseline.py --out`` folder (its ``secure_vs_baseline.json`` and
``anchor_clouds.npz``); a baseline's folder among the containers gives the measures' own spread
between seeds (a plain model against another). Prints, per model of the containers: cover PSNR
against the baseline's, hidden PSNR / SSIM, bits, release size against the baseline's, density ratio and coverage (the geometric
security measures, r = 3% of the hidden object's bounding-box diagonal) and the reference-free audit
score, with how far the audit's suspicious box lies from the hidden object's box (0: they touch).

    python scripts/split_runs.py --baseline runs/bunny_base_s0 runs/bunny_cover_s0 runs/bunny_rdo_s0 \\
        --png docs/geometric_security_1080p_bunny.png
"""
import argparse
from pathlib import Path

import numpy as np

from securegs_warp.compare import BASELINE, SCENE_AND_BUDGET, density_ratio, read_report
from securegs_warp.secure import steganalysis
from securegs_warp.secure.security import plot_anchor_clouds


# What must agree between a baseline's run and a container's for one to be scored against the other
# (the seed may differ: a plain model of another seed gives the measures' own spread).
SAME = SCENE_AND_BUDGET + ("exposure_radius",)


def load(folder: Path) -> tuple[dict, dict]:
    """``compare.read_report`` of one folder whose report names every SAME field; SystemExit naming
    what is wrong."""
    try:
        report, clouds = read_report(folder)
    except ValueError as e:
        raise SystemExit(str(e)) from None
    missing = [key for key in SAME if key not in report["meta"]]
    if missing:
        raise SystemExit(f"{folder}: its report's meta lacks {', '.join(missing)}")
    return report, clouds


def box_gap(box, points: np.ndarray) -> float | None:
    """Distance between an axis-aligned box [[lo], [hi]] and the bounding box of ``points`` [M, 3]
    (None without a box: the audit found no suspicious region)."""
    if box is None:
        return None
    lo, hi = (np.asarray(v) for v in box)
    gap = np.maximum(0.0, np.maximum(lo - points.max(0), points.min(0) - hi))
    return float(np.linalg.norm(gap))


def fmt(value, spec: str) -> str:
    """``value`` formatted by ``spec``, or "–" for None (a measure that does not apply)."""
    return "–" if value is None else format(value, spec)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", type=Path, required=True, help="the folder of the baseline's run")
    ap.add_argument("containers", type=Path, nargs="+", help="folders of the SecureGS runs")
    ap.add_argument("--png", type=Path, help="draw the anchor clouds (baseline, then each container) here")
    args = ap.parse_args()
    report, arrays = load(args.baseline)
    base = report["rows"].get(BASELINE)
    if base is None:
        ap.error(f"{args.baseline}: holds no {BASELINE!r} row")
    hidden = arrays["hidden_points"]
    base_audit = steganalysis.audit({"xyz": arrays[BASELINE]})
    clouds = {BASELINE: arrays[BASELINE]}
    print(f"Baseline: {args.baseline.name} (seed {report['meta']['seed']})\n")
    print("| run | model | cover PSNR (vs baseline) | hidden PSNR / SSIM | bits | release MB (×) | anchors | "
          "density ratio | coverage (baseline) | audit score (baseline) | suspicious box to hidden box |")
    print("|---" * 11 + "|")
    for folder in args.containers:
        theirs, their_arrays = load(folder)
        differ = [k for k in SAME if theirs["meta"][k] != report["meta"][k]]
        if differ or not np.array_equal(their_arrays["hidden_points"], hidden):
            ap.error(f"{folder}: another scene or budget than the baseline's ({', '.join(differ or ['hidden points'])})")
        for label, row in theirs["rows"].items():
            audit = steganalysis.audit({"xyz": their_arrays[label]})
            bits = "–" if row.get("bit_accuracy") is None else f"{100 * row['bit_accuracy']:.0f}%"
            hid = "–" if row.get("psnr_hidden") is None else f"{row['psnr_hidden']:.2f} / {row['ssim_hidden']:.3f}"
            cover = f"{row['psnr_public']:.2f} ({row['psnr_public'] - base['psnr_public']:+.2f})"
            size = f"{row['size_mb']:.2f} ({row['size_mb'] / base['size_mb']:.2f}×)"
            print(f"| {folder.name} (seed {theirs['meta']['seed']}) | {label} | {cover} | {hid} | {bits} | {size} "
                  f"| {row['anchors']:,} "
                  f"| {fmt(density_ratio(row['exposure'], base['exposure']), '.2f')} "
                  f"| {row['exposure']['coverage']:.3f} ({base['exposure']['coverage']:.3f}) "
                  f"| {fmt(audit['score'], '.1f')} ({fmt(base_audit['score'], '.1f')}) "
                  f"| {fmt(box_gap(audit['suspicious_box'], hidden), '.2f')} "
                  f"({fmt(box_gap(base_audit['suspicious_box'], hidden), '.2f')}) |")
            clouds[f"{folder.name}: {label}"] = their_arrays[label]
    if args.png:
        plot_anchor_clouds(args.png, clouds, hidden)


if __name__ == "__main__":
    main()
