"""``RasterOptions.capture``: ``rasterize`` replayed from Warp graphs for fixed-size loops.

One ``_Captured`` per (device, N, C, image size, options) holds static copies of the inputs, one
``RenderPlan`` over them and an intersection capacity: set from its first render's count (read on
the host once), and grown only past a later render that overflowed it. The forward (projection,
binning to the capacity with padding keys, blend) and the backward (blend adjoint, projection
adjoint) are captured as Warp graphs on CUDA after a first direct run and replayed thereafter; on
the CPU the same launches run directly.

The eager op learns the intersection count and the inputs' finiteness before it sorts (one host
synchronisation). A replay cannot: its graph checks the inputs and writes both into one status
buffer, copied to host memory asynchronously, and the next forward of the same entry reads it after
waiting for that earlier forward only (not for the work queued since). A non-finite input raises
there. A count past the capacity (the render lacked some
intersections) grows that entry's capacity for the renders to come, and raises unless the caller
already asked whether that render was complete (``info["complete"]``, which itself raises for a
non-finite input): a training loop that asks can drop the step instead of stopping
(``train.base.ViewTrainer.step``).

Two renders of the same shape may be in flight at once (a public and a hidden render before one
backward): an entry is leased from forward until its backward ran or its autograd graph was freed,
and a busy entry makes the pool build another.
"""
from __future__ import annotations

import collections
import functools
import gc

import torch
import warp as wp

from .kernels.checks import flag_nonfinite
from .lease import Lease
from .rasterizer import OUTPUT_NAMES, SECOND_BACKWARD, RasterOptions, RenderPlan, check_finite
from .warp_scope import warp_stream

# Capacity = HEADROOM × the intersections of the first render (or of one that overflowed it) +
# SLACK: room for the scene to move.
HEADROOM = 1.25
SLACK = 4096
# Shapes kept: a loop whose N changes every call gains nothing from capture, and must not keep
# a graph and buffers per N; the least recently used shape without a render in flight goes first.
MAX_SHAPES = 4

_POOL: collections.OrderedDict[tuple, list[_Captured]] = collections.OrderedDict()


class _Captured:
    def __init__(self, inputs: dict, checked: dict, width: int, height: int, opts: RasterOptions):
        self.static, self.names, self.checks = _static_inputs(inputs, checked)
        # The inputs each forward copies in: all but a colour table that is the colours themselves
        # (the same for every render of the entry: the table's storage is one of its options).
        self.copied = [name for name, t in inputs.items() if name != "color_table" or t is not inputs["colors"]]
        self.static_copied = [self.static[name] for name in self.copied]
        self.plan = RenderPlan(self.static, width, height, opts)
        self.cuda = self.static["means"].device.type == "cuda"
        # What each forward writes for the host to read: [1 + K] int64, the intersection count, then
        # 1 for each of the K checked inputs (``self.names``) holding a NaN or inf.
        self.status = torch.zeros(1 + len(checked), device=self.static["means"].device, dtype=torch.int64)
        self.w_status = wp.from_torch(self.status, dtype=wp.int64)
        with self.plan.scoped():
            self.plan.project_and_count()
        needed = int(self.plan.ends[-1]) if self.plan.n else 0
        self.plan.allocate_intersections(int(needed * HEADROOM) + SLACK)
        self.graphs = {}
        self.busy = False
        self.pending: _Render | None = None  # the last forward, not yet read
        if self.cuda:  # where the replays' status lands, asynchronously
            self.host_status = torch.empty_like(self.status, device="cpu", pin_memory=True)
        # Gradients the backward accumulates into, zeroed by each replay: the inputs' (the projection's
        # adjoint adds to them), the blending backward's table and the background's. The projection's
        # outputs' gradients and the colours' are overwritten from the table.
        w = self.plan.w
        self.zeroed_grads = [w[k].grad for k in ("means", "quats", "scales", "opacities", "background")]
        self.zeroed_grads.append(w["gaussian_grads"])
        # Where each backward copies the output gradients (dL/d image, alpha, depth) for its graph.
        self.cotangents = [torch.zeros_like(self.plan.out[k]) for k in ("image", "alpha", "depth")]
        self.w_cotangents = [wp.from_torch(t, dtype=wp.float32) for t in self.cotangents]

    def _forward_ops(self):
        self.w_status.zero_()
        for values, ends, first_slot in self.checks:
            wp.launch(flag_nonfinite, dim=values.shape[0], inputs=[values, ends, self.w_status, first_slot])
        self.plan.project_and_count()
        if self.plan.n:
            wp.copy(self.w_status, self.plan.w["ends"], src_offset=self.plan.n - 1, count=1)
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
        # On the CPU, or inside a caller's CUDA graph (secure.hidden_graph), which records these
        # launches itself, the launches run directly.
        direct = not self.cuda or torch.cuda.is_current_stream_capturing()
        graph = None if direct else self.graphs.get(name)
        if graph is not None:
            # A replay names its stream: it needs none of the scope's device and stream switches.
            wp.capture_launch(graph, stream=warp_stream(self.static["means"].device))
            return
        with self.plan.scoped():
            ops()
            if direct:
                return
            side = torch.cuda.Stream(self.static["means"].device)
            side.wait_stream(torch.cuda.current_stream())
            w_side = warp_stream(side)
            # A garbage collection during the capture could free a CUDA graph (a caller's, or an
            # evicted entry's), which CUDA refuses while a stream captures, and the capture would
            # fail: collect before (as torch.cuda.graph does) and not during.
            gc.collect()
            collecting = gc.isenabled()
            gc.disable()
            try:
                # Warp launches go to its current stream: make it the capturing one.
                with wp.ScopedStream(w_side), wp.ScopedCapture(device=self.plan.device, stream=w_side) as capture:
                    ops()
            finally:
                if collecting:
                    gc.enable()
            torch.cuda.current_stream().wait_stream(side)
            self.graphs[name] = capture.graph

    def check_pending(self, grow: bool = True) -> None:
        """Read the last forward once it has finished: raise for a non-finite input; for an
        overflow of the capacity, grow it past that render's count (``grow``; its graphs are
        captured again) and raise unless its caller asked ``complete()``."""
        render, self.pending = self.pending, None
        if render is None:
            return
        render.read()
        check_finite((render.names, render.finite))
        if render.needed > render.capacity:
            if grow:
                self.grow(render.needed)
            if not render.asked:
                raise RuntimeError(
                    f"a captured render needed {render.needed} tile intersections, more than the capacity of "
                    f"{render.capacity} fixed by the renders of its shape before it: its image lacked some (the "
                    "capacity has grown for the next render); check info['complete'] where the scene changes "
                    "this much, or render with capture=False")

    def forward(self, inputs: dict) -> tuple[list, _Render]:
        self.check_pending()
        # One multi-tensor copy (a launch or two on CUDA) rather than one a tensor.
        torch._foreach_copy_(self.static_copied, [inputs[name] for name in self.copied])
        self._run("forward", self._forward_ops)
        if self.cuda and torch.cuda.is_current_stream_capturing():
            # Inside a caller's graph nothing runs before its replays: there is nothing to read
            # now. The caller compares info["n_intersections"] with info["capacity"] after each.
            self.pending = None
        elif self.cuda:
            self.host_status.copy_(self.status, non_blocking=True)
            event = torch.cuda.Event()
            event.record()
            self.pending = _Render(event, self.host_status, self.names, self.plan.capacity)
        else:
            self.pending = _Render(None, self.status.clone(), self.names, self.plan.capacity)
        return copies([self.plan.out[k] for k in OUTPUT_NAMES] + [self.status[0]]), self.pending

    def grow(self, needed: int) -> None:
        """Make room for a render of ``needed`` intersections and those to come (its graphs are
        captured again)."""
        # The old buffers may still be read by a queued replay: torch's allocator reuses them only
        # after the work queued on its stream, the one every launch here uses.
        self.plan.allocate_intersections(int(needed * HEADROOM) + SLACK)
        self.graphs.clear()  # they sort into the old buffers

    def backward(self, grads, means2d_grad: torch.Tensor) -> list:
        """The inputs' gradients (fresh tensors) from the output gradients (image, alpha, depth; None
        for an output the loss does not use); adds dL/d means2d into ``means2d_grad``."""
        given = []
        for buffer, g in zip(self.cotangents, grads):
            if g is None:
                buffer.zero_()
            else:
                given.append((buffer, g))
        if given:
            torch._foreach_copy_(*map(list, zip(*given)))
        self._run("backward", self._backward_ops)
        # Read in stream order, before any later replay overwrites it.
        means2d_grad += self.plan.means2d_grad
        return copies(self.plan.grads)


class _Render:
    """One captured forward's status (intersection count, then a non-finite flag per checked input
    named in ``names``), in host memory that its entry's next forward reuses: read (``read``) before
    that, and kept."""

    def __init__(self, event, status: torch.Tensor, names: tuple, capacity: int):
        self.event, self.status, self.names, self.capacity = event, status, names, capacity
        self.needed: int | None = None
        self.finite: list | None = None
        self.asked = False

    def read(self) -> None:
        if self.needed is None:
            if self.event is not None:
                self.event.synchronize()
            count, *flags = self.status.tolist()
            self.needed, self.finite = count, [flag == 0 for flag in flags]

    def complete(self) -> bool:
        """Whether the capacity held every tile intersection of this render (waits for it only);
        raises, as the eager op does, for a non-finite input."""
        self.asked = True
        self.read()
        check_finite((self.names, self.finite))
        return self.needed <= self.capacity


def settle() -> None:
    """Read the last forward of every entry not awaiting its backward (``check_pending``): a
    caller's CUDA graph that records captured renders (secure.hidden_graph) cannot wait for one
    while it captures, and takes only such entries. A busy entry's render is its caller's to ask
    about (``complete``) before it is read."""
    for entries in _POOL.values():
        for entry in entries:
            if not entry.busy:
                entry.check_pending()


def _static_inputs(inputs: dict, checked: dict):
    """A captured entry's copies of ``inputs`` (the buffers its graphs read), the names of the
    ``checked`` inputs (error name → key of ``inputs``) in the order of their status slots, and the
    launches of ``flag_nonfinite`` that check them: [(values, segment ends, first slot)].

    The checked float32 inputs share one buffer, each padded with zeros to whole vec4s, so that one
    launch reading four values a thread checks them all (segment s, ending at vec4 ends[s], is slot
    1 + s); a float16 colour table is checked by a launch of its own."""
    device = inputs["means"].device
    wide = [name for name, key in checked.items() if inputs[key].dtype == torch.float32]
    names = tuple(wide) + tuple(name for name in checked if name not in wide)
    sizes = [-(-inputs[checked[name]].numel() // 4) for name in wide]  # in vec4s
    arena = torch.zeros(max(sum(sizes), 1), 4, device=device, dtype=torch.float32)
    static, start = {}, 0
    for name, size in zip(wide, sizes):
        t = inputs[checked[name]]
        static[checked[name]] = arena.view(-1)[4 * start:4 * start + t.numel()].view(t.shape).copy_(t)
        start += size
    for key, t in inputs.items():
        if key not in static:
            static[key] = t.detach().clone()
    if inputs["color_table"] is inputs["colors"]:
        static["color_table"] = static["colors"]
    ends = torch.tensor(sizes, dtype=torch.int32).cumsum(0, dtype=torch.int32).to(device)
    checks = [(wp.from_torch(arena, dtype=wp.vec4), wp.from_torch(ends, dtype=wp.int32), 1)] if wide else []
    for slot, name in enumerate(names[len(wide):], 1 + len(wide)):
        t = static[checked[name]]
        checks.append((wp.from_torch(t.reshape(-1), dtype=wp.dtype_from_torch(t.dtype)),
                       wp.from_torch(torch.tensor([t.numel()], dtype=torch.int32, device=device), dtype=wp.int32), slot))
    return static, names, checks


def copies(tensors: list) -> list:
    """Fresh copies of ``tensors``: one multi-tensor copy per dtype (a launch on CUDA) rather than a
    clone each. A replay overwrites its entry's buffers, which the caller's tensors must outlive."""
    out = [torch.empty_like(t) for t in tensors]
    groups = collections.defaultdict(lambda: ([], []))
    for dst, src in zip(out, tensors):
        groups[src.dtype][0].append(dst)
        groups[src.dtype][1].append(src)
    for dst, src in groups.values():
        torch._foreach_copy_(dst, src)
    return out


def _acquire(inputs: dict, checked: dict, width: int, height: int, opts: RasterOptions) -> _Captured:
    means, colors = inputs["means"], inputs["colors"]
    key = (str(means.device), means.shape[0], colors.shape[1], width, height, opts)
    entries = _POOL.setdefault(key, [])
    _POOL.move_to_end(key)
    while len(_POOL) > MAX_SHAPES:
        idle = next((k for k, v in _POOL.items() if k != key and not any(e.busy for e in v)), None)
        if idle is None:
            break
        for entry in _POOL.pop(idle):  # an evicted entry's last render is still checked
            entry.check_pending(grow=False)
    for entry in entries:
        if not entry.busy:
            return entry
    entries.append(_Captured(inputs, checked, width, height, opts))
    return entries[-1]


class _CapturedRasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, background, inputs, width, height, opts, info, checked):
        wp.init()
        entry = _acquire(inputs, checked, width, height, opts)
        outputs, render = entry.forward(inputs)
        # Taken once the replay is queued (nothing else can take the entry in between).
        ctx.lease = Lease(entry)
        ctx.info = info
        # For a caller's graph that records this render (secure.hidden_graph): the capacity it
        # replays with, the entry's growth, and a lease that keeps the entry (and so the buffers the
        # graph reads) from other renders while the graph lives.
        info.update(capacity=entry.plan.capacity, grow=entry.grow, lease=functools.partial(Lease, entry))
        if render is not None:
            info["complete"] = render.complete
        ctx.mark_non_differentiable(*outputs[3:8])
        # An output the loss does not use gets None in backward, not a tensor of zeros its size.
        ctx.set_materialize_grads(False)
        return tuple(outputs)

    @staticmethod
    def backward(ctx, g_image, g_alpha, g_depth, *_):
        lease = ctx.lease
        if lease is None:
            raise RuntimeError(SECOND_BACKWARD)
        ctx.lease = None
        try:
            grads = lease.entry.backward((g_image, g_alpha, g_depth), ctx.info["means2d_grad"])
        finally:
            lease.release()
        # means, quats, scales, opacities, colors, background; nothing for the rest.
        return (*grads, None, None, None, None, None, None)


def rasterize_captured(inputs: dict, width: int, height: int, opts: RasterOptions, info: dict, checked: dict):
    """``rasterize``'s outputs (image, alpha, depth, radii, means2d, conics, depths, opacities,
    n_intersections as a 0-d device tensor) from a pooled captured entry; ``inputs`` as
    ``RenderPlan`` takes them; ``checked``: the inputs whose finiteness is checked, as name in an
    error message → key of ``inputs``."""
    return _CapturedRasterize.apply(inputs["means"], inputs["quats"], inputs["scales"], inputs["opacities"],
                                    inputs["colors"], inputs["background"], inputs, width, height, opts, info, checked)
