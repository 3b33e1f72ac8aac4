"""Probe: where a key's hidden Gaussians lie in its box, and where F_o†'s default initialisation
puts them (the figures of docs/results.md, "Hidden Gaussians that start on the object's surface").

For each RUN (a `securegs hide` run folder of the box frame): the hidden Gaussians the key decodes
for its first hidden view, and how many lie in each eighth of the box's height (box units -1..1,
bottom first). With --init: the spread of F_o†'s raw outputs at the default box-frame sizes on
random inputs (seed 0), and the 90th percentile of the offsets' coordinates (box units).

    PYTHONPATH=. python docs/probes/hidden_placement.py RUN [RUN ...] [--init]
"""
import sys
from pathlib import Path

import torch

from securegs_warp.cli.common import quiet_warp
from securegs_warp.config import BOX_FRAME_DEFAULTS, HeadsConfig
from securegs_warp.scaffold_model import build_heads
from securegs_warp.secure.container import PLAIN_KEY, KeyViews, open_container
from securegs_warp.secure.heads import PrivateHeads

quiet_warp()
for run in (Path(a) for a in sys.argv[1:] if a != "--init"):
    model, meta = open_container(run / "public", run / PLAIN_KEY)
    centre, half = model.private.box
    with torch.no_grad():
        means = model.hidden_gaussians(KeyViews.from_metadata(meta, "cpu").hidden[0])["means"]
    heights = torch.histc((means[:, 2] - centre[2]) / half[2], bins=8, min=-1, max=1).int().tolist()
    print(f"{run}: {len(means)} hidden Gaussians; by eighth of the box's height, bottom first: {heights}")
if "--init" in sys.argv:
    torch.manual_seed(0)
    options = {k: BOX_FRAME_DEFAULTS[k] for k in ("n_hidden", "width", "serving", "encoding")}
    public = HeadsConfig()
    heads = PrivateHeads(build_heads(public), frame="box", **options)
    with torch.no_grad():
        where = torch.rand(BOX_FRAME_DEFAULTS["serving"], 3) * 4 - 2
        feat = 0.1 * torch.randn(len(where), public.feat_dim)
        raw = heads.offset_mlp(torch.cat([feat, heads.encode(where)], dim=1))
    offset = torch.tanh(raw).abs()
    print(f"F_o† at initialisation: raw std {float(raw.std()):.3f}; 90% of the offsets' coordinates within "
          f"{float(offset.quantile(0.9)):.3f} of the half-extent from the box's centre")
