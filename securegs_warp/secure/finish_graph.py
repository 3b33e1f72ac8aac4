"""The finishing phase's step replayed from CUDA graphs (``SecureConfig.hidden_capture`` on CUDA).

In the finishing phase (``SecureConfig.hidden_finish``) only the private heads train, on hidden
renders of a release that no longer changes, so every step has the same shapes: the serving
anchors' rows, the views' size, the rasterizer's intersection capacity. The step is bound by host
work (docs/results.md, "The finishing phase replayed"): a few hundred small torch ops and autograd
nodes around the decoding and rasterize that already replay. So the whole step is captured, in two
graphs. The first draws the attacks, decodes, rasterizes, takes the loss and its backward, and
tests the gradients' finiteness and each render's intersection count against its capacity; the
second applies Adam. Between the two the host reads that test (one synchronisation, as the eager
step's gradient check) and skips the update of a step that failed it, as
``ViewTrainer.checked_update`` does. A render that overflowed its capacity grows it, and the graphs
are captured again.

A replay reads its view from fixed buffers: the camera's matrices and each secret's hidden target,
copied in before it. The attacks draw from the device's default generator, which torch's graphs advance at
every replay (``robust.perturb`` with only device-drawn attacks reads nothing back to the host).
The graphs are captured after WARMUP eager steps of the phase (kernels loaded, the rasterizer's
capacity set, Adam's state made); the last runs on a side stream, as torch asks of a capture's
warm-up.

Two differences from the eager step: a non-finite rasterizer input does not raise (the eager
rasterize checks its inputs before it sorts; a replay cannot) but gives non-finite gradients, and
the step is skipped and logged as such; and the graphs, with the memory of a step's intermediate
tensors, live as long as the trainer.
"""
from __future__ import annotations

import copy

import torch
import warp as wp

from ..render import camera_tensors
from ..train.base import frozen, nonfinite_gradient_counts
from ..warp_scope import warp_stream

# Eager phase steps before the capture (and again after a render overflowed its capacity).
WARMUP = 3
# The phase's attacks a replay draws: those of robust.DEVICE_DRAWN that the CUDA tests replay.
# noise-xyz draws on the device too, but it also changes which anchors serve (by rank), a path no
# test has replayed inside a capture: a phase that trains against it runs op by op.
REPLAYED_ATTACKS = ("prune-random", "noise-feat")


def replayable(trainer) -> bool:
    """Whether ``trainer``'s finishing steps can be replayed: on CUDA with ``hidden_capture``,
    training views of one size, every hidden render a whole view (no crop) of fixed rows replayed by
    the rasterizer (``SecureTrainer.replays_hidden_raster``) of a payload with a target per training
    view, and only REPLAYED_ATTACKS."""
    if not (trainer.device.type == "cuda" and trainer.secure.hidden_capture):
        return False
    if any(attack.name not in REPLAYED_ATTACKS for attack in trainer.finish_robust):
        return False
    if len({(cam.width, cam.height) for cam in trainer.scene.train}) > 1:  # the fixed buffers hold one view
        return False
    rendered = [secret for secret, p in enumerate(trainer.payloads) if p.has_images]
    return all(trainer.payloads[secret].views is not None and not trainer.crops_hidden(secret)
               and trainer.replays_hidden_raster(secret, trainer.strategy.reads_hidden, None)
               for secret in rendered)


class FinishGraph:
    """The finishing phase's step of one ``SecureTrainer`` (``replayable``), replayed once captured.

    ``ready``: whether ``step`` replays (else the trainer runs the step eagerly and calls
    ``after_eager``). ``step(index)`` returns (loss as a 0-d tensor, the hidden PSNRs as
    functions as ``_hidden_losses`` reports them, what was skipped and why)."""

    def __init__(self, trainer):
        self.trainer = trainer
        self.eager_steps = 0
        self.graphs = None  # (forward and backward, update) once captured
        self.side = torch.cuda.Stream(trainer.device)
        # Once captured: the camera the replays render, secret -> (that camera, target buffer), the
        # rasterizer's info of each render and the leases that keep its entry, and the outputs a
        # replay writes. status: [1 + R] bool (the gradients finite, then each of the R renders
        # within its capacity).
        self.camera, self.views, self.infos, self.leases = None, {}, [], []
        self.loss = self.extra = self.status = self.warp_capture = None

    @property
    def ready(self) -> bool:
        return self.graphs is not None

    def eager_stream(self):
        """Where an eager phase step runs: the last before the capture on a side stream."""
        if self.eager_steps == WARMUP - 1:
            self.side.wait_stream(torch.cuda.current_stream())
            return torch.cuda.stream(self.side)
        return torch.cuda.stream(torch.cuda.current_stream())

    def after_eager(self, step: int, index: int) -> None:
        """Count an eager phase step; after the WARMUP-th, capture the graphs."""
        self.eager_steps += 1
        if self.eager_steps == WARMUP:
            torch.cuda.current_stream().wait_stream(self.side)
            self._capture(step, index)

    def _capture(self, step: int, index: int) -> None:
        t = self.trainer
        optimizer = t._finishing_optimizer()
        _make_capturable(optimizer)
        params = [p for group in optimizer.param_groups for p in group["params"]]
        # The view every secret renders: a camera whose matrices are fixed tensors, and each
        # secret's target buffer.
        self.camera = copy.copy(t.scene.train[index])
        self.camera.device_tensors = tuple(x.clone() for x in camera_tensors(t.scene.train[index], t.device))
        self.views = {secret: (self.camera, p.views[index].clone()) for secret, p in enumerate(t.payloads)
                      if p.has_images}
        optimizer.zero_grad(set_to_none=True)  # the backward's gradients live in the graph's memory
        index_of = t.device.index if t.device.index is not None else torch.cuda.current_device()
        draws = torch.cuda.default_generators[index_of]
        forward, renders = torch.cuda.CUDAGraph(), []
        # Torch captures, on a stream Warp launches on too; Warp is told of the capture (external),
        # so that its sorts' scratch memory is freed after the capture rather than during it.
        stream = warp_stream(self.side)
        with frozen(t.model.anchors, t.model.heads), wp.ScopedStream(stream), \
                torch.cuda.graph(forward, stream=self.side):
            wp.capture_begin(stream=stream, force_module_load=False, external=True)
            try:
                anchors = t._attacked_anchors(None, t.finish_robust, draws=draws)
                self.extra, _ = t._hidden_losses(index, renders, step, anchors, None, 1.0, views=self.views)
                self.loss = t.image_losses(renders)
                self.loss.backward()
                grads = [p.grad for p in params if p.grad is not None]
                finite = torch.isfinite(torch.nn.utils.get_total_norm(grads, norm_type=1.0))
                complete = torch.stack([out["info"]["n_intersections"] <= out["info"]["capacity"]
                                        for out, _, _ in renders])
                self.status = torch.cat([finite[None], complete])
            finally:
                # Warp's record of the capture keeps the kernel modules it launched loaded.
                self.warp_capture = wp.capture_end(stream=stream)
        update = torch.cuda.CUDAGraph()
        with torch.cuda.graph(update, pool=forward.pool(), stream=self.side):
            optimizer.step()
        self.infos = [out["info"] for out, _, _ in renders]
        # The rasterizer's entries stay this graph's while it lives: no other render may write or
        # regrow the buffers it reads.
        self.leases = [info["lease"]() for info in self.infos]
        self.graphs = (forward, update)

    def step(self, index: int) -> tuple[torch.Tensor, dict, dict]:
        t = self.trainer
        for fixed, value in zip(self.camera.device_tensors, camera_tensors(t.scene.train[index], t.device)):
            fixed.copy_(value)
        for secret, (_, target) in self.views.items():
            target.copy_(t.payloads[secret].views[index])
        forward, update = self.graphs
        forward.replay()
        finite, *complete = self.status.tolist()
        skipped = {}
        if not finite:
            bad = nonfinite_gradient_counts(t._finishing_optimizer())
            skipped.update(nonfinite_grads=sum(bad.values()), nonfinite_groups=sorted(bad))
        if not all(complete):
            skipped["incomplete_renders"] = complete.count(False)
            self._regrow([info for info, ok in zip(self.infos, complete) if not ok])
        if not skipped:
            update.replay()
        return self.loss, self.extra, skipped

    def _regrow(self, overflowed: list) -> None:
        """After a replay whose renders (their rasterize infos ``overflowed``) needed more
        intersections than their capacities: grow them, drop the graphs (they read the old buffers)
        and capture again after WARMUP eager steps."""
        for lease in self.leases:
            lease.release()
        for info in overflowed:
            info["grow"](int(info["n_intersections"]))
        self.graphs, self.leases, self.eager_steps = None, [], 0
        self.trainer._finishing_optimizer().zero_grad(set_to_none=True)


def _make_capturable(optimizer: torch.optim.Adam) -> None:
    """Adam that a CUDA graph can replay: its step counts and learning rates on the device (the
    trainer fills each group's learning rate in place before every step)."""
    for group in optimizer.param_groups:
        device = group["params"][0].device
        group["capturable"] = True
        if not torch.is_tensor(group["lr"]):
            group["lr"] = torch.tensor(float(group["lr"]), device=device)
        for p in group["params"]:
            state = optimizer.state.get(p)
            if state and not state["step"].is_cuda:
                state["step"] = state["step"].to(device=device, dtype=torch.float32)
