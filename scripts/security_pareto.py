"""Hidden PSNR against the density ratio (anchors within r of the hidden-only surface over the plain
model's) of SecureGS variants, from ``secure_vs_baseline.json`` reports: a Pareto plot of what each
knob trades. Each report's variants are divided by the baseline in ``--baseline`` (the plain model
trained on the same scene, seed and budget), or by the report's own.

    python scripts/security_pareto.py --out docs/pareto.png --baseline runs/a/secure_vs_baseline.json \\
        runs/a/secure_vs_baseline.json runs/knobs/secure_vs_baseline.json
"""
import argparse
import json

from securegs_warp.compare import BASELINE, density_ratio
from securegs_warp.io.atomic import save_figure


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", nargs="+")
    ap.add_argument("--baseline", help="report holding the baseline row (default: each report's own)")
    ap.add_argument("--title", default="")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shared = json.load(open(args.baseline))["rows"][BASELINE] if args.baseline else None
    fig, ax = plt.subplots(figsize=(7, 5))
    for path in args.reports:
        rows = json.load(open(path))["rows"]
        base = shared or rows[BASELINE]
        for label, row in rows.items():
            if label == BASELINE or row.get("psnr_hidden") is None:
                continue
            ratio = density_ratio(row["exposure"], base["exposure"])
            paper = "cover" not in label
            ax.scatter(ratio, row["psnr_hidden"], marker="s" if paper else "o", c="tab:red" if paper else "tab:blue")
            ax.annotate(label.replace("SecureGS", "").strip(" ()") or "rdo", (ratio, row["psnr_hidden"]), fontsize=7,
                        xytext=(4, 2), textcoords="offset points")
    ax.axvline(1.1, ls="--", c="gray", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("density ratio: anchors within r of the hidden-only surface / plain Scaffold-GS's (log)")
    ax.set_ylabel("hidden PSNR (dB)")
    ax.set_title(args.title + " (red squares: paper's RDO; blue: cover mode; dashed: goal 1.1)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, args.out, dpi=110)


if __name__ == "__main__":
    main()
