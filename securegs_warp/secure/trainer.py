"""SecureGS training: the Scaffold-GS trainer plus a private hidden branch per secret.

Per step: the public render of a training view gives ℓ_ori; each secret's private heads decode the
same anchors into hidden Gaussians (positions from its F_o†) rendered from the same camera against
its payload's hidden view (or, for an image payload, from the one chosen view) for λ·ℓ_hid; each
bit payload moves the anchor features onto its bit of its keyed decoder F_b† after every step. One
backward through all renders, then the region-aware strategy looks at every branch's gradients.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import warnings

import numpy as np
import torch

from .. import evaluation
from ..config import BOX_FRAME_DEFAULTS, SecureConfig, TrainConfig, recorded_phase
from ..data import Camera, SceneData
from ..kept import Kept
from ..train.base import evaluated, frozen
from ..train.losses import psnr
from ..train.schedules import exponential_lr
from ..train.trainer import ScaffoldTrainer
from . import hidden_graph
from .crop import Crop, box_crop
from .heads import PrivateHeads, farthest_points
from .keyed_bits import KeyedBitDecoder, new_seed
from .model import SecureModel
from .payload import Payload, build_payload, message_string, parse_secrets, recorded_payload
from .robust import parse_robust, perturb, public_opacity

# The hidden render must beat the best flat image by this much to count as learnt (a collapsed
# branch scores at or below it; a learnt one, tens of dB above on the mug).
HIDDEN_LEARNT_MARGIN_DB = 1.0
# The box frame's box: the hidden object's bounds grown by this fraction of their diagonal.
BOX_MARGIN = 0.05
# With several bit payloads each anchor feature must agree with one bit of every message: the
# projections onto their half-spaces alternate this many times after each step (alternating
# projections onto convex sets approach their intersection; the keys' directions are nearly
# orthogonal, so few rounds are needed).
PROJECTION_ROUNDS = 3
# The finishing phase (SecureConfig.hidden_finish) restarts each private head's learning rate at its
# schedule's value this far into the run and decays it to the schedule's final value: restarted at
# the initial rate, the phase undid part of what the joint run had learnt (docs/results.md, "The
# finishing phase").
FINISH_LR_FROM = 0.5
# The key keeps the mean of the private heads' weights over the finishing phase's steps after this
# fraction of it (stochastic weight averaging): each step trains against another random attack, so
# the last step's weights are one noisy draw around what the phase converged to (docs/results.md,
# "Averaging the finishing phase's weights").
FINISH_AVERAGE_FROM = 0.5


def hidden_seed(seed: int) -> int:
    """The seed of robust training's draws for a run of training seed ``seed``: another stream
    than the public training's (the golden ratio's odd 64-bit multiple, XOR-ed in), still fixed
    by the one seed config.json records."""
    return (seed ^ 0x9E3779B97F4A7C15) & (2**63 - 1)


def secret_suffix(secret: int) -> str:
    """What a metric of secret ``secret`` (0-based) is suffixed with: nothing for the first, _2, _3 ..."""
    return "" if secret == 0 else f"_{secret + 1}"


def warn_of_bits_without_voters(decoder: KeyedBitDecoder, xyz: torch.Tensor, cell_voxels: float) -> None:
    """Warn, with their number, when some bits of ``decoder``'s message have no anchor among those
    at positions xyz [N, 3] (``KeyedBitDecoder.bits_without_voters``): those read 0."""
    vacant = decoder.bits_without_voters(xyz)
    if vacant:
        warnings.warn(f"{vacant} of the message's {decoder.n_bits} bits fall in no occupied cell of the keyed grid "
                      f"({cell_voxels:g} voxels a cell; the {len(xyz)} anchors occupy too few cells): they will read "
                      f"0. A shorter message or a finer grid (--bit-cell) gives every bit voters.", stacklevel=2)


class SecureTrainer(ScaffoldTrainer):
    """Trains a ``SecureModel``: the Scaffold-GS trainer plus each secret's private heads and payload.

    secure: the SecureGS options (payloads, λ, gradient shares, HDGER, density strategy); its
    strategy's schedule is scaled to ``config.iterations``. Attributes beyond the base class:
    ``secure`` (with its robust training, bit margin and finishing phase resolved,
    ``SecureConfig.resolved``), ``payloads`` (each secret's hidden targets, in the order of
    ``model.secrets``), ``robust`` and ``finish_robust`` (the attacks the hidden branch trains
    against in the joint run and in the finishing phase, parsed) and ``finish_steps`` (the
    finishing phase's steps after ``config.iterations``; ``total_steps`` is the run's whole length).

    A resumed run (``restore``) that has not begun its finishing phase takes this ``secure``'s
    length and attacks for it, "auto" resolved as for a new run; ``securegs hide --resume`` keeps
    the recorded ones unless the command names others. To keep them here, pass the values of
    ``config.recorded_phase`` of the run's recorded ``secure`` section.
    """

    def __init__(self, scene: SceneData, config: TrainConfig, secure: SecureConfig, device="cpu"):
        # Built before the model, so that a payload the scene cannot carry fails before training.
        self.payloads = [build_payload(spec, scene, torch.device(device)) for spec in parse_secrets(secure.payload)]
        if not secure.hdger and sum(p.has_images for p in self.payloads) > 1:
            raise ValueError("w/o HDGER the anchors hold one set of explicit hidden offsets: it trains one hidden "
                             "image payload, not several")
        for p in self.payloads:
            if secure.hidden_weight is not None:
                p.weight = float(secure.hidden_weight)
        # Each bit decoder's seed is secret like its message (not from the training seed, which
        # config.json records), drawn apart for every secret; a checkpoint keeps them.
        self.bit_seeds = [new_seed() if p.bits is not None else None for p in self.payloads]
        kinds = [p.spec.kind for p in self.payloads]
        strategy = dataclasses.replace(secure.strategy.scaled_to(config.iterations), mode=secure.strategy_mode(kinds))
        self.secure = secure = secure.resolved(kinds, strategy.mode)
        self.robust = parse_robust(secure.robust, "robust") if secure.robust else []
        self.finish_robust = parse_robust(secure.finish_robust, "finish_robust") if secure.finish_robust else []
        strategy.use_bbox = (all(p.spec.kind != "scene" for p in self.payloads)
                             and any(p.spec.kind in ("object", "image") for p in self.payloads))
        self.strategy = strategy  # the private heads, built with the model, read its mode
        # The last step before the bit projection begins (SecureConfig.bits_from): growth ends at
        # update_until, and a run that does not densify never grows.
        self.bits_start = strategy.update_until if secure.bits_from == "growth-end" and config.densify else 0
        # Each bit decoder's BitProjection of the anchor positions after_update last refitted to.
        self._projections = Kept()
        # Each secret's crops (view index -> Crop or None), kept while its box is unchanged.
        self._crops = [Kept() for _ in self.payloads]
        # Bits alone have no hidden render to finish.
        self.finish_steps = round(secure.hidden_finish * config.iterations) \
            if any(p.has_images for p in self.payloads) else 0
        # Made when the phase begins (or a checkpoint of it is restored): it holds the private
        # heads alone, so nothing else can move in the phase.
        self._finish_optimizer = None
        # Each phase's hidden branch replayed from CUDA graphs (secure.hidden_graph): phase ->
        # HiddenGraph, made at its first hidden step where it can be (None: op by op).
        self._graphs = {}
        # The running mean of the private heads' weights late in the phase (_average_private):
        # {"count": steps folded in, "weights": [tensor per parameter of the finishing optimizer]}.
        self._finish_average = None
        # Robust training's draws come from a stream of their own, so that they leave the public
        # training's (the views' order, the density strategy's draws) as in plain Scaffold-GS of the
        # same seed: with no hidden gradient on the release (the codes) the release is then the plain
        # model's, whatever it hides.
        self.hidden_generator = torch.Generator().manual_seed(hidden_seed(config.seed))
        super().__init__(scene, config, device=device, strategy=strategy)

    @property
    def payload(self) -> Payload:
        """The payload of a run with one secret."""
        if len(self.payloads) != 1:
            raise ValueError(f"this run hides {len(self.payloads)} secrets: pick one of payloads by index")
        return self.payloads[0]

    def _make_model(self, anchors, heads) -> SecureModel:
        bit_cell = self.secure.bit_cell_voxels * anchors.voxel_size
        secrets = [self._make_private(heads, p, seed, bit_cell).to(anchors.xyz.device)
                   for p, seed in zip(self.payloads, self.bit_seeds)]
        for private in secrets:
            private.fix_serving(anchors.xyz)
        if not self.secure.hdger and any(p.has_images for p in self.payloads):
            anchors.add_hidden_offsets()
        return SecureModel(anchors, heads, secrets)

    def _make_private(self, heads, payload: Payload, bit_seed: str | None, bit_cell: float) -> PrivateHeads:
        options = self.secure.private_options(payload.spec.kind, self.strategy.mode)
        k_hidden = options.get("n_hidden") or heads.n_offsets
        if self.strategy.reads_hidden and k_hidden != heads.n_offsets:
            raise ValueError(f"the {self.strategy.mode} mode keeps the hidden Gaussians' statistics in the public "
                             f"offset slots: it needs hidden_offsets = k ({heads.n_offsets}), got {k_hidden} (the "
                             f"box frame's default is {BOX_FRAME_DEFAULTS['n_hidden']}; pass --hidden-offsets)")
        private = PrivateHeads(heads, message=message_string(payload.bits), bit_seed=bit_seed,
                               bit_cell=None if payload.bits is None else bit_cell,
                               offsets=self.secure.hdger, hidden=payload.has_images, **options)
        if options["frame"] == "box" and private.decoder is not None:
            bounds = getattr(self.scene, "hidden_bbox", None)
            if bounds is None or payload.spec.kind != "object":
                raise ValueError("hidden_frame 'box' decodes a hidden object inside its bounds: it needs an object "
                                 "payload on a scene that knows the object's box")
            lo, hi = np.asarray(bounds, dtype=np.float32)
            margin = BOX_MARGIN * float(np.linalg.norm(hi - lo))  # room for splats that reach past the surface
            private.set_box(lo - margin, hi + margin)
            if self.secure.hidden_start == "surface":
                points = self.scene.hidden_points
                if points is None:
                    raise ValueError("hidden_start 'surface' starts the hidden Gaussians on the object's surface: it "
                                     "needs a scene that knows points on it (or hidden_start 'centre')")
                private.start_at(farthest_points(torch.as_tensor(points, dtype=torch.float32), private.n_offsets))
        return private

    def head_groups(self) -> dict:
        groups = dict(self.model.heads.named_mlps())
        for i, private in enumerate(self.model.secrets):
            prefix = "private_" if i == 0 else f"private{i + 1}_"  # the schedules strip it (_mlp_schedule)
            groups.update({prefix + name: module for name, module in private.named_mlps().items()})
        return groups

    def config_sections(self) -> dict:
        """As config.json records them: a literal message by its length (``bits:0b1011`` ->
        ``bits:4``), so that a run resumes with either; ``restore`` compares a literal given on
        resume with the checkpoint's message."""
        return {**super().config_sections(),
                "secure": dataclasses.replace(self.secure, payload=recorded_payload(self.secure.payload))}

    # -- the finishing phase --------------------------------------------------------------------

    @property
    def total_steps(self) -> int:
        """The joint run's iterations, then the finishing phase's steps."""
        return self.config.iterations + self.finish_steps

    def train_step(self, step: int, index: int) -> dict:
        if step <= self.config.iterations or not self.finish_steps:
            return super().train_step(step, index)
        return self._finish_step(step, index)

    def _finish_step(self, step: int, index: int) -> dict:
        """A step of the finishing phase (``SecureConfig.hidden_finish``): each secret's hidden loss
        on training view ``index`` (against ``finish_robust``'s attacks) trains its private heads alone.
        The release (anchors and public heads, and so the cover, the anchor cloud and the bits)
        stays as the joint run left it (without HDGER that includes its explicit hidden offsets: only
        the private MLPs train). On CUDA the step is replayed from graphs where
        ``hidden_graph.replayable`` allows, after a few steps op by op. Reports "psnr" as the first
        hidden render's PSNR and "phase": "finish"."""
        optimizer = self._finishing_optimizer()
        # From FINISH_LR_FROM of the schedule at the phase's first step to its end at the last.
        progress = FINISH_LR_FROM + (1.0 - FINISH_LR_FROM) * (step - self.config.iterations) / self.finish_steps
        for group in optimizer.param_groups:
            lr = exponential_lr(*self._mlp_schedule(group["name"]), 1, progress)
            if torch.is_tensor(group["lr"]):  # a replayed update reads it where it is
                group["lr"].fill_(lr)
            else:
                group["lr"] = lr
        joint = self._graphs.pop(hidden_graph.JOINT, None)
        if joint is not None:  # its rasterizer entries are the phase's to take
            joint.close()
        graph = self._hidden_graph(hidden_graph.FINISH)
        if graph is not None:
            loss, extra, entry = graph.run(step, index)
            extra = evaluated({**extra, **self.checked_update(optimizer, [entry], lambda: graph.update(optimizer))})
        else:
            loss, extra = self._eager_finish_step(step, index, optimizer)
        self._average_private(step)
        first = next(value for key, value in extra.items() if key.startswith("psnr_hidden"))
        return {"loss": loss.item(), "psnr": first, "phase": "finish", **self.size_stats(), **extra}

    def _hidden_graph(self, phase: str) -> hidden_graph.HiddenGraph | None:
        """The hidden branch of ``phase`` replayed from CUDA graphs, where ``hidden_graph.replayable``."""
        if phase not in self._graphs:
            self._graphs[phase] = hidden_graph.HiddenGraph(self, phase) if hidden_graph.replayable(self, phase) else None
        return self._graphs[phase]

    def _eager_finish_step(self, step: int, index: int, optimizer) -> tuple[torch.Tensor, dict]:
        """A finishing step op by op: (its loss, the numbers it reports)."""
        def public():
            with torch.no_grad():
                return self.render(self.scene.train[index], camera_index=index)["gaussians"]

        renders = []
        # The release's parameters take no gradient for the step only: after the phase the model is
        # an ordinary one again (an attack may fine-tune it).
        with frozen(self.model.anchors, self.model.heads):
            extra, _ = self._hidden_losses(index, renders, step, self._attacked_anchors(public, self.finish_robust),
                                           None, 1.0)
            loss = self.image_losses(renders)
            loss.backward()
        return loss, evaluated({**extra, **self.checked_update(optimizer, renders, optimizer.step)})

    @torch.no_grad()
    def _average_private(self, step: int) -> None:
        """After phase step ``step``: fold the private heads' weights into their running mean once
        past FINISH_AVERAGE_FROM of the phase; at the phase's last step the heads take the mean."""
        if step <= self.config.iterations + FINISH_AVERAGE_FROM * self.finish_steps:
            return
        params = [p for group in self._finishing_optimizer().param_groups for p in group["params"]]
        if self._finish_average is None:
            self._finish_average = {"count": 0, "weights": [torch.zeros_like(p) for p in params]}
        self._finish_average["count"] += 1
        torch._foreach_lerp_(self._finish_average["weights"], params, 1.0 / self._finish_average["count"])
        if step == self.total_steps:
            torch._foreach_copy_(params, self._finish_average["weights"])

    def _finishing_optimizer(self) -> torch.optim.Adam:
        """Adam over the private heads alone."""
        if self._finish_optimizer is None:
            private = {name: module for name, module in self.head_groups().items() if name.startswith("private")}
            self._finish_optimizer = self.adam([{"params": list(module.parameters()), "lr": 0.0, "name": name}
                                                for name, module in private.items()])
        return self._finish_optimizer

    # -- rendering ------------------------------------------------------------------------------

    def render_hidden(self, cam: Camera, camera_index: int | None = None, step: int | None = None,
                      anchors=None, secret: int = 0, visible: torch.Tensor | None = None,
                      compact: bool = True, replay_raster: bool = False) -> dict:
        """Secret ``secret``'s hidden render of a view, with the gradient shares of training
        ``step`` (default: the step counter); ``anchors``: robust training's perturbed anchors;
        ``visible``, ``compact``: see ``SecureModel.render_hidden``; ``replay_raster``: rasterize with
        ``RasterOptions.capture`` (for renders of one row count and image size, step after step)."""
        options = dataclasses.replace(self.config.raster, capture=True) if replay_raster else self.config.raster
        return self.model.render_hidden(cam, options, background=self.payloads[secret].background,
                                        camera_index=camera_index, feature_grad=self.current_feature_grad(step, secret),
                                        scaling_grad=self.gradient_shares(secret)[1], anchors=anchors, secret=secret,
                                        visible=visible, capture=self.secure.hidden_capture, compact=compact)

    def gradient_shares(self, secret: int = 0) -> tuple[float, float]:
        """Secret ``secret``'s (feature, scaling) shares of its hidden loss's gradient on the release
        (``SecureConfig.gradient_shares``)."""
        return self.secure.gradient_shares(self.payloads[secret].spec.kind, self.strategy.mode)

    def current_feature_grad(self, step: int | None = None, secret: int = 0) -> float:
        """Secret ``secret``'s feature share until feature_grad_until of the run, 0 after it."""
        step = self.step_count if step is None else step
        if step > self.secure.feature_grad_until * self.config.iterations:
            return 0.0
        return self.gradient_shares(secret)[0]

    def extra_losses(self, index: int, renders: list, branches: dict, step: int) -> dict:
        stride = self.secure.hidden_stride
        if step % stride:
            return {}  # a plain step between hidden ones (SecureConfig.hidden_stride)
        graph = self._hidden_graph(hidden_graph.JOINT)
        if graph is not None:
            _, extra, entry = graph.run(step, index)
            graph.scatter(self.model.anchors)
            renders.append(entry)
            # No branches["hidden"]: the strategy of the cover mode reads no hidden Gaussian.
            return extra
        public = branches["public"][0]
        anchors = self._attacked_anchors(lambda: public, self.robust)
        # Same anchors as the public render: its visibility test holds for the same view.
        visible = public["visible_mask"] if anchors is None else None
        extra, hidden = self._hidden_losses(index, renders, step, anchors, visible, stride)
        if hidden:
            branches["hidden"] = hidden
        return extra

    def _attacked_anchors(self, public, attacks: list):
        """Robust training: this step's copy of the anchors attacked by ``attacks`` (``self.robust``
        in the joint run, ``self.finish_robust`` in the finishing phase) for the hidden renders (None
        without attacks; the bits are projected into every anchor after the update, see
        after_update). ``public()``: the Gaussians of the step's public render, read only by
        prune-opacity (its scatter of the public opacities costs a host synchronisation)."""
        if not attacks:
            return None
        opacity = public_opacity(public(), self.model.anchors) \
            if any(a.name == "prune-opacity" for a in attacks) else None
        return perturb(self.model.anchors, attacks, self.hidden_generator, opacity)

    def _hidden_losses(self, index: int, renders: list, step: int, anchors, visible, scale: float,
                       views: dict | None = None):
        """Appends each secret's hidden render of training view ``index`` (or of its image's view)
        to ``renders``, weighted λ·``scale``. anchors: the attacked copy or None, or secret -> the
        rows it decodes (a replayed step's serving rows, ``secure.hidden_graph``); visible: the
        public render's visibility of view ``index`` for those anchors, or None; views: secret ->
        (camera, target [H, W, 3]) that stand for that view (a replayed step's fixed buffers).
        Returns (the numbers to report, [(gaussians, info, weight)] of each hidden render for the
        strategy)."""
        extra, hidden = {}, []
        for secret, p in enumerate(self.payloads):
            view = index if p.views is not None else p.image_view
            if view is None:
                continue
            crop = self._hidden_crop(secret, view)
            camera = self.scene.train[view] if crop is None else crop.camera
            target = p.views[view] if p.views is not None else p.image
            if views is not None:
                camera, target = views[secret]
            # The Gaussians that fail the opacity test stay in the render at opacity 0 (a host
            # synchronisation fewer) unless the strategy reads the hidden Gaussians row by row.
            compact = self.strategy.reads_hidden
            decoded = anchors.get(secret) if isinstance(anchors, dict) else anchors
            out = self.render_hidden(camera, camera_index=view, step=step, anchors=decoded, secret=secret,
                                     visible=visible if view == index else None, compact=compact,
                                     replay_raster=self.replays_hidden_raster(secret, compact, crop))
            share = 1.0
            if crop is not None:
                target, share = target[crop.rows, crop.cols], crop.share
                out["pixel_share"] = share
            renders.append((out, target, p.weight * scale))
            hidden.append((out["gaussians"], out["info"], p.weight * scale))
            extra["psnr_hidden" + secret_suffix(secret)] = functools.partial(view_psnr, out["image"].detach(),
                                                                             target, share)
        return extra, hidden

    def replays_hidden_raster(self, secret: int, compact: bool, crop: Crop | None) -> bool:
        """Whether a training step's hidden render of secret ``secret`` rasterizes with
        ``RasterOptions.capture``: on CUDA with ``hidden_capture``, for an uncompacted render of
        fixed rows (``SecureModel.fixed_rows``) at whole views, one shape step after step until the
        serving radius is refit (a step whose view overflows the capacity is skipped, see
        ``ViewTrainer.step``)."""
        return (self.secure.hidden_capture and self.device.type == "cuda" and not compact and crop is None
                and self.model.fixed_rows(secret))

    def crops_hidden(self, secret: int) -> bool:
        """Whether secret ``secret``'s hidden renders are cropped to its box (``_hidden_crop``)."""
        return self.secure.hidden_crop and self.model.secrets[secret].frame == "box" and self.strategy.mode == "cover"

    def _hidden_crop(self, secret: int, view: int) -> Crop | None:
        """The part of training view ``view`` that secret ``secret``'s hidden render is trained on
        (``SecureConfig.hidden_crop``: box-frame keys in the cover mode), or None: the whole view.
        Other modes grow anchors from the hidden render's screen-space gradients, which are scaled by
        the image's size: they render whole views."""
        if not self.crops_hidden(secret):
            return None
        private = self.model.secrets[secret]
        # One host read of the box while it is unchanged, then each view's crop from it.
        box, crops = self._crops[secret].get((private.box,), lambda: (private.box.detach().cpu().numpy(), {}))
        if view not in crops:
            crops[view] = box_crop(self.scene.train[view], box, self.config.raster.tile_size)
        return crops[view]

    @torch.no_grad()
    def after_update(self, step: int) -> None:
        """Refit each box-frame key's serving radius to the anchors densification left
        (``PrivateHeads.fix_serving``), then, from the step ``bits_from`` names on, move each anchor
        feature the least distance that makes its vote agree with its bit of every message by
        bit_margin (a projection, not a loss: a loss's gradient goes through Adam, which turns it
        into steps of the learning rate on every coordinate and cost the cover 0.3-1.2 dB; the
        projection moves a feature along one direction, only as far as needed)."""
        anchors = self.model.anchors
        # Anchor positions train at learning rate 0 (as Scaffold-GS's), so they change only when
        # densification (or a restore) replaces the tensor: the serving radii and each anchor's bit
        # are refitted then, or after a new message, not every step (each refit costs a sort and a
        # device-to-host read).
        def refit():
            for private in self.model.secrets:
                private.fix_serving(anchors.xyz)
            return [private.bits.projection(anchors.xyz) for private in self.model.secrets if private.bits is not None]

        projections = self._projections.get((anchors.xyz, *(private.bits for private in self.model.secrets)), refit)
        decoders = [private.bits for private in self.model.secrets if private.bits is not None]
        if not decoders or step <= self.bits_start:
            return
        if step == self.bits_start + 1:
            for decoder in decoders:
                warn_of_bits_without_voters(decoder, anchors.xyz, self.secure.bit_cell_voxels)
        feat = anchors.feat.detach()
        for _ in range(PROJECTION_ROUNDS if len(decoders) > 1 else 1):
            for decoder, projection in zip(decoders, projections):
                feat = decoder.project(feat, anchors.xyz, self.secure.bit_margin, projection)
        anchors.feat.copy_(feat)

    # -- evaluation -----------------------------------------------------------------------------

    @torch.no_grad()
    def evaluate_hidden(self, secret: int = 0) -> dict:
        """Secret ``secret``'s hidden metrics: PSNR/SSIM on held-out views (object, scene) or at the
        image's view, and bit accuracy."""
        p, out = self.payloads[secret], {}
        def render(cam, index=None):
            return self.render_hidden(cam, index, secret=secret)["image"].clamp(0, 1)

        if p.views is not None and p.test_views is not None:
            pairs = [(render(c), t) for c, t in zip(self.scene.test, p.test_views)]
        elif p.views is not None:
            pairs = [(render(c, i), t) for i, (c, t) in enumerate(zip(self.scene.train, p.views))]
        elif p.image is not None:
            pairs = [(render(self.scene.train[p.image_view], p.image_view), p.image)]
        else:
            pairs = []
        if pairs:
            metrics = evaluation.image_metrics(pairs, self.device, with_lpips=False)
            out["psnr_hidden"], out["ssim_hidden"] = metrics["psnr"], metrics["ssim"]
            # What the best flat image (each target's mean colour) scores. A hidden branch that
            # never learnt (too small a gradient share, too short a run) renders the bare
            # background or noise, no better than that: no failure to the metrics above, but one to
            # the person who hid something. None where a target is itself flat.
            flat = flat_image_psnr([target for _, target in pairs])
            if np.isfinite(flat):
                out["psnr_hidden_flat"] = flat
                out["hidden_learnt"] = out["psnr_hidden"] > flat + HIDDEN_LEARNT_MARGIN_DB
            else:
                out["psnr_hidden_flat"] = out["hidden_learnt"] = None
            cams = self.scene.evaluation_views
            out["fps_hidden"] = evaluation.render_fps(lambda cam: self.render_hidden(cam, secret=secret), cams,
                                                      self.device)
        if p.bits is not None:
            out["bit_accuracy"] = self.bit_accuracy(secret=secret)
            # One bit per occupied cell of the keyed grid: a message longer than a model's cells can
            # carry reads 0 where no anchor votes.
            out["bits_without_voters"] = self.model.secrets[secret].bits.bits_without_voters(self.model.anchors.xyz)
        return out

    @torch.no_grad()
    def bit_accuracy(self, anchors=None, secret: int = 0) -> float | None:
        """The fraction of secret ``secret``'s message its key's bit decoder reads from ``anchors``
        (an ``AnchorModel``): this container's by default, or another model's (on a model trained
        without this key it is a fair coin per bit: 0.5 on average). None without a bit payload."""
        bits = self.payloads[secret].bits
        if bits is None:
            return None
        decoded = self.model.decode_bits(anchors, secret=secret)
        return float((decoded == bits.long()).float().mean())

    # -- checkpoints ----------------------------------------------------------------------------

    def checkpoint_state(self) -> dict:
        # The messages and seeds were drawn at random when the run began: resuming keeps them.
        return {**super().checkpoint_state(), "hidden_generator": self.hidden_generator.get_state(),
                "private": [private.state_dict() for private in self.model.secrets],
                "messages": [None if p.bits is None else p.bits.detach().cpu() for p in self.payloads],
                "bit_seeds": list(self.bit_seeds),
                "finish_optimizer": None if self._finish_optimizer is None else self._finish_optimizer.state_dict(),
                "finish_average": self._finish_average}

    def _check_phase(self, state: dict, path) -> None:
        """Refuse a checkpoint inside its finishing phase whose phase length or attacks differ from
        this run's: the phase's learning rates, Adam state and running mean belong to them, so once
        it has begun they stay (config.RESUMABLE_CHANGES lets a run change them before). A
        checkpoint without a readable config is left to the base class's check."""
        config = state.get("config")
        into = int(state.get("step", 0)) - self.config.iterations
        if into <= 0 or not isinstance(config, dict) or not isinstance(config.get("secure"), dict):
            return
        for name, saved in recorded_phase(config["secure"]).items():
            mine = getattr(self.secure, name)
            if saved != mine:
                raise ValueError(f"{path}: the run is {into} steps into a finishing phase with {name} {saved!r} "
                                 f"(--{name.replace('_', '-')}); resume it with that value, not {mine!r}")

    def check_checkpoint(self, state: dict, path) -> None:
        super().check_checkpoint(state, path)
        self._check_phase(state, path)
        self._check_private(state, path)

    def restore(self, state: dict, path) -> None:
        super().restore(state, path)
        if "hidden_generator" in state:  # else written when the draws shared the public generator
            self.hidden_generator.set_state(state["hidden_generator"].cpu())
        self.bit_seeds = list(state["bit_seeds"])
        for private, p, saved, message, seed in zip(self.model.secrets, self.payloads, state["private"],
                                                    state["messages"], self.bit_seeds):
            private.load_state_dict(saved)
            if p.bits is not None:
                p.bits = message.to(self.device)
                private.set_message(message_string(p.bits), seed, private.bits.cell)
                private.to(self.device)
        for graph in filter(None, self._graphs.values()):
            graph.close()
        self._finish_optimizer, self._graphs = None, {}
        if state.get("finish_optimizer") is not None:
            optimizer = self._finishing_optimizer()
            optimizer.load_state_dict(state["finish_optimizer"])
            if self.device.type != "cuda":  # written by a replayed phase on CUDA (hidden_graph)
                for group in optimizer.param_groups:
                    group["capturable"], group["lr"] = False, float(group["lr"])
        # None: written before the averaging window (or before the averaging existed: it restarts here).
        average = state.get("finish_average")
        self._finish_average = None if average is None else \
            {"count": average["count"], "weights": [w.to(self.device) for w in average["weights"]]}

    def _check_config(self, saved: dict | None, path) -> None:
        # Checkpoints written before ``config_sections`` recorded a literal message by its length hold
        # the literal: compared as recorded, they resume as before.
        secure = saved.get("secure") if isinstance(saved, dict) else None
        if isinstance(secure, dict) and isinstance(secure.get("payload"), str):
            try:
                saved = {**saved, "secure": {**secure, "payload": recorded_payload(secure["payload"])}}
            except ValueError:
                pass  # not a payload this version reads: the comparison names the field
        super()._check_config(saved, path)

    def _check_private(self, state: dict, path) -> None:
        """Refuse a checkpoint whose secrets this run cannot take: another number of them, or private
        heads of other tensors or shapes (an earlier version, other private-head options)."""
        if any(not isinstance(state.get(name), list) or len(state[name]) != len(self.payloads)
               for name in ("private", "bit_seeds", "messages")):
            raise ValueError(f"{path}: the checkpoint holds another number of secrets (or was written by an earlier "
                             "securegs-warp); start the run again")
        for i, (payload, message) in enumerate(zip(self.payloads, state["messages"])):
            spec = payload.spec
            if spec.bit_string is not None and message_string(message) != spec.bit_string:
                raise ValueError(f"{path}: secret {i + 1} of the run hides another message than the one given now; "
                                 f"resume with bits:{spec.bits} (the checkpoint keeps its message) or the same one")
        for private, saved in zip(self.model.secrets, state["private"]):
            mine = private.state_dict()
            if set(saved) != set(mine):
                raise ValueError(f"{path}: the checkpoint's private heads hold other tensors than this version's "
                                 f"({', '.join(sorted(set(saved) ^ set(mine)))}; written by an "
                                 "earlier securegs-warp); start the run again")
            differing = next((name for name, t in mine.items() if saved[name].shape != t.shape), None)
            if differing is not None:
                raise ValueError(f"{path}: the checkpoint's private heads have other shapes than this run's "
                                 f"({differing}: {tuple(saved[differing].shape)} against "
                                 f"{tuple(mine[differing].shape)}); it was written with other "
                                 "private-head options (or defaults: --hidden-encoding was 0 before it defaulted to "
                                 "6): resume with those")


def view_psnr(image: torch.Tensor, target: torch.Tensor, share: float) -> float:
    """PSNR in dB over a whole view of a render [h, w, 3] of part of it against the same part of
    the target, the rest of the view (1 − ``share`` of its pixels) matching exactly."""
    return psnr(image, target) - 10.0 * math.log10(share)


def flat_image_psnr(targets: list[torch.Tensor]) -> float:
    """The mean PSNR of the best flat images (each target [H, W, 3]'s mean colour) against those
    targets: what a render that holds nothing of them scores at best."""
    return float(np.mean([psnr(t.mean(dim=(0, 1)).expand_as(t), t) for t in targets]))
