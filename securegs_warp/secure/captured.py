"""The private decoder of a box-frame key replayed from CUDA graphs during training.

A SecureGS step is bound by host work at 1080p (docs/results.md, "Launches in a training step"):
the hidden branch's decoding is some eighty small torch ops forward and as many autograd nodes
backward, each a launch the GPU finishes long before the host issues the next. In the box frame
the anchors that decode are the serving ones, a fixed count between refits of the serving radius,
so the decoding of their rows (``decode_rows``: view directions, the private MLPs, offsets, scales)
has a fixed shape: ``torch.cuda.make_graphed_callables`` captures its forward and its backward
once per shape, and each step replays them as one autograd node. The gathers of the anchor rows
and the opacity test stay eager (they index by data).
"""
from __future__ import annotations

import collections

import torch
from torch import nn

from ..model.neural_gaussians import decode_rows

# Shapes kept per key: the serving count changes only when a tie at the serving radius moves.
MAX_SHAPES = 4


class _Rows(nn.Module):
    """``decode_rows`` with a key's private decoder and offset predictor as this module's parameters
    (what the captured backward differentiates), the key itself held outside the module tree so
    that its bit decoder and buffers are no inputs of the graph."""

    def __init__(self, private):
        super().__init__()
        self.decoder, self.offset_mlp = private.decoder, private.offset_mlp
        self._key = (private,)

    def forward(self, xyz, feat, log_scaling, centre):
        return decode_rows(self.decoder, self._key[0].hidden_offsets, xyz, feat, log_scaling, centre)


class CapturedRows:
    """A ``RowDecoder`` for one key (``PrivateHeads`` with ``frame="box"``): the graphs of its rows'
    decoding, one per (anchor count, which inputs need a gradient); the same values as
    ``decode_rows`` up to float rounding. CUDA only; called with gradients enabled (training)."""

    def __init__(self, private):
        if private.frame != "box" or private.offset_mlp is None:
            raise ValueError("only a box-frame key with an offset predictor decodes a fixed set of anchors")
        self.private = private
        self._graphs: collections.OrderedDict[tuple, tuple] = collections.OrderedDict()

    def _sources(self) -> tuple:
        """What a graph reads by address besides its inputs: a replaced tensor needs a new capture."""
        return (*self.private.decoder.parameters(), *self.private.offset_mlp.parameters(), self.private.box)

    def __call__(self, xyz: torch.Tensor, feat: torch.Tensor, log_scaling: torch.Tensor, centre: torch.Tensor):
        if xyz.device.type != "cuda":
            raise ValueError(f"CapturedRows replays CUDA graphs; the anchors are on {xyz.device}")
        key = (xyz.shape[0], feat.requires_grad, log_scaling.requires_grad, xyz.device)
        sources = self._sources()
        entry = self._graphs.get(key)
        if entry is None or len(entry[0]) != len(sources) or any(a is not b for a, b in zip(entry[0], sources)):
            samples = (xyz.detach().clone(), feat.detach().clone().requires_grad_(feat.requires_grad),
                       log_scaling.detach().clone().requires_grad_(log_scaling.requires_grad), centre.detach().clone())
            # The capture's warm-up runs on a side stream, where the parameters' gradient
            # accumulators are made; later backwards feed them from torch's current stream, which
            # torch orders with a wait between the streams on the device (not the host) and warns
            # of at the first backward. The switch is process-wide, as torch offers it.
            if hasattr(torch.autograd.graph, "set_warn_on_accumulate_grad_stream_mismatch"):
                torch.autograd.graph.set_warn_on_accumulate_grad_stream_mismatch(False)
            entry = (sources, torch.cuda.make_graphed_callables(_Rows(self.private), samples,
                                                                allow_unused_input=True))
            self._graphs[key] = entry
            while len(self._graphs) > MAX_SHAPES:
                self._graphs.popitem(last=False)
        self._graphs.move_to_end(key)
        return entry[1](xyz, feat, log_scaling, centre)
