"""Score SecureGS runs trained in other processes than their baseline (``secure_vs_baseline.py
--no-baseline``) against the baseline's run of the same scene, seed and budget.

Each argument is a ``secure_vs_baseline.py --out`` folder (its ``secure_vs_baseline.json`` and
``anchor_clouds.npz``); a baseline's folder among the containers gives the measures' own spread
between seeds (a plain model against another). Prints, per model of the containers: cover PSNR against the baseline's, hidden
PSNR / SSIM, bits, release size against the baseline's, density ratio and coverage (the geometric
security measures, r = 3% of the hidden object's bounding-box diagonal) and the reference-free audit
score, with how far the audit's suspicious box lies from the hidden object's box (0: they touch).

    python scripts/split_runs.py --baseline runs/bunny_base_s0 runs/bunny_cover_s0 runs/bunny_rdo_s0 \\
        --png docs/geometric_security_1080p_bunny.png
"""
import argparse
import json
from pathlib import Path

import numpy as np

from securegs_warp.compare import BASELINE, density_ratio
from securegs_warp.secure import steganalysis
from securegs_warp.secure.security import exposure, plot_anchor_clouds


def load(folder: Path) -> tuple[dict, dict]:
    """(the report of secure_vs_baseline.json, the arrays of anchor_clouds.npz) of one folder;
    SystemExit naming what is missing."""
    try:
        report = json.loads((folder / "secure_vs_baseline.json").read_text())
        with np.load(folder / "anchor_clouds.npz", allow_pickle=False) as arrays:  # no pickled objects
            return report, {name: arrays[name] for name in arrays.files}
    except (OSError, ValueError) as e:
        raise SystemExit(f"{folder}: not a secure_vs_baseline.py output folder ({e})") from None


def box_gap(box, points: np.ndarray) -> float:
    """Distance between an axis-aligned box [[lo], [hi]] and the bounding box of ``points`` [M, 3]."""
    lo, hi = (np.asarray(v) for v in box)
    gap = np.maximum(0.0, np.maximum(lo - points.max(0), points.min(0) - hi))
    return float(np.linalg.norm(gap))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", type=Path, required=True, help="the folder of the baseline's run")
    ap.add_argument("containers", type=Path, nargs="+", help="folders of the SecureGS runs")
    ap.add_argument("--png", type=Path, help="draw the anchor clouds (baseline, then each container) here")
    args = ap.parse_args()
    report, arrays = load(args.baseline)
    rows = report["rows"]
    if BASELINE not in rows:
        ap.error(f"{args.baseline}: holds no {BASELINE!r} row")
    hidden, scene = arrays["hidden_points"], arrays["scene_points"]
    radius = report["meta"]["exposure_radius"]  # the one secure_vs_baseline.py measured with
    base = rows[BASELINE]
    base_exposure = exposure(arrays[BASELINE], hidden, scene, radius)
    clouds = {BASELINE: arrays[BASELINE]}
    print("| run | model | cover PSNR (vs baseline) | hidden PSNR / SSIM | bits | release MB (×) | anchors | "
          "density ratio | coverage (baseline) | audit score (baseline) | suspicious box to hidden box |")
    print("|---" * 11 + "|")
    base_audit = steganalysis.audit({"xyz": arrays[BASELINE]})
    for folder in args.containers:
        their_report, their_arrays = load(folder)
        if not np.array_equal(their_arrays["hidden_points"], hidden):
            ap.error(f"{folder}: another hidden object than the baseline's (another scene or mesh)")
        for label, row in their_report["rows"].items():
            xyz = their_arrays[label]
            exposed = exposure(xyz, hidden, scene, radius)
            audit = steganalysis.audit({"xyz": xyz})
            bits = "–" if row.get("bit_accuracy") is None else f"{100 * row['bit_accuracy']:.0f}%"
            hid = "–" if row.get("psnr_hidden") is None else f"{row['psnr_hidden']:.2f} / {row['ssim_hidden']:.3f}"
            print(f"| {folder.name} | {label} | {row['psnr_public']:.2f} ({row['psnr_public'] - base['psnr_public']:+.2f}) "
                  f"| {hid} | {bits} "
                  f"| {row['size_mb']:.2f} ({row['size_mb'] / base['size_mb']:.2f}×) | {row['anchors']:,} "
                  f"| {density_ratio(exposed, base_exposure):.2f} "
                  f"| {exposed['coverage']:.3f} ({base_exposure['coverage']:.3f}) "
                  f"| {audit['score']:.1f} ({base_audit['score']:.1f}) "
                  f"| {box_gap(audit['suspicious_box'], hidden):.2f} ({box_gap(base_audit['suspicious_box'], hidden):.2f}) |")
            clouds[label] = xyz
    if args.png:
        plot_anchor_clouds(args.png, clouds, hidden)


if __name__ == "__main__":
    main()
