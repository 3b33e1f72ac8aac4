"""What each effect costs: render forward and forward+backward of one random Scaffold-GS model for the
base effect set and for base + each single effect, measured side by side in one run.

Rounds are interleaved (every variant once per round) so machine load falls on all alike; each number
is the median over rounds. CUDA events on a GPU, perf_counter on the CPU (securegs_warp.benchmark.timed).

    python scripts/bench_effects.py                                   # CPU, quick
    python scripts/bench_effects.py --device cuda --width 1920 --height 1080 --anchors 100000
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import os
import statistics

import numpy as np
import torch

from securegs_warp.benchmark import timed
from securegs_warp.config import HeadsConfig
from securegs_warp.data import Camera
from securegs_warp.io.atomic import atomic_write
from securegs_warp.model import AnchorModel, ScaffoldHeads
from securegs_warp.rasterizer import RasterOptions
from securegs_warp.render import render_view
from securegs_warp.scaffold_model import neutral_heads
from securegs_warp.secure.heads import PrivateHeads
from securegs_warp.secure.keyed_bits import new_seed

FEAT, OFFSETS, BITS, CAMERAS = 32, 10, 48, 4


@dataclasses.dataclass(frozen=True)
class Variant:
    """One effect set: the heads' optional inputs, rasterizer flags, a background, a hidden branch."""

    heads: HeadsConfig = HeadsConfig()
    raster: dict = dataclasses.field(default_factory=dict)
    background: bool = False
    hidden: str | None = None  # "object" (private decoder + a second render) or "bits" (the bit head)


VARIANTS = {
    "base": Variant(),
    "antialiased": Variant(raster={"antialiased": True}),
    "depth accumulated": Variant(raster={"render_depth": "accumulated"}),
    "depth expected": Variant(raster={"render_depth": "expected"}),
    "background": Variant(background=True),
    "feature bank": Variant(HeadsConfig(feature_bank=True)),
    "appearance": Variant(HeadsConfig(appearance_dim=32)),
    "distance inputs": Variant(HeadsConfig(opacity_dist=True, cov_dist=True, color_dist=True)),
    "hidden object": Variant(hidden="object"),
    "hidden bits": Variant(hidden="bits"),
}


def random_model(anchors: int, device) -> AnchorModel:
    """``anchors`` anchors (× OFFSETS Gaussians) filling the view of the identity camera, 2–4 units away."""
    g = torch.Generator().manual_seed(0)
    xyz = torch.rand(anchors, 3, generator=g) * torch.tensor([4.0, 3.0, 2.0]) - torch.tensor([2.0, 1.5, -2.0])
    return AnchorModel(
        xyz=xyz, feat=torch.randn(anchors, FEAT, generator=g) * 0.5,
        offsets=torch.randn(anchors, OFFSETS, 3, generator=g) * 0.5,
        scaling=torch.log(torch.full((anchors, 6), 0.03)), rotation=torch.tensor([[1.0, 0, 0, 0]]).repeat(anchors, 1),
        opacity=torch.zeros(anchors, 1),
    ).to(device)


def render_fn(model, plain: ScaffoldHeads, variant: Variant, cam: Camera, device, tile_size: int):
    """A closure rendering ``cam`` with only ``variant``'s stages; returns (image [H, W, 3], alpha [H, W, 1]).

    Every variant decodes the same Gaussians: its heads are ``plain`` widened with neutral weights for
    its inputs, and a hidden decoder is a copy of them, so a time differs only by the effect's stage."""
    heads = neutral_heads(plain, variant.heads, num_cameras=CAMERAS)
    raster = RasterOptions(tile_size=tile_size, **variant.raster)
    private = None
    if variant.hidden is not None:
        bits = ({"message": "01" * (BITS // 2), "bit_seed": new_seed(), "bit_cell": 0.1}
                if variant.hidden == "bits" else {})
        private = PrivateHeads(heads, **bits, hidden=variant.hidden == "object").to(device)
        if private.decoder is not None:
            private.decoder.load_state_dict(heads.state_dict())
    background = torch.ones(3, device=device) if variant.background else None

    def fn():
        out = render_view(model, heads, cam, background, raster, camera_index=1)
        image, alpha = out["image"], out["alpha"]
        if private is not None and private.decoder is not None:
            hid = render_view(model, private.decoder, cam, None, raster, offset_source=private.hidden_offsets,
                              anchor_source=private.anchor_source)
            image, alpha = image + hid["image"], alpha + hid["alpha"]
        if private is not None and private.bits is not None:
            image = image + 0.0 * private.bit_logits(model.feat, model.xyz)[0].sigmoid().mean()
        return image, alpha
    return fn


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--anchors", type=int, default=2000)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--tile-size", type=int, default=None, help="default: 8 on the CPU, 16 on CUDA")
    ap.add_argument("--out", default="runs/bench_effects")
    args = ap.parse_args()
    device = args.device
    tile = args.tile_size or RasterOptions.for_device(device).tile_size
    f = 0.9 * args.width
    K = np.array([[f, 0, args.width / 2], [0, f, args.height / 2], [0, 0, 1]], dtype=np.float32)
    cam = Camera("bench", np.eye(4, dtype=np.float32), K, args.width, args.height)
    model = random_model(args.anchors, device)
    grads = (torch.rand(args.height, args.width, 3, device=device), torch.rand(args.height, args.width, 1, device=device))

    torch.manual_seed(0)
    plain = ScaffoldHeads(FEAT, OFFSETS).to(device)
    fns = {name: render_fn(model, plain, e, cam, device, tile) for name, e in VARIANTS.items()}
    times = {(name, bwd): [] for name in fns for bwd in (False, True)}
    for name, fn in fns.items():  # warm-up: compiles each variant's kernels once
        timed(fn, True, device, 1, 1, grads)
    for _ in range(args.rounds):
        for name, fn in fns.items():
            for bwd in (False, True):
                times[(name, bwd)].append(timed(fn, bwd, device, 0, 1, grads))

    med = {key: statistics.median(v) for key, v in times.items()}
    rows = [{"variant": name, "fwd_ms": med[(name, False)],
             "fwd_bwd_ms": med[(name, True)], "fwd_ratio": med[(name, False)] / med[("base", False)],
             "fwd_bwd_ratio": med[(name, True)] / med[("base", True)]} for name in fns]
    header = (f"{device}, {args.width}x{args.height}, {args.anchors} anchors × {OFFSETS} offsets, tile {tile}, "
              f"median of {args.rounds} interleaved rounds\n\n")
    md = header + "| variant | fwd ms | fwd+bwd ms | fwd ratio | fwd+bwd ratio |\n|---|---|---|---|---|\n"
    md += "".join(f"| {r['variant']} | {r['fwd_ms']:.2f} | {r['fwd_bwd_ms']:.2f} | "
                  f"{r['fwd_ratio']:.2f} | {r['fwd_bwd_ratio']:.2f} |\n" for r in rows)
    print(md)
    os.makedirs(args.out, exist_ok=True)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(os.path.join(args.out, "effects.csv"), lambda fh: fh.write(buf.getvalue().encode()))
    atomic_write(os.path.join(args.out, "effects.md"), lambda fh: fh.write(md.encode()))


if __name__ == "__main__":
    main()
