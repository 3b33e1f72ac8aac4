"""The hidden branch's training step replayed from a CUDA graph (``SecureConfig.hidden_capture`` on CUDA).

A SecureGS step's hidden branch is bound by host work at 1080p (docs/results.md, "Launches in a
training step"): a few hundred small torch ops and autograd nodes around the decoding and the
rasterize, which replay on their own (``secure.captured``, ``RasterOptions.capture``). A box-frame
key decodes its serving anchors only, a count fixed between refits of its serving radius, at views
of one size: the whole branch has one shape step after step. So it is one graph. Each step copies
in what changes (the serving anchors' rows, gathered from the model into fixed buffers,
``ServingRows``; the camera's matrices; each secret's target), and the replay draws the attacks on
those rows (dropout and feature noise, drawn from the device's generator, which the graph advances
at every replay), decodes, rasterizes, takes the hidden loss and its backward, and tests each
render's intersection count against its capacity.

Its outputs: the hidden loss and images, the private heads' gradients (handed to the parameters
after each replay), and, in the joint run (``JOINT``), the gradients of the rows' features and
scalings, which ``scatter`` adds into the anchors' before the public backward adds its own. In
the finishing phase (``FINISH``) the release does not change: the rows take no gradient, and a
second graph applies Adam to the private heads. The trainer's ``checked_update`` reads the
gradients' finiteness and the renders' completeness (``complete``) as for an eager step; a render
that overflowed its capacity grows it, and the graphs are captured again.

The attacks act on the serving rows alone, which are all the hidden branch reads: dropout drops
exactly the drawn fraction of them (op by op it drops that fraction of all anchors, and so about
that fraction of the serving ones: each row is dropped as often, the count varies less), and
feature noise is scaled by the spread of the features over all anchors (``PerturbedAnchors.spread``),
as op by op. The graphs are captured after WARMUP steps that run the same ops eagerly (kernels
loaded, the rasterizer's capacity set, Adam's state made); the last of them runs on a side stream,
as torch asks of a capture's warm-up.

Differences from a step op by op:
- The attacks are drawn from the device's default generator (seeded by the run's seed), which a
  checkpoint does not hold: a resumed run draws other attacks than an uninterrupted one would.
- A non-finite rasterizer input does not raise (the eager rasterize checks its inputs before it
  sorts; a replay cannot) but gives non-finite gradients, and the step is skipped and logged as such.
- The graphs, with the memory of a step's intermediate tensors, live until they are dropped
  (``close``: when the finishing phase begins, when its trainer is restored from a checkpoint) or
  their trainer is.
"""
from __future__ import annotations

import copy

import torch
import warp as wp

from .. import raster_graph
from ..attacks import column_spread
from ..render import camera_tensors
from ..warp_scope import warp_stream
from .robust import PerturbedAnchors, perturb

JOINT, FINISH = "joint", "finish"
# Steps run op by op before the capture (and again after a render overflowed its capacity or a
# key's serving count changed).
WARMUP = 3
# The attacks a replay draws: those of robust.DEVICE_DRAWN that the CUDA tests replay. noise-xyz
# draws on the device too, but it also changes which anchors serve (by rank), which the gathered
# rows cannot: a run that trains against it runs op by op.
REPLAYED_ATTACKS = ("prune-random", "noise-feat")
# The attributes gathered of each serving anchor: all of PerturbedAnchors' (the private decoding
# reads xyz, feat and scaling; the rest keep the rows a whole PerturbedAnchors).
ROW_FIELDS = ("xyz", "feat", "offsets", "scaling", "rotation", "opacity")
# The rows' attributes that take the hidden loss's gradient in the joint run.
TRAINED_FIELDS = ("feat", "scaling")


def replayable(trainer, phase: str) -> bool:
    """Whether ``trainer``'s hidden branch in ``phase`` (JOINT or FINISH) can be replayed: on CUDA
    with ``hidden_capture``, the phase's attacks among REPLAYED_ATTACKS, training views of one size,
    every hidden render a whole view (no crop) of a box-frame key's serving rows rasterized with
    the capture (``SecureTrainer.replays_hidden_raster``; the cover mode, whose strategy reads no
    hidden Gaussian) of a payload with a target per training view."""
    if not (trainer.device.type == "cuda" and trainer.secure.hidden_capture):
        return False
    attacks = trainer.robust if phase == JOINT else trainer.finish_robust
    if any(attack.name not in REPLAYED_ATTACKS for attack in attacks):
        return False
    if len({(cam.width, cam.height) for cam in trainer.scene.train}) > 1:  # the fixed buffers hold one view
        return False
    rendered = _rendered(trainer)
    return bool(rendered) and all(
        trainer.payloads[secret].views is not None and not trainer.crops_hidden(secret)
        and trainer.replays_hidden_raster(secret, trainer.strategy.reads_hidden, None) for secret in rendered)


def _rendered(trainer) -> list[int]:
    """The secrets of ``trainer`` that have a hidden render (whose rows a graph decodes)."""
    return [secret for secret, p in enumerate(trainer.payloads) if p.has_images]


class ServingRows:
    """Fixed buffers holding one key's S serving anchors' rows, in the order of its serving index,
    and the model's feature spread: ``view`` is the ``PerturbedAnchors`` (``serving_rows``) the key
    decodes, xyz [S, 3], feat [S, d], offsets [S, k, 3], scaling [S, 6], rotation [S, 4], opacity
    [S, 1], spread {"feat": [1, d]}; its TRAINED_FIELDS are leaves taking gradients when ``trained``.
    ``index`` [S] long: the model rows they were last gathered from (the key's serving index, read
    outside any graph). Made from ``anchors`` (an ``AnchorModel``) and ``index``, and refilled every
    step (``fill``)."""

    def __init__(self, anchors, index: torch.Tensor, trained: bool):
        rows = {name: torch.empty_like(getattr(anchors, name).detach()[:len(index)]) for name in ROW_FIELDS}
        for name in TRAINED_FIELDS:
            rows[name].requires_grad_(trained)
        self.index = index
        self.view = PerturbedAnchors(**rows, serving_rows=True, spread={"feat": torch.empty_like(anchors.feat.detach()[:1])})
        self.fill(anchors, index)

    def fill(self, anchors, index: torch.Tensor) -> None:
        """Copy the rows ``index`` [S] of ``anchors`` and the spread of its features in."""
        self.index = index
        with torch.no_grad():
            for name in ROW_FIELDS:
                torch.index_select(getattr(anchors, name).detach(), 0, index, out=getattr(self.view, name))
            self.view.spread["feat"].copy_(column_spread(anchors.feat))

    def scatter(self, anchors, retain: bool) -> None:
        """Add the rows' gradients into ``anchors``' features and scalings (before the public
        backward, which adds its own). retain: leave them in the rows (a graph's buffers, which the
        next replay overwrites); else they are cleared (the next backward op by op would add to them)."""
        for name in TRAINED_FIELDS:
            leaf = getattr(self.view, name)
            if leaf.grad is None:  # a gradient share of 0 detaches it
                continue
            param = getattr(anchors, name)
            if param.grad is None:
                param.grad = torch.zeros_like(param)
            param.grad.index_add_(0, self.index, leaf.grad)
            if not retain:
                leaf.grad = None


class HiddenGraph:
    """The hidden branch of one ``SecureTrainer`` in one phase (JOINT or FINISH; ``replayable``).

    ``run(step, index)`` makes the step's hidden renders of training view ``index``, their loss and
    its backward, op by op for WARMUP steps and replayed after: returns (the hidden loss, weighted,
    as a 0-d tensor without gradient; the hidden PSNRs as functions, as ``_hidden_losses`` reports
    them; the entry that stands for the hidden renders in the step's renders, for
    ``image_losses`` and ``checked_update``). In the joint run ``scatter`` then hands the rows'
    gradients to the anchors; in the phase ``update`` is the step's optimizer update."""

    def __init__(self, trainer, phase: str):
        self.trainer, self.phase = trainer, phase
        self.attacks = trainer.robust if phase == JOINT else trainer.finish_robust
        self.side = torch.cuda.Stream(trainer.device)
        index_of = trainer.device.index if trainer.device.index is not None else torch.cuda.current_device()
        self.draws = torch.cuda.default_generators[index_of]
        # What the buffers and graphs were made for (``_made_for``).
        self.made_for = None
        # secret -> ServingRows; the camera every secret renders (its matrices fixed tensors);
        # secret -> (that camera, target buffer [H, W, 3]).
        self.rows, self.camera, self.views = {}, None, {}
        self.eager_steps = 0
        self.graphs = None  # (forward and backward, update or None) once captured
        # Once captured: each render's rasterizer info and the leases that keep its entry; the
        # outputs a replay writes (loss, extra, status: [R] bool, each render within its capacity);
        # (parameter, its gradient buffer in the graph); Warp's record of the capture.
        self.infos, self.leases, self.grads = [], [], []
        self.loss = self.extra = self.status = self.warp_capture = None
        # The last eager step's renders' completeness tests. Only those: a render's tensors would
        # keep its autograd graph's gradient accumulators, and so the stream they were made on,
        # alive into the capture, whose backward may not wait for another stream.
        self.eager_complete = []

    @property
    def ready(self) -> bool:
        return self.graphs is not None

    def _params(self) -> list:
        t = self.trainer
        return [p for secret in self.rows for p in t.model.secrets[secret].parameters()]

    def _made_for(self, step: int) -> tuple:
        """(each rendered secret's serving count, each one's features' gradient share at ``step``):
        buffers and graphs are made again when it changes (a refit to another count;
        feature_grad_until)."""
        t = self.trainer
        counts = tuple(len(t.model.secrets[s].serving_index(t.model.anchors.xyz)) for s in _rendered(t))
        shares = tuple(t.current_feature_grad(step, s) if self.phase == JOINT else 0.0 for s in _rendered(t))
        return counts, shares

    def run(self, step: int, index: int) -> tuple[torch.Tensor, dict, tuple]:
        t = self.trainer
        made_for = self._made_for(step)
        if made_for != self.made_for:
            self._make_buffers(index)
            self.made_for = made_for
        anchors = t.model.anchors
        for secret, rows in self.rows.items():
            rows.fill(anchors, t.model.secrets[secret].serving_index(anchors.xyz))
        for fixed, value in zip(self.camera.device_tensors, camera_tensors(t.scene.train[index], t.device)):
            fixed.copy_(value)
        for secret, (_, target) in self.views.items():
            target.copy_(t.payloads[secret].views[index])
        if not self.ready and self.eager_steps >= WARMUP and self._capturable():
            self._capture(step, index)
        if self.ready:
            self.graphs[0].replay()
            for p, grad in self.grads:
                p.grad = grad
            loss, extra = self.loss, self.extra
        else:
            warm_up = self.eager_steps == WARMUP - 1  # on the side stream, as the capture will run
            if warm_up:
                self.side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(self.side if warm_up else torch.cuda.current_stream()):
                loss, extra, renders, _ = self._losses(step, index)
            self.eager_complete = [out["info"]["complete"] for out, _, _ in renders if "complete" in out["info"]]
            if warm_up:
                torch.cuda.current_stream().wait_stream(self.side)
            self.eager_steps += 1
        return loss.detach(), extra, ({"loss": loss.detach(), "info": {"complete": self.complete}}, None, 1.0)

    def _make_buffers(self, index: int) -> None:
        """Buffers for the current serving rows and views; any graph of the old ones is dropped."""
        self.close()
        t = self.trainer
        anchors = t.model.anchors
        self.rows = {secret: ServingRows(anchors, t.model.secrets[secret].serving_index(anchors.xyz),
                                         trained=self.phase == JOINT) for secret in _rendered(t)}
        self.camera = copy.copy(t.scene.train[index])
        self.camera.device_tensors = tuple(x.clone() for x in camera_tensors(t.scene.train[index], t.device))
        self.views = {secret: (self.camera, t.payloads[secret].views[index].clone()) for secret in self.rows}

    def _losses(self, step: int, index: int) -> tuple:
        """The hidden renders of the buffers' rows and view, their loss and its backward (op by op,
        or recorded into a capture): (loss, extra, renders, status)."""
        t = self.trainer
        anchors = {secret: perturb(rows.view, self.attacks, t.hidden_generator, None, self.draws) if self.attacks
                   else rows.view for secret, rows in self.rows.items()}
        renders = []
        scale = t.secure.hidden_stride if self.phase == JOINT else 1.0
        extra, _ = t._hidden_losses(index, renders, step, anchors, None, scale, views=self.views)
        loss = t.image_losses(renders)
        loss.backward()
        status = torch.stack([out["info"]["n_intersections"] <= out["info"]["capacity"] for out, _, _ in renders])
        return loss, extra, renders, status

    def _capturable(self) -> bool:
        """Whether the graphs can be captured now: in the finishing phase Adam's state must exist (a
        capture would record its zero-filling, to be replayed at every step), which it does unless
        every warm-up step was skipped."""
        if self.phase == JOINT:
            return True
        optimizer = self.trainer._finishing_optimizer()
        return all(p in optimizer.state for group in optimizer.param_groups for p in group["params"])

    def _capture(self, step: int, index: int) -> None:
        t = self.trainer
        params = self._params()
        leaves = [getattr(rows.view, name) for rows in self.rows.values() for name in TRAINED_FIELDS]
        for p in (*params, *leaves):  # the backward's gradients are to live in the graph's memory
            p.grad = None
        forward, renders = torch.cuda.CUDAGraph(), None
        raster_graph.settle()
        # Torch captures, on a stream Warp launches on too; Warp is told of the capture (external),
        # so that its sorts' scratch memory is freed after the capture rather than during it.
        stream = warp_stream(self.side)
        self.side.wait_stream(torch.cuda.current_stream())
        with wp.ScopedStream(stream), torch.cuda.graph(forward, stream=self.side):
            wp.capture_begin(stream=stream, force_module_load=False, external=True)
            try:
                self.loss, self.extra, renders, self.status = self._losses(step, index)
            finally:
                # Warp's record of the capture keeps the kernel modules it launched loaded.
                self.warp_capture = wp.capture_end(stream=stream)
        update = None
        if self.phase == FINISH:
            optimizer = t._finishing_optimizer()
            _make_capturable(optimizer)
            update = torch.cuda.CUDAGraph()
            with torch.cuda.graph(update, pool=forward.pool(), stream=self.side):
                optimizer.step()
        torch.cuda.current_stream().wait_stream(self.side)
        self.grads = [(p, p.grad) for p in (*params, *leaves) if p.grad is not None]
        self.infos = [out["info"] for out, _, _ in renders]
        # The rasterizer's entries stay this graph's while it lives: no other render may write or
        # regrow the buffers it reads.
        self.leases = [info["lease"]() for info in self.infos]
        self.graphs = (forward, update)

    def scatter(self, anchors) -> None:
        """After ``run`` in the joint run: add the rows' gradients into ``anchors``' (``ServingRows.scatter``)."""
        for rows in self.rows.values():
            rows.scatter(anchors, retain=self.ready)

    def update(self, optimizer: torch.optim.Optimizer) -> None:
        """The finishing phase's update of the private heads: replayed once captured."""
        if self.ready:
            self.graphs[1].replay()
        else:
            optimizer.step()

    def complete(self) -> bool:
        """Whether every hidden render of the step held all its tile intersections (read after the
        step's gradient check, so it waits for nothing). A replayed render that did not grows its
        capacity, and the graphs are captured again after WARMUP eager steps."""
        if not self.ready:
            return all([complete() for complete in self.eager_complete])  # each asked: see raster_graph
        flags = self.status.tolist()
        if all(flags):
            return True
        overflowed = [info for info, ok in zip(self.infos, flags) if not ok]
        self.close()
        for info in overflowed:
            info["grow"](int(info["n_intersections"]))
        return False

    def close(self) -> None:
        """Drop the graphs and give their rasterizer entries back (another phase's, or a new
        capture's, renders may take them)."""
        for lease in self.leases:
            lease.release()
        for p, _ in self.grads:
            p.grad = None
        self.graphs, self.leases, self.grads, self.infos, self.eager_steps = None, [], [], [], 0
        self.loss = self.extra = self.status = self.warp_capture = None


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
