"""The private decoder of a box-frame key replayed from CUDA graphs during training.

A SecureGS step is bound by host work at 1080p (docs/results.md, "Launches in a training step"):
the hidden branch's decoding is some eighty small torch ops forward and as many autograd nodes
backward, each a launch the GPU finishes long before the host issues the next. In the box frame
the anchors that decode are the serving ones, a count that stays fixed between refits of the
serving radius (or follows the anchors while there are no more than ``serving`` of them), so the
decoding of their rows (``decode_rows``: view directions, the latent grid's and the codes' features
where the key has them, the private MLPs, offsets, scales) has a fixed shape: ``torch.cuda.make_graphed_callables``
captures its forward and its backward once per shape, and each step replays them as one autograd
node. The gathers of the anchor rows and the opacity test stay eager (they index by data).

A replay writes fixed buffers: its outputs and the parameters' gradients. So a call decodes op by
op instead when a call of the same graph still awaits its backward (``Lease``), or when a
parameter holds a gradient (the replayed backward hands the parameters its gradient buffer, which
the next replay overwrites; training sets gradients to None after every step), or inside a
caller's graph (the whole hidden branch's, ``secure.hidden_graph``), which records the ops themselves.
"""
from __future__ import annotations

import collections
import warnings

import torch
from torch import nn

from ..lease import Lease
from ..model.neural_gaussians import decode_rows

# Shapes kept per key: the serving count changes at a tie at the serving radius, or with the
# anchors while they are no more than the serving count.
MAX_SHAPES = 4

# The capture's warm-up runs on a side stream, where the parameters' gradient accumulators are
# made, and the captured autograd graph keeps them for as long as the graph lives; each replayed
# backward then feeds them from torch's current stream, which torch orders with a wait between the
# streams on the device (not the host), warning at the first backward.
warnings.filterwarnings("ignore", message=r"The AccumulateGrad node's stream does not match")


def replayable(t: torch.Tensor) -> bool:
    """Whether CUDA graphs can decode rows on ``t``'s device."""
    return t.is_cuda


class _Rows(nn.Module):
    """``decode_rows`` with a key's private heads: their parameters are what the captured backward
    differentiates (the key's buffers are no inputs of a graph)."""

    def __init__(self, private):
        super().__init__()
        self.private = private

    def forward(self, xyz, feat, log_scaling, centre):
        return decode_rows(self.private.decoder, self.private.hidden_offsets, xyz, feat, log_scaling, centre,
                           anchor_source=self.private.anchor_source)


class _Graph:
    def __init__(self, sources: tuple, graphed: nn.Module):
        self.sources, self.graphed, self.busy = sources, graphed, False


class CapturedRows:
    """A ``RowDecoder`` for one key (``PrivateHeads`` with ``frame="box"``): the graphs of its rows'
    decoding, one per (anchor count, which inputs need a gradient); the same values as
    ``decode_rows`` up to float rounding. For CUDA tensors with gradients enabled (training;
    ``SecureModel.render_hidden`` decides)."""

    def __init__(self, private):
        if private.frame != "box" or private.offset_mlp is None:
            raise ValueError("only a box-frame key with an offset predictor decodes a fixed set of anchors")
        self.private = private
        self._graphs: collections.OrderedDict[tuple, _Graph] = collections.OrderedDict()

    def _sources(self) -> tuple:
        """What a graph reads by address besides its inputs (the parameters, the key's box): a
        replaced tensor needs a new capture. Compared by identity, not ``Kept``'s versions, since
        Adam writes the parameters in place every step and a replay reads them where they are."""
        return (*self.private.parameters(), self.private.box)

    def __call__(self, xyz: torch.Tensor, feat: torch.Tensor, log_scaling: torch.Tensor, centre: torch.Tensor):
        """The Nv*k Gaussians of Nv anchors at positions xyz [Nv, 3] (no gradient), with features feat
        [Nv, d] and log scalings [Nv, 6], seen from the camera centre [3]: ``decode_rows``' tuple."""
        sources = self._sources()
        key = (xyz.shape[0], feat.requires_grad, log_scaling.requires_grad, xyz.device)
        graph = self._graphs.get(key)
        # Inside a caller's CUDA graph (secure.hidden_graph) the ops are recorded there instead.
        if (xyz.requires_grad or (graph is not None and graph.busy)
                or (xyz.is_cuda and torch.cuda.is_current_stream_capturing())
                or any(p.grad is not None for p in sources[:-1])):
            return decode_rows(self.private.decoder, self.private.hidden_offsets, xyz, feat, log_scaling, centre,
                               anchor_source=self.private.anchor_source)
        if graph is None or len(graph.sources) != len(sources) or any(a is not b for a, b in zip(graph.sources, sources)):
            samples = (xyz.detach().clone(), feat.detach().clone().requires_grad_(feat.requires_grad),
                       log_scaling.detach().clone().requires_grad_(log_scaling.requires_grad), centre.detach().clone())
            graph = _Graph(sources, torch.cuda.make_graphed_callables(_Rows(self.private), samples,
                                                                      allow_unused_input=True))
            self._graphs[key] = graph
            while len(self._graphs) > MAX_SHAPES:
                self._graphs.popitem(last=False)
        self._graphs.move_to_end(key)
        neural_opacity, *rest = graph.graphed(xyz, feat, log_scaling, centre)
        node = neural_opacity.grad_fn
        if node is not None:
            # Busy until the replayed backward ran, or until the autograd graph holding it is freed.
            lease = Lease(graph)
            node.register_hook(lambda grad_inputs, grad_outputs: lease.release())
        # The graph's output buffers are overwritten by the next replay: the caller gets copies (an
        # uncompacted decoding hands these very tensors on, see generate_neural_gaussians).
        return tuple(t.clone() for t in (neural_opacity, *rest))
