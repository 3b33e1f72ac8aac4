"""``RasterOptions.capture``: ``rasterize`` replayed from Warp graphs for fixed-size loops.

One ``_Captured`` per (device, N, C, image size, options) holds static copies of the inputs, one
``RenderPlan`` over them and an intersection capacity fixed when it is made (the only host read of a
count). The forward (projection, binning to the capacity with padding keys, blend) and the backward
(blend adjoint, projection adjoint) are captured as Warp graphs on CUDA after a first direct run and
replayed thereafter; on the CPU the same launches run directly.

The eager op learns the intersection count and the inputs' finiteness before it sorts (one host
synchronisation). A replay cannot: it copies both to host memory asynchronously and the next forward
of the same entry checks them after waiting for that earlier forward only (not for the work queued
since), raising for an overflow of the capacity or a non-finite input of that earlier render.

Two renders of the same shape may be in flight at once (a public and a hidden render before one
backward): an entry is leased from forward until its backward ran or its autograd graph was freed,
and a busy entry makes the pool build another.
"""
from __future__ import annotations

import collections

import torch
import warp as wp

from .lease import Lease
from .rasterizer import OUTPUT_NAMES, RasterOptions, RenderPlan, check_finite

# Capacity = HEADROOM × the first render's intersections + SLACK: room for the scene to move.
HEADROOM = 1.25
SLACK = 4096
# Shapes kept: a loop whose N changes every call gains nothing from capture, and must not keep
# a graph and buffers per N; the least recently used shape without a render in flight goes first.
MAX_SHAPES = 4

_POOL: collections.OrderedDict[tuple, list[_Captured]] = collections.OrderedDict()


class _Captured:
    def __init__(self, inputs: dict, width: int, height: int, opts: RasterOptions):
        self.static = {name: t.detach().clone() for name, t in inputs.items()}
        if inputs["color_table"] is inputs["colors"]:
            self.static["color_table"] = self.static["colors"]
        self.plan = RenderPlan(self.static, width, height, opts)
        self.cuda = self.static["means"].device.type == "cuda"
        with self.plan.scoped():
            self.plan.project_and_count()
        needed = int(self.plan.ends[-1]) if self.plan.n else 0
        self.plan.allocate_intersections(int(needed * HEADROOM) + SLACK)
        self.graphs = {}
        self.busy = False
        self.pending = None  # (event, host count, host flags, names) of the last forward, unchecked
        if self.cuda:  # where the replays' count and finiteness flags land, asynchronously
            self.host_count = torch.empty(1, dtype=torch.int64, pin_memory=True)
            self.host_flags = torch.empty(len(inputs) + 1, dtype=torch.bool, pin_memory=True)
        self.zeroed_outputs = [self.plan.w[k] for k in ("means2d", "conics", "depths", "opac_out")]
        # Gradients the backward accumulates into, zeroed by each replay.
        self.zeroed_grads = [a.grad for a in self.plan.w.values() if isinstance(a, wp.array) and a.grad is not None]
        self.zeroed_grads.append(self.plan.w["colors_grad"])
        # Where each backward copies the output gradients (dL/d image, alpha, depth) for its graph.
        self.cotangents = [torch.zeros_like(self.plan.out[k]) for k in ("image", "alpha", "depth")]
        self.w_cotangents = [wp.from_torch(t, dtype=wp.float32) for t in self.cotangents]

    def _forward_ops(self):
        for a in self.zeroed_outputs:
            a.zero_()
        self.plan.project_and_count()
        self.plan.sort_intersections(self.plan.capacity, padded=True)
        self.plan.blend()

    def _backward_ops(self):
        for a in self.zeroed_grads:
            a.zero_()
        self.plan.backward(self.w_cotangents)

    def _run(self, name: str, ops) -> None:
        """``ops()`` directly (the CPU, and CUDA's first call, which also loads the kernels), then
        captured on a side stream (CUDA cannot capture torch's legacy default stream) and replayed
        on torch's current stream."""
        with self.plan.scoped():
            if not self.cuda:
                ops()
                return
            graph = self.graphs.get(name)
            if graph is None:
                ops()
                side = torch.cuda.Stream(self.static["means"].device)
                side.wait_stream(torch.cuda.current_stream())
                w_side = wp.stream_from_torch(side)
                # Warp launches go to its current stream: make it the capturing one.
                with wp.ScopedStream(w_side), wp.ScopedCapture(device=self.plan.device, stream=w_side) as capture:
                    ops()
                torch.cuda.current_stream().wait_stream(side)
                self.graphs[name] = capture.graph
            else:
                wp.capture_launch(graph, stream=wp.stream_from_torch(torch.cuda.current_stream()))

    def check_pending(self) -> None:
        """Raise for the last forward's overflow or non-finite input, once it has finished."""
        if self.pending is None:
            return
        event, count, flags, names = self.pending
        self.pending = None
        if event is not None:
            event.synchronize()
        check_finite((names, flags.tolist()))
        if int(count) > self.plan.capacity:
            raise RuntimeError(
                f"a captured render needed {int(count)} tile intersections, more than the capacity of "
                f"{self.plan.capacity} fixed when its shape was first rendered: its image lacked some; render "
                f"with capture=False where the scene changes this much")

    def forward(self, inputs: dict, finite) -> list:
        self.check_pending()
        for name, t in inputs.items():
            if name != "color_table" or t is not inputs["colors"]:
                self.static[name].copy_(t)
        self._run("forward", self._forward_ops)
        names, flags = finite
        count = self.plan.ends[-1:] if self.plan.n else torch.zeros(1, dtype=torch.int64)
        flags = flags if flags is not None else torch.ones(0, dtype=torch.bool)
        if self.cuda:
            self.host_count.copy_(count, non_blocking=True)
            host_flags = self.host_flags[:flags.numel()]
            host_flags.copy_(flags, non_blocking=True)
            event = torch.cuda.Event()
            event.record()
            self.pending = (event, self.host_count, host_flags, names)
        else:
            self.pending = (None, count.clone(), flags.clone(), names)
            self.check_pending()
        out = [self.plan.out[k].clone() for k in OUTPUT_NAMES]
        return out + [self.plan.ends[-1].clone() if self.plan.n else 0]

    def backward(self, grads) -> list:
        for buffer, g in zip(self.cotangents, grads):
            if g is None:
                buffer.zero_()
            else:
                buffer.copy_(g)
        self._run("backward", self._backward_ops)
        return [g.clone() for g in self.plan.grads], self.plan.means2d_grad.clone()


def _acquire(inputs: dict, width: int, height: int, opts: RasterOptions) -> _Captured:
    means, colors = inputs["means"], inputs["colors"]
    key = (str(means.device), means.shape[0], colors.shape[1], width, height, opts)
    entries = _POOL.setdefault(key, [])
    _POOL.move_to_end(key)
    while len(_POOL) > MAX_SHAPES:
        idle = next((k for k, v in _POOL.items() if k != key and not any(e.busy for e in v)), None)
        if idle is None:
            break
        for entry in _POOL.pop(idle):  # an evicted entry's last render is still checked
            entry.check_pending()
    for entry in entries:
        if not entry.busy:
            return entry
    entries.append(_Captured(inputs, width, height, opts))
    return entries[-1]


class _CapturedRasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, background, inputs, width, height, opts, info, finite):
        wp.init()
        entry = _acquire(inputs, width, height, opts)
        lease = Lease(entry)
        try:
            outputs = entry.forward(inputs, finite)
        except BaseException:
            lease.release()
            raise
        ctx.lease = lease
        ctx.info = info
        ctx.mark_non_differentiable(*outputs[3:8])
        return tuple(outputs)

    @staticmethod
    def backward(ctx, g_image, g_alpha, g_depth, *_):
        lease = ctx.lease
        ctx.lease = None
        try:
            grads, means2d_grad = lease.entry.backward((g_image, g_alpha, g_depth))
        finally:
            lease.release()
        ctx.info["means2d_grad"] += means2d_grad
        # means, quats, scales, opacities, colors, background; nothing for the rest.
        return (*grads, None, None, None, None, None, None)


def rasterize_captured(inputs: dict, width: int, height: int, opts: RasterOptions, info: dict, finite):
    """``rasterize``'s outputs (image, alpha, depth, radii, means2d, conics, depths, opacities,
    n_intersections as a 0-d device tensor) from a pooled captured entry; ``inputs`` as
    ``RenderPlan`` takes them."""
    return _CapturedRasterize.apply(inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"],
                                    inputs["colors"], inputs["background"], inputs, width, height, opts, info, finite)
