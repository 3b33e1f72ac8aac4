"""What every trainer here shares: the view order, the step with its hooks, evaluation and
checkpoints (one class with ``step()``, ``evaluate()`` and checkpoints, Warp examples style).

A step renders one training view through ``securegs_warp.rasterize``, takes the image loss,
backpropagates, lets the densification strategy look at the gradients, then steps Adam. A
checkpoint holds everything a step changes (the model, Adam, strategy statistics, random state),
written atomically, so an interrupted run resumes where it stopped. Subclasses
(``ScaffoldTrainer``, ``GaussianTrainer``) build the model, the optimizer and its schedules.
"""
from __future__ import annotations

import contextlib
import io
import time

import torch

from .. import evaluation
from ..config import RESUMABLE_CHANGES, TrainConfig, first_difference, from_dict, to_dict
from ..data import Camera, SceneData
from ..keys import is_sealed, seal, unseal, write_private
from .losses import batch_photometric_loss, photometric_loss, psnr


class ViewTrainer:
    """The training loop of a model on a ``SceneData``, one view per step.

    A subclass sets ``model`` (with ``render(cam, options, background=, camera_index=)``),
    ``optimizer``, ``strategy`` and ``strategy_state`` in its ``__init__`` and implements
    ``_update_learning_rates``, ``densify``, ``size_stats``, ``model_state`` and ``restore_model``.
    """

    # Entries a checkpoint of this trainer must hold beyond the common ones.
    model_state_keys: tuple = ("model",)

    def __init__(self, scene: SceneData, config: TrainConfig, device: str | torch.device = "cpu"):
        if not scene.train:
            raise ValueError(f"scene {scene.name!r} has no training views")
        self.scene = scene
        self.config = config
        self.device = torch.device(device)
        self.generator = torch.Generator().manual_seed(config.seed)
        # The scene's own background (a NeRF-synthetic object on white, the synthetic sky): the
        # rasterizer composites it only because the scene asks for it; black costs nothing.
        self.background = None if scene.background is None else torch.tensor(
            scene.background, dtype=torch.float32, device=self.device)
        self.spatial_scale = float(scene.cameras_extent)
        self.step_count = 0
        self.train_seconds = 0.0  # wall time spent in step(), kept across resumes
        self._targets = [torch.as_tensor(c.image, device=self.device) for c in scene.train]
        self._order: list[int] = []

    def adam(self, groups: list[dict]) -> torch.optim.Adam:
        """Adam over ``groups`` (learning rates set per group, eps 1e-15 as 3DGS and Scaffold-GS).
        On CUDA one fused kernel updates every tensor of every group (the foreach path launches
        several per group); the update is Adam's either way, up to float rounding."""
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=self.device.type == "cuda")

    # -- what a subclass provides ---------------------------------------------------------------

    def _update_learning_rates(self, step: int) -> None:
        raise NotImplementedError

    def densify(self, step: int, branches: dict) -> dict:
        """Run the strategy's hook after backward; returns what changed."""
        raise NotImplementedError

    def densify_skipped(self, step: int) -> dict:
        """For a step whose update was skipped: what its strategy does at that step whatever the
        gradients (3DGS's opacity reset; Scaffold-GS's steps all read gradient statistics)."""
        return {}

    def size_stats(self) -> dict:
        """The model's size as reported each step ({"anchors": N} or {"gaussians": N})."""
        raise NotImplementedError

    def model_state(self) -> dict:
        """The model's entries of a checkpoint (named in ``model_state_keys``)."""
        raise NotImplementedError

    def restore_model(self, state: dict) -> None:
        """Rebuild ``model`` from ``model_state()`` output, and a fresh optimizer for it."""
        raise NotImplementedError

    # -- the step -------------------------------------------------------------------------------

    def _next_view(self) -> int:
        """Training views in a random order, each once per epoch (as 3DGS picks them). The view
        stays at the end of the order until ``step`` completes."""
        if not self._order:
            self._order = torch.randperm(len(self.scene.train), generator=self.generator).tolist()
        return self._order[-1]

    def render(self, cam: Camera, camera_index: int | None = None) -> dict:
        """The public render of one view with this run's rasterizer options and background."""
        return self.model.render(cam, self.config.raster, background=self.background, camera_index=camera_index)

    def image_loss(self, out: dict, target: torch.Tensor) -> torch.Tensor:
        """(1 − α)·L1 + α·(1 − SSIM) of one render, plus its ``regularizer``: ``image_losses`` of it alone."""
        return self.image_losses([(out, target, 1.0)])

    def image_losses(self, renders: list) -> torch.Tensor:
        """Σ weight · (share · ((1 − α)·L1 + α·(1 − SSIM)) + ``regularizer``) over ``renders`` [(out,
        target, weight)]; the photometric terms of images of one shape in one batched call (a SecureGS
        step's public and hidden renders: half the launches of separate calls, the same sum up to float
        rounding). share: ``out["pixel_share"]`` for a render of part of a view (the part's share of
        the view's pixels, the rest being background in both; secure.crop), else 1. An entry whose
        out holds "loss" (a 0-d tensor without gradient: renders whose loss was taken and
        differentiated elsewhere, weighted) adds that. Subclasses change a render's loss through
        ``regularizer``."""
        # A hidden branch replayed from a CUDA graph (secure.hidden_graph) took its loss and backward
        # there: its weighted loss joins the sum as a number.
        computed = [out["loss"] for out, _, _ in renders if "loss" in out]
        renders = [render for render in renders if "loss" not in render[0]]
        images = [out["image"] for out, _, _ in renders]
        targets = [target for _, target, _ in renders]
        if len({image.shape for image in images}) > 1:
            terms = [photometric_loss(image, target, self.config.ssim_weight) for image, target in zip(images, targets)]
        elif images:
            terms = batch_photometric_loss(torch.stack(images), torch.stack(targets), self.config.ssim_weight).unbind()
        else:  # only renders whose loss was taken elsewhere
            terms = []
        loss = None
        for term, (out, _, weight) in zip(terms, renders):
            share = out.get("pixel_share")
            term = term if share is None else share * term
            regularizer = self.regularizer(out)
            term = term if regularizer is None else term + regularizer
            term = term if weight == 1.0 else weight * term
            loss = term if loss is None else loss + term
        for term in computed:
            loss = term if loss is None else loss + term
        return loss

    def regularizer(self, out: dict) -> torch.Tensor | None:
        """A render's loss term beyond the image (None: none; Scaffold-GS adds its volume term)."""
        return None

    @property
    def total_steps(self) -> int:
        """The steps of a whole run (the SecureGS trainer adds its finishing phase)."""
        return self.config.iterations

    def step(self) -> dict:
        """One training iteration. Returns {"loss", "psnr", size_stats(), what densification changed, ...}
        ("psnr": the training view's public render; the SecureGS trainer's finishing steps, marked
        "phase": "finish", give their hidden render's instead).

        The step counter advances only once the step's work is done, so an interrupt in the middle
        leaves the trainer at the last completed step.
        """
        t0 = time.perf_counter()
        step = self.step_count + 1
        index = self._next_view()  # taken off the order only when the step completes
        result = self.train_step(step, index)
        self._order.pop()
        self.step_count = step
        self.train_seconds += time.perf_counter() - t0
        return result

    def train_step(self, step: int, index: int) -> dict:
        """Step ``step`` on training view ``index``: the public render and ``extra_losses``, one
        backward, densification and the optimizer's update."""
        self._update_learning_rates(step)
        out = self.render(self.scene.train[index], camera_index=index)
        target = self._targets[index]
        branches = {"public": (out["gaussians"], out["info"])}
        renders = [(out, target, 1.0)]
        extra = self.extra_losses(index, renders, branches, step)
        loss = self.image_losses(renders)
        loss.backward()
        changed = {}

        def update():
            nonlocal changed
            if self.config.densify:
                changed = self.densify(step, branches)
            self.optimizer.step()
            self.after_update(step)

        skipped = self.checked_update(self.optimizer, renders, update)
        if skipped and self.config.densify:
            changed = self.densify_skipped(step)
        extra = evaluated({**extra, **skipped})
        return {"loss": loss.item(), "psnr": psnr(out["image"].detach(), target), **self.size_stats(),
                **extra, **changed}

    @staticmethod
    def checked_update(optimizer: torch.optim.Optimizer, renders: list, update) -> dict:
        """After the backward of ``renders`` [(out, target, weight)]: call ``update()`` unless a
        gradient of ``optimizer``'s is not finite or a captured render lacked intersections, then
        clear the gradients. Returns what was skipped and why ({} when ``update`` ran)."""
        bad = nonfinite_gradient_counts(optimizer)
        # After that synchronisation, asking a captured render whether it was whole waits for nothing.
        incomplete = incomplete_renders(renders)
        skipped = {}
        if bad:
            # Skip the whole update, as mixed-precision training does on overflow: see
            # nonfinite_gradient_counts for why zeroing the bad entries is not enough.
            skipped.update(nonfinite_grads=sum(bad.values()), nonfinite_groups=sorted(bad))
        if incomplete:  # a render that lacked intersections gave the wrong gradients
            skipped["incomplete_renders"] = incomplete
        if not skipped:
            update()
        optimizer.zero_grad(set_to_none=True)
        return skipped

    def after_update(self, step: int) -> None:
        """Hook after step ``step``'s optimizer update (the SecureGS trainer moves the anchor
        features onto the message there)."""

    def extra_losses(self, index: int, renders: list, branches: dict, step: int) -> dict:
        """Hook for further losses: appends (out, target, weight) to ``renders`` for each further render
        whose weighted ``image_loss`` joins the public one's (``image_losses``; or ({"loss": a weighted
        loss already differentiated, "info": {"complete": ...}}, None, 1.0) for renders whose loss was
        taken and differentiated elsewhere), and returns numbers to report, each a value or a function
        that gives it at the end of the step; a hidden render adds its (gaussians, info) to
        ``branches`` under "hidden". Plain training has the public loss only."""
        return {}

    @torch.no_grad()
    def evaluate(self, cameras: list[Camera] | None = None, timing_repeats: int = 3, with_lpips: bool = False,
                 on_render=None) -> dict:
        """PSNR, SSIM (and LPIPS when asked and possible) on held-out views (the test split by
        default), and rendering FPS. ``on_render(cam, image [H, W, 3])`` sees each render (to save it)."""
        cameras = self.scene.test if cameras is None else cameras
        metrics = evaluation.evaluate_views(self.render, cameras, self.device, timing_repeats=timing_repeats,
                                            with_lpips=with_lpips, on_render=on_render)
        return {**metrics, **self.size_stats()}

    # -- checkpoints ----------------------------------------------------------------------------

    def config_sections(self) -> dict:
        """Section name -> config object this trainer runs with (a checkpoint stores them)."""
        return {"train": self.config}

    def checkpoint_state(self) -> dict:
        """Everything a step changes, as tensors and plain numbers (loadable with weights_only)."""
        return {
            "step": self.step_count,
            "train_seconds": self.train_seconds,
            "config": {name: to_dict(section) for name, section in self.config_sections().items()},
            **self.model_state(),
            "optimizer": self.optimizer.state_dict(),
            "strategy": self.strategy_state,
            "generator": self.generator.get_state(),
            "order": list(self._order),
        }

    def save_checkpoint(self, path, passphrase: str | None = None) -> None:
        """Write ``checkpoint_state()`` atomically, owner-only; sealed like a key with ``passphrase``
        (a SecureGS checkpoint holds the private heads, so a sealed run's checkpoints are sealed too)."""
        buffer = io.BytesIO()
        torch.save(self.checkpoint_state(), buffer)
        data = buffer.getvalue()
        write_private(path, seal(data, passphrase) if passphrase is not None else data)

    def load_checkpoint(self, path, passphrase: str | None = None) -> None:
        """Restore a checkpoint written by ``save_checkpoint``. Only tensors and plain numbers are
        read (``weights_only``); a sealed one needs its passphrase. A damaged, foreign or unsafe file
        raises ValueError naming it."""
        try:
            blob = open(path, "rb").read()
        except OSError as e:
            raise ValueError(f"{path}: cannot read the checkpoint ({e.strerror or e})") from None
        if is_sealed(blob):
            blob = unseal(path, blob, passphrase, what="checkpoint")
        try:
            state = torch.load(io.BytesIO(blob), map_location=self.device, weights_only=True)
        except Exception as e:  # torch raises UnpicklingError, RuntimeError, EOFError, zip errors ...
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise ValueError(f"{path}: not a checkpoint this version can read safely ({first[:200]})") from None
        if not isinstance(state, dict) or not {"step", "config", "optimizer", *self.model_state_keys} <= set(state):
            raise ValueError(f"{path}: not a securegs checkpoint of this kind of run (missing entries)")
        self.restore(state, path)

    def restore(self, state: dict, path) -> None:
        self.check_checkpoint(state, path)
        self.restore_model(state)
        self.optimizer.load_state_dict(state["optimizer"])
        self.strategy_state = state["strategy"]
        self.generator.set_state(state["generator"].cpu())  # map_location put it on the run's device
        self._order = list(state["order"])
        self.step_count = int(state["step"])
        self.train_seconds = float(state["train_seconds"])

    def check_checkpoint(self, state: dict, path) -> None:
        """Refuse a checkpoint this trainer cannot continue, before anything of it is loaded (a
        refused resume leaves the trainer as it was). Subclasses add their own checks."""
        self._check_config(state.get("config"), path)

    def _check_config(self, saved: dict | None, path) -> None:
        """Refuse a checkpoint written with other options, naming the first field that differs."""
        mine = self.config_sections()
        if not isinstance(saved, dict) or set(saved) != set(mine):
            raise ValueError(f"{path}: checkpoint was written with other training options (a different kind of "
                             "run); resume with the run's own config")
        for section, value in mine.items():
            try:
                other = from_dict(type(value), saved[section], section)
            except ValueError as e:
                raise ValueError(f"{path}: checkpoint was written with other training options ({e})") from None
            field = first_difference(value, other, section, RESUMABLE_CHANGES)
            if field is not None:
                raise ValueError(f"{path}: checkpoint was written with other training options ({field} differs); "
                                 "resume with the run's own config")


def psnr_label(stats: dict) -> str:
    """What a step's "psnr" (``ViewTrainer.step``) measures: "psnr" (the public render of the
    training view) or, in the SecureGS trainer's finishing steps, "psnr_hidden"."""
    return "psnr_hidden" if stats.get("phase") == "finish" else "psnr"


def evaluated(numbers: dict) -> dict:
    """``numbers`` with each function replaced by its value. Numbers that read the device (a host
    synchronisation each) are taken once the whole step is queued; ``extra_losses`` hands them over
    as functions for that reason."""
    return {key: value() if callable(value) else value for key, value in numbers.items()}


@contextlib.contextmanager
def frozen(*modules: torch.nn.Module):
    """Within the block the parameters of ``modules`` that take gradients take none; afterwards
    they do again."""
    params = [p for module in modules for p in module.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


def incomplete_renders(renders: list) -> int:
    """How many of a step's renders [(out, target, weight)] lacked tile intersections: captured
    renders (``RasterOptions.capture``) whose view needed more than the capacity that their shape had
    (which then grows for the next render; ``rasterize``'s ``info["complete"]``)."""
    infos = [out.get("info", {}) for out, _, _ in renders]  # a decoded image (GS-Hider's) has none
    return sum(not info["complete"]() for info in infos if "complete" in info)


@torch.no_grad()
def nonfinite_gradient_counts(optimizer: torch.optim.Optimizer) -> dict[str, int]:
    """Parameter group name -> number of inf/NaN gradient entries, for the groups that have any
    (empty: every gradient is finite). One host sync: the finite case, every step's, costs one
    fused reduction (the L1 norm of all gradients, which an inf or NaN entry makes non-finite); only
    a non-finite norm, which huge finite entries can also give, counts entry by entry.

    The trainer skips a step with any such entry: no optimizer step, and no densification step
    either (neither its statistics nor, on an update step, growth and pruning, which wait for the
    next update). Both ways of going on can damage the model:
    - Applied, an inf or NaN reaches Adam and becomes NaN in its moments for good: the parameter's
      later updates are NaN however small the learning rate (an anchor would drop out of every view
      and never be pruned).
    - Zeroing just those entries applies the rest of a gradient computed through an overflow, whose
      finite entries may be huge as well; one huge gradient fills Adam's second moment, and the
      entry then barely moves for thousands of steps. Mixed-precision training skips such steps for
      the same reason.
    """
    named = [(group.get("name", f"group {i}"), [p.grad for p in group["params"] if p.grad is not None])
             for i, group in enumerate(optimizer.param_groups)]
    named = [(name, grads) for name, grads in named if grads]
    if not named:
        return {}
    if bool(torch.isfinite(torch.nn.utils.get_total_norm([g for _, grads in named for g in grads], norm_type=1.0))):
        return {}
    totals = torch.stack([sum((~torch.isfinite(g)).sum() for g in grads) for _, grads in named]).tolist()
    return {name: int(n) for (name, _), n in zip(named, totals) if n}
