"""``securegs audit``: steganalysis of a release by someone who holds the file (and, to measure the
leak, the key): the analysis is ``secure.steganalysis``."""
from __future__ import annotations

import json

import torch

from ..secure import steganalysis
from ..secure.container import open_container
from . import common
from .secure import passphrase_from


@torch.no_grad()
def cmd_audit(args) -> int:
    common.quiet_warp()
    model, meta = open_container(args.release, args.key, passphrase_from(args), device="cpu")
    reference = open_container(args.reference, device="cpu")[0] if args.reference else None
    release = steganalysis.release_arrays(model)
    ref = steganalysis.release_arrays(reference) if reference is not None else None
    report = steganalysis.audit(release, ref)
    if args.key is not None:
        report.update(coverage=None, density_ratio=None)  # present and null where not measured
        report.update(_leakage(model, meta, release, ref))
    if args.json:
        args.quiet = True  # stdout is the one JSON object: no "done in" line after it
        print(json.dumps(report))
        return 0
    print(f"anchors: {report['anchors']}")
    print(f"score: {report['score']:.2f} (the most suspicious region's; higher is more suspicious)")
    if report["suspicious_box"] is not None:
        lo, hi = report["suspicious_box"]
        print("suspicious box: [" + ", ".join(f"{v:.3f}" for v in lo) + "] to [" + ", ".join(f"{v:.3f}" for v in hi)
              + "]" + "".join(f", {k} {v:.2f}" for k, v in report.get("region", {}).items()))
    for name, value in report.get("attribute_distances", {}).items():
        print(f"sliced Wasserstein, {name}: " + ("not comparable (the releases' shapes differ)" if value is None
                                                  else f"{value:.4f}"))
    for name in ("coverage", "reference_coverage", "density_ratio"):
        if report.get(name) is not None:
            print(f"{name}: {report[name]:.3f}")
    if "leakage_note" in report:
        print(f"note: {report['leakage_note']}")
    return 0


def _leakage(model, meta: dict, release: dict, ref: dict | None) -> dict:
    """What the key's hidden surface finds in the anchor cloud (``steganalysis.leakage``), or a
    ``leakage_note`` saying why it cannot be measured."""
    try:
        points, threshold = steganalysis.key_surface(model, meta)
    except steganalysis.NoHiddenSurface as why:
        return {"leakage_note": str(why)}
    found = steganalysis.leakage(release["xyz"], points, None if ref is None else ref["xyz"])
    found["surface_opacity"] = threshold
    if ref is None:
        found["leakage_note"] = "density_ratio compares with a plain model of the scene: give --reference"
    return found


def add_parsers(sub) -> None:
    p = sub.add_parser("audit", help="steganalysis of a release: does its anchor cloud show a hidden object?",
                       description="Region tests of the release's anchor cloud (density and nearest-neighbour "
                                   "spacing of each region against the rest, isolation), the most suspicious "
                                   "region as a box with a score; with --reference (a plain model of the same "
                                   "scene) the tests against it and the attribute distributions' distances; with "
                                   "--key the leak itself (density ratio and coverage of the hidden surface).")
    p.add_argument("release", help="the release folder (point_cloud.ply + MLPs)")
    p.add_argument("--reference", help="a plain Scaffold-GS release of the same scene to compare with")
    p.add_argument("--key", help="the release's key: measure what the hidden object leaves in the anchor cloud")
    p.add_argument("--passphrase-env", help="environment variable holding the key's passphrase")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=cmd_audit)
