"""The config tree: every option of a run, each with one name and one home.

    RunConfig
    ├── scene: SceneSpec            what to train on (a built-in scene or a data folder)
    ├── train: TrainConfig          training: which model (Scaffold-GS or plain 3DGS), its options
    │   ├── heads: HeadsConfig      which head inputs exist (feature bank, appearance, distances)
    │   ├── gaussians: GaussiansConfig   plain 3DGS: SH degree and learning rates
    │   └── raster: RasterOptions   the rasterizer's options (tile size, antialiasing, ...)
    └── secure: SecureConfig | None SecureGS: payload, λ, gradient shares, HDGER
        └── strategy: RegionAwareStrategy   density optimisation (mode, r_down, ...)

    StegaNeRFConfig                 the 3DGS + StegaNeRF baseline's fine-tuning (baselines.steganerf;
                                    run by scripts/compare_methods.py, not a run folder's section)

The CLI flags, ``config.json``, checkpoints, key metadata and the scripts' variants all go through
:func:`to_dict` / :func:`from_dict` and :func:`apply_overrides`, by field name. A field that is off
builds nothing: the heads get an input only when its flag is set, and each raster flag selects its
own compiled kernels, so a scene pays only for the effects it asks for.
"""
from __future__ import annotations

import dataclasses
import math
import typing
from pathlib import Path

from .data import load_scene, reads_as_folder
from .rasterizer import RasterOptions
from .strategies import RegionAwareStrategy


@dataclasses.dataclass(frozen=True)
class HeadsConfig:
    """The shapes and optional inputs of Scaffold-GS's MLP heads (``ScaffoldHeads``).

    feat_dim: d, anchor feature width and MLP hidden width. n_offsets: k, neural Gaussians per anchor.
    feature_bank: blend the feature at three resolutions with view-dependent weights.
    appearance_dim: width of a per-training-camera appearance code fed to the colour MLP (0: none).
    opacity_dist, cov_dist, color_dist: also feed the anchor-camera distance to that MLP.
    """

    feat_dim: int = 32
    n_offsets: int = 10
    feature_bank: bool = False
    appearance_dim: int = 0
    opacity_dist: bool = False
    cov_dist: bool = False
    color_dist: bool = False

    def __post_init__(self):
        if self.feat_dim < 1 or self.n_offsets < 1:
            raise ValueError(f"feat_dim and n_offsets must be >= 1, got {self.feat_dim}, {self.n_offsets}")
        if self.appearance_dim < 0:
            raise ValueError(f"appearance_dim must be >= 0, got {self.appearance_dim}")


MODELS = ("scaffold", "3dgs")
"""What ``securegs train`` can train: Scaffold-GS (anchors + MLPs) or plain 3DGS (explicit Gaussians)."""


@dataclasses.dataclass(frozen=True)
class GaussiansConfig:
    """Plain 3DGS (``TrainConfig.model == "3dgs"``); defaults are 3DGS's for its 30k-step runs.

    sh_degree: the largest spherical-harmonic degree of the colours (0..3). sh_interval: steps per
    degree as 3DGS raises it from 0 (1000 of 30k; scaled to the run's length like the
    densification schedule). Learning rates: means_lr an (initial, final) exponential schedule
    times the scene's camera extent; features_rest at sh_lr / 20, as 3DGS.
    """

    sh_degree: int = 3
    sh_interval: int = 1000
    means_lr: tuple = (0.00016, 0.0000016)
    sh_lr: float = 0.0025
    opacity_lr: float = 0.05
    scale_lr: float = 0.005
    quat_lr: float = 0.001

    def __post_init__(self):
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if self.sh_interval < 1:
            raise ValueError(f"sh_interval must be >= 1, got {self.sh_interval}")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training; defaults are Scaffold-GS's (learning rates for its 30k-step runs), and 3DGS's in
    ``gaussians`` when ``model`` is "3dgs" (the Scaffold-GS fields other than the shared
    iterations, seed, raster, ssim_weight and densify are then unused).

    Learning-rate pairs are (initial, final) of an exponential schedule over the run.
    """

    iterations: int = 30_000
    model: str = "scaffold"
    gaussians: GaussiansConfig = dataclasses.field(default_factory=GaussiansConfig)
    seed: int = 0
    voxel_size: float = 0.0  # <= 0: from the sparse points' nearest-neighbour distances
    heads: HeadsConfig = dataclasses.field(default_factory=HeadsConfig)
    raster: RasterOptions = dataclasses.field(default_factory=RasterOptions)
    ssim_weight: float = 0.2
    volume_weight: float = 0.01
    feature_lr: float = 0.0075
    scaling_lr: float = 0.007
    offset_lr: tuple = (0.01, 0.0001)  # times the scene's camera extent
    mlp_opacity_lr: tuple = (0.002, 0.00002)
    mlp_cov_lr: tuple = (0.004, 0.004)
    mlp_color_lr: tuple = (0.008, 0.00005)
    mlp_featurebank_lr: tuple = (0.01, 0.00001)
    appearance_lr: tuple = (0.05, 0.0005)
    mlp_offset_lr: tuple = (0.004, 0.0004)  # SecureGS's private offset predictor F_o† (no paper value)
    latent_lr: tuple = (0.0075, 0.00075)  # SecureGS's private latent grid (starts at feature_lr; no paper value)
    # SecureGS's private codes, the key's counterpart of the public features. None: feature_lr, held as
    # Scaffold-GS holds the features' rate (on the latent grid's decaying schedule the hidden object
    # came out lower: docs/results.md, "The codes' learning rate").
    code_lr: tuple | None = None
    densify: bool = True

    def __post_init__(self):
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        check_seed(self.seed)
        # exponential_lr interpolates log-linearly: a pair needs two positive rates, or two zeros (frozen).
        for field in dataclasses.fields(self):
            if field.name.endswith("_lr"):
                rates = getattr(self, field.name)
                if rates is None:  # derived from another rate (code_lr)
                    continue
                pair = tuple(rates) if isinstance(rates, (tuple, list)) else (rates,)
                if not (all(r > 0 for r in pair) or all(r == 0 for r in pair)):
                    raise ValueError(f"{field.name} must be positive (or all 0: frozen), got {rates}")
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {', '.join(MODELS)}, got {self.model!r}")


def check_seed(seed: int, name: str = "seed") -> None:
    """Refuse a seed that torch's generators cannot take (a signed 64-bit integer) by its name."""
    if not -2**63 <= seed < 2**63:
        raise ValueError(f"{name} must fit a signed 64-bit integer, got {seed}")


@dataclasses.dataclass(frozen=True)
class StegaNeRFConfig:
    """StegaNeRF (Li et al., CVPR 2023) on a trained plain 3DGS scene: fine-tune the scene so that a
    U-Net decoder recovers a hidden image from its render at any view. Defaults follow the authors'
    code (chenxinli001/StegaNeRF, opt_stega.py) where it states them; the rest is marked.

    iterations: fine-tuning steps (one training view each). rgb_target: what the fine-tuned render
    is held to, "init" (the scene's render before fine-tuning, the authors' ``mse_cp init``) or
    "gt" (the training images). tune: "color" (only the SH colours move, the authors' fixed-geometry
    setting), "dc" (only the degree-0 SH colour, so that the signal cannot be view-dependent
    colour fitted to each training view apart; not the authors', whose Plenoxels grid has SH too) or
    "all" (every Gaussian attribute; the 3DGS analogue of also training density).
    rgb_weight, hidden_weight, clean_weight, classifier_weight: the loss weights of the render's MSE,
    the decoder's MSE to the hidden image on fine-tuned renders, its MSE to black on the original
    renders, and the classifier's BCE (the authors' w_rgb 1, w_wm 0.5 and w_wm_ctr 0.5 or 1, w_dis
    0.01). gradient_masking: scale each SH coefficient's gradient by (e_min / e)^masking_power, e
    the mean magnitude of that coefficient over the scene, so the coefficients that carry most of
    the appearance move least (the authors' adaptive gradient masking; their power is a flag,
    n_power_softw, default unknown here: 1). color_lr: Adam's learning rate for the SH
    coefficients (3DGS's; the paper's grid optimiser has no counterpart). decoder_lr,
    classifier_lr: the U-Net's and the classifier's Adam learning rates at the start, decayed
    exponentially to a tenth by the last step (the authors' lr_unet 1e-3 -> 1e-4, lr_class
    1e-4 -> 1e-5). decoder_width: the U-Net's and classifier's first-level width (the authors'
    VGG16 has 64; 16 trains on a CPU). decoder_levels, decoder_size: the U-Net's resolutions and
    the square size it reads the render at (the authors' VGG16 U-Net: 5 and wm_resize 128). The
    size must be fixed and the bottleneck must see the whole picture: a 3-level U-Net at the
    view's own size (decoder_levels 3, decoder_size 0) learns only the hidden image's mean colour
    (docs/results.md, "StegaNeRF: what it needs to learn"). decoder_antialias: shrink the render to
    decoder_size² by averaging every pixel under each output pixel (torch's antialiased bilinear)
    rather than bilinear sampling, which at 1080p reads one pixel in 63, so that only a
    signal placed on the sampled pixels of each training view reaches the decoder (the authors'
    U-Net samples too, nearest-neighbour: off by default).
    """

    iterations: int = 600
    rgb_target: str = "init"
    tune: str = "color"
    rgb_weight: float = 1.0
    hidden_weight: float = 1.0
    clean_weight: float = 1.0
    classifier_weight: float = 0.01
    gradient_masking: bool = True
    masking_power: float = 1.0
    color_lr: float = 0.0025
    decoder_lr: float = 0.001
    decoder_width: int = 16
    decoder_levels: int = 5
    decoder_size: int = 128
    decoder_antialias: bool = False
    classifier_lr: float = 0.0001

    def __post_init__(self):
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.rgb_target not in ("init", "gt"):
            raise ValueError(f"rgb_target must be 'init' or 'gt', got {self.rgb_target!r}")
        if self.tune not in ("color", "dc", "all"):
            raise ValueError(f"tune must be 'color', 'dc' or 'all', got {self.tune!r}")
        if self.decoder_width < 1:
            raise ValueError(f"decoder_width must be >= 1, got {self.decoder_width}")
        if self.decoder_levels < 1:
            raise ValueError(f"decoder_levels must be >= 1, got {self.decoder_levels}")
        if self.decoder_size < 0:
            raise ValueError(f"decoder_size must be >= 0 (0: the view's size), got {self.decoder_size}")
        for name in ("rgb_weight", "hidden_weight", "clean_weight", "classifier_weight", "masking_power",
                     "color_lr", "decoder_lr", "classifier_lr"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


# The box frame's private decoder: k_hid hidden Gaussians from each of the `serving` anchors nearest
# the hidden object (the key keeps the radius that takes them in), through MLPs `width` wide
# (docs/results.md, "Geometric security", measures them). Private codes in the key (`codes` rows,
# `code_cells` cells an axis) carry what the hidden loss would otherwise have written into the public
# features, so the release trains as plain Scaffold-GS does (GRADIENT_SHARES): a cover closer to the
# plain model and a release the audit tells apart less often, for some hidden fidelity at 1080p
# (docs/results.md, "Private codes by default").
BOX_FRAME_DEFAULTS = {"n_hidden": 32, "width": 128, "serving": 1024, "encoding": 6, "depth": 1, "latent": 0,
                      "codes": 16384, "code_cells": 64}
# Where the box frame's hidden Gaussians start (SecureConfig.hidden_start).
HIDDEN_STARTS = ("surface", "centre")
# The shares of the hidden loss's gradient that reach the public features and scalings (feature,
# scaling) for a decoder without private codes: a small share on the features keeps the cover close
# to plain Scaffold-GS and still lets the private heads read the hidden object from them
# (docs/results.md, "What costs the cover its fidelity"). A decoder with codes takes none.
GRADIENT_SHARES = (0.1, 1.0)
# What ``robust`` "auto" trains a hidden object in the cover mode against, and the bit margin it
# was measured with: the payload then survives random pruning, feature noise and purify for no
# training time (docs/results.md, "Robust training by default").
ROBUST_RECIPE = "prune-random:0.3+noise-feat:0.3"
ROBUST_BIT_MARGIN = 0.25
BIT_MARGIN = 1.0
# When the bit projection begins (SecureConfig.bits_from).
BITS_FROM = ("start", "growth-end")
# The finishing phase (a fraction of the iterations) a hidden object in the cover mode gets by default:
# the measured gain in hidden PSNR for about a tenth more training time (docs/results.md, "The
# finishing phase").
FINISH_FRACTION = 0.25
# What the finishing phase trains against where ``robust`` "auto" chose ROBUST_RECIPE: harder dropout
# than the joint run's. The release is frozen in the phase, so the redundancy it teaches the private
# heads costs the cover nothing, only some unattacked hidden fidelity (docs/results.md, "Harder
# dropout in the phase", has the trade).
FINISH_ROBUST_RECIPE = "prune-random:0.5+noise-feat:0.3"


@dataclasses.dataclass(frozen=True)
class SecureConfig:
    """SecureGS on top of a ``TrainConfig``.

    payload: what is hidden (``PayloadSpec`` syntax: ``object``, ``scene``, ``image[:FILE[@VIEW]]``,
        ``bits[:L or :0101...]``, joined with ``+``); several secrets, each with its own private
        heads and key, are separated by ``,`` (``object+bits:48,bits:64``; payload.parse_secrets).
    hidden_weight: λ of ℓ_ori + λ·ℓ_hid; None takes the payload's default (payload.HIDDEN_WEIGHT).
    hidden_feature_grad, hidden_scaling_grad: the share of ℓ_hid's gradient that reaches the public
        anchor features f_v and scalings l_v (1: all of it, as in the paper; 0: none). Both are
        public attributes; below 1 the public loss dominates them and the cover stays closer to
        plain Scaffold-GS, while the private heads carry more of the hidden payload. At 0 in the
        anchor frame the hidden branch is never learnt (the private heads cannot decode it from
        features nothing shapes for it); the box frame still learns it from the anchors' box
        positions and the key's codes. None: 0 for a secret whose decoder has private codes,
        GRADIENT_SHARES otherwise (``gradient_shares``).
    feature_grad_until: the fraction of the run during which hidden_feature_grad applies (after it
        the public loss alone finishes the features).
    bit_margin: after every step each anchor feature is moved the least distance that makes its
        vote's logit agree with its bit by this much (secure/keyed_bits.py; 1: sigmoid 0.73). The
        bits live in the public anchor features, so a larger margin costs the cover fidelity.
        None: ROBUST_BIT_MARGIN where ``robust`` "auto" chose ROBUST_RECIPE, BIT_MARGIN otherwise
        (``margin``).
    bits_from: when the bit projection (bit_margin) begins: "growth-end" (the default), after every
        step once the density strategy has made its last change to the anchor set (``update_until``;
        from the first step when nothing densifies); "start", after every step of the run (what runs
        recorded before this field existed did, and keep: RECORDED_BEFORE).
        Until growth ends the release trains as plain Scaffold-GS of its seed does, so its anchors
        (grown and pruned by that training) are the plain model's, and the anchor cloud says
        nothing of the bits (nor, with the private codes, of the hidden object); the public heads
        then have the rest of the run to adapt to the projected features (docs/results.md, "Bits
        after growth").
    bit_cell_voxels: the edge, in base voxels, of the keyed grid whose cells deal the anchors among
        the bits (the key stores the edge in scene units): an anchor keeps its bit while its position
        moves by less than its distance to a cell face, so a coarser grid survives larger position
        changes (quantisation, float16, noise) and a finer one gives each bit more independent voters.
        16: 8-bit quantisation of a scene's positions moves them by up to an eighth of a 16-voxel cell,
        by half of a 4-voxel one; a message of L bits needs well over L occupied cells (about
        L·exp(−cells/L) bits go without a voter), and a demo-sized model occupies thousands
        (docs/results.md, "The bits read by a majority of signs, and a coarser grid").
    hdger: the paper's hybrid decoupled Gaussian encryption: hidden offsets come from the private
        MLP F_o†; False ("w/o HDGER", an ablation) stores explicit hidden offsets per anchor, which
        cannot be released.
    robust: attacks the hidden branch trains against, joined with + (``secure.robust``:
        ``prune-random:F``, ``noise-xyz:S``, ``noise-feat:S``, ``quantize:B``; strengths drawn each
        step up to the given value); None: none; "auto": ROBUST_RECIPE for a run that hides an object
        (and bits) in the cover mode, none otherwise (``robust_spec``). The public branch is untouched.
    strategy: the region-aware density strategy and its mode (rdo, scaffold, global, shared, cover;
        None: ``strategy_mode`` chooses).
    hidden_frame: where the private F_o† places hidden Gaussians (``PrivateHeads``): "anchor" (the
        paper: near their anchor) or "box" (anywhere in the hidden object's box, decoded from the
        cover's anchors nearest it); None: "box" for an object with the "cover" mode, "anchor"
        otherwise.
    hidden_offsets, hidden_width, hidden_anchors: k_hid (hidden Gaussians per anchor), the private
        MLPs' hidden width and, in the box frame, how many anchors nearest the box decode hidden
        Gaussians. None: the public k and d and every visible anchor in the anchor frame,
        BOX_FRAME_DEFAULTS in the box frame.
    hidden_crop: in the box frame and the cover mode, train each hidden render on the tile-aligned
        part of the view that the key's box can reach (``secure.crop``): the rest of an object's
        hidden view is background in the target, and in the render up to the tails of splats near
        the box's faces, which the crop leaves untrained. Off by default: what it saves in time it
        may cost in hidden fidelity (docs/results.md, "the hidden crop").
    hidden_latent: in the box frame, the resolution r of the key's latent grid (``secure.heads.LatentGrid``:
        r³ private features over the box's neighbourhood, added to each serving anchor's public
        feature before the private heads decode it; 0: none). None: BOX_FRAME_DEFAULTS in the box
        frame; the anchor frame has none.
    hidden_codes: in the box frame, the rows of the key's private per-anchor codes
        (``secure.heads.AnchorCodes``: a feature of the key's for each serving anchor, added to its
        public one before the private heads decode it; 0: none), which take the place of
        hidden_feature_grad's share of the hidden gradient in the release (docs/results.md, "private
        codes"). None: BOX_FRAME_DEFAULTS in the box frame; the anchor frame has none.
    hidden_code_scales: the codes add to the serving anchors' log scalings too (``AnchorCodes``
        scales), taking the place of hidden_scaling_grad's share as well; needs hidden_codes.
    hidden_code_cells: the codes' cells per axis of the contracted box frame (``AnchorCodes``
        cells; saved in the key); None: BOX_FRAME_DEFAULTS.
    hidden_encoding, hidden_depth: F_o†'s octaves of sines and cosines of the anchor's box position
        (box frame only; 0: the position alone) and its number of hidden layers (``PrivateHeads``
        encoding, depth). None: BOX_FRAME_DEFAULTS in the box frame, PrivateHeads' (0 and 1) in the anchor frame.
    hidden_eps2d: the hidden render's screen-space dilation (``PrivateHeads`` eps2d, saved in the key),
        in training and whenever the key renders; None: the public render's ``RasterOptions.eps2d``.
    hidden_scale_gain: how many times its anchor's scale a hidden Gaussian may grow
        (``PrivateHeads`` scale_gain, saved in the key); None: 1, Scaffold-GS's bound. Not the
        default: at low resolution it lifted an object whose large flat parts the cover's small
        anchors could not cover and cost the others; at 1080p it cost both kinds (docs/results.md,
        "A private scale gain", measured before ``hidden_start`` "surface").
    hidden_start: where the box frame's hidden Gaussians start: "surface" (hidden Gaussian j of every
        serving anchor at one of k_hid points spread over the object's surface by farthest-point
        sampling of the scene's points on it, ``PrivateHeads.start_at``) or "centre" (F_o†'s default
        initialisation, which starts them all near the box's centre: the parts of an object far from
        it, such as a lamp's base, then draw few Gaussians that can reach them, docs/results.md,
        "Hidden Gaussians that start on the object's surface"). Training only: the key holds the weights.
    hidden_stride: the hidden renders are made and trained on every hidden_stride-th step only, their
        loss weighted hidden_stride times, so that the hidden loss's gradient keeps its mean over the
        run; the steps between are plain Scaffold-GS steps (plus the bit projection). Most of what a
        SecureGS step adds to a Scaffold-GS step is the per-op host work of the hidden branch, so
        this is the knob that trades hidden fidelity for training time (docs/results.md, "The hidden
        stride"). The private heads take one Adam step per hidden step; the RDO mode gathers ∇_hid
        on the steps that are multiples of both this and its own ``hidden_every``.
    hidden_finish: after the joint run, the private heads alone train on the hidden loss (against
        ``finish_robust``'s attacks) for this fraction of ``iterations`` more steps, while the release stays as
        the joint run left it: the cover, the anchor cloud and the bits do not change, only the key.
        During the joint run the anchor features the private heads read keep moving; the finishing
        phase fits the heads to the features that are published (docs/results.md, "The finishing
        phase"). The key keeps the mean of the heads' weights over the phase's steps after
        ``secure.trainer.FINISH_AVERAGE_FROM`` of it. 0: none; None: FINISH_FRACTION for a run that
        hides an object in the cover mode, where it was measured, 0 otherwise
        (``finish_fraction``). Payloads without a hidden render (bits alone) have nothing to finish.
    finish_robust: the attacks the finishing phase trains against (``robust``'s syntax); None: none;
        "auto": FINISH_ROBUST_RECIPE where ``robust`` "auto" chose ROBUST_RECIPE, ``robust``'s
        resolved spec otherwise (``finish_robust_spec``).
    hidden_capture: on CUDA, a box-frame key's decoding of its serving anchors (``hidden_anchors``
        > 0) is replayed from CUDA graphs during training (``secure.captured``): the same values up
        to float rounding, for a fraction of the host work; in the cover mode without the hidden
        crop its rasterize is replayed too (``RasterOptions.capture``; the intersection capacity
        grows with what the views need, and a step whose render overflowed it is skipped). Robust
        training's attacks on anchor positions (``noise-xyz``, ``quantize``) replay too: they serve
        as many anchors, by rank (``SecureModel._decoding_rows``). The whole hidden branch
        (attacks, decoding, rasterize, loss, backward; in the finishing phase also Adam) is then
        replayed from CUDA graphs where ``secure.hidden_graph.replayable`` allows (training views
        of one size, whole views, an object payload in the cover mode, the phase's attacks of
        prune-random and noise-feat only, drawn on the serving rows alone from the device's
        generator, which a checkpoint does not hold: a resumed run draws other attacks);
        otherwise it runs op by op. Evaluation (no gradients) and the CPU decode op by op, as
        everything does with it off.
    """

    payload: str = "object+bits:48"
    hidden_weight: float | None = None
    hidden_feature_grad: float | None = None
    hidden_scaling_grad: float | None = None
    feature_grad_until: float = 1.0
    robust: str | None = "auto"
    bit_margin: float | None = None
    bits_from: str = "growth-end"
    bit_cell_voxels: float = 16.0
    hdger: bool = True
    strategy: RegionAwareStrategy = dataclasses.field(default_factory=RegionAwareStrategy)
    hidden_frame: str | None = None
    hidden_offsets: int | None = None
    hidden_width: int | None = None
    hidden_anchors: int | None = None
    hidden_latent: int | None = None
    hidden_codes: int | None = None
    hidden_code_scales: bool = False
    hidden_code_cells: int | None = None
    hidden_encoding: int | None = None
    hidden_depth: int | None = None
    hidden_eps2d: float | None = None
    hidden_scale_gain: float | None = None
    hidden_crop: bool = False
    hidden_start: str = "surface"
    hidden_stride: int = 1
    hidden_finish: float | None = None
    finish_robust: str | None = "auto"
    hidden_capture: bool = True

    def strategy_mode(self, kinds) -> str:
        """The density mode of a run whose secrets hide ``kinds`` (``PayloadSpec.kind`` of each; None
        for bits alone):
        ``strategy.mode`` when given, else "cover" when one of them is an object (the paper's RDO grows
        anchors on the hidden surface, so the public anchor cloud draws the object: docs/results.md,
        "Geometric security") or when all are bits (no hidden render gives RDO a gradient, and its
        empty Γ_hid growth still draws from the growth generator, so the anchors would drift from
        plain Scaffold-GS's of the seed), and "rdo" for images and scenes, which have no surface of
        their own to keep out of the cloud."""
        if self.strategy.mode is not None:
            return self.strategy.mode
        return "cover" if "object" in kinds or all(kind is None for kind in kinds) else "rdo"

    def robust_spec(self, kinds, mode: str) -> str | None:
        """The attacks a run whose secrets hide ``kinds`` (``PayloadSpec.kind`` of each; None for
        bits alone) in density ``mode`` (``strategy_mode``) trains against: ``robust``, with "auto"
        resolved. The recipe is measured on an object (and its bits) in the cover mode only, and
        applies to a run whose other secrets are bits alone; an image or scene decodes from the
        visible anchors, where dropout changes the rows every step."""
        if self.robust != "auto":
            return self.robust
        measured = mode == "cover" and "object" in kinds and all(kind in ("object", None) for kind in kinds)
        return ROBUST_RECIPE if measured else None

    def finish_robust_spec(self, kinds, mode: str) -> str | None:
        """The attacks the finishing phase of such a run trains against: ``finish_robust``, with
        "auto" resolved (FINISH_ROBUST_RECIPE where ``robust`` "auto" chose ROBUST_RECIPE, where it
        was measured; the joint run's attacks otherwise)."""
        if self.finish_robust != "auto":
            return self.finish_robust
        joint = self.robust_spec(kinds, mode)
        return FINISH_ROBUST_RECIPE if self.robust == "auto" and joint else joint

    def margin(self, kinds, mode: str) -> float:
        """``bit_margin``, or its default for such a run: the recipe's where "auto" chose the recipe
        (``robust_spec``), BIT_MARGIN otherwise (an explicit ``robust`` keeps it: nothing else
        was measured with 0.25)."""
        if self.bit_margin is not None:
            return self.bit_margin
        return ROBUST_BIT_MARGIN if self.robust == "auto" and self.robust_spec(kinds, mode) else BIT_MARGIN

    def finish_fraction(self, kinds, mode: str) -> float:
        """``hidden_finish``, or its default for a run hiding ``kinds`` in ``mode``."""
        if self.hidden_finish is not None:
            return self.hidden_finish
        return FINISH_FRACTION if mode == "cover" and "object" in kinds else 0.0

    def resolved(self, kinds, mode: str) -> "SecureConfig":
        """This config with ``robust``, ``bit_margin``, ``hidden_finish`` and ``finish_robust`` as a run
        hiding ``kinds`` in ``mode`` uses them (what config.json and a checkpoint record, so that a
        later default cannot change a resumed run)."""
        return dataclasses.replace(self, robust=self.robust_spec(kinds, mode), bit_margin=self.margin(kinds, mode),
                                   hidden_finish=self.finish_fraction(kinds, mode),
                                   finish_robust=self.finish_robust_spec(kinds, mode))

    def private_options(self, kind: str | None, mode: str) -> dict:
        """The ``PrivateHeads`` keyword arguments these options select (frame, n_hidden, width,
        serving, encoding, depth, latent, codes, code_scales, code_cells, eps2d, scale_gain) for a secret hiding ``kind`` (a ``PayloadSpec.kind``) in a run of
        density ``mode`` (``strategy_mode``), with the frame's defaults filled in."""
        frame = self.hidden_frame or ("box" if mode == "cover" and kind == "object" else "anchor")
        given = {"n_hidden": self.hidden_offsets, "width": self.hidden_width, "serving": self.hidden_anchors,
                 "encoding": self.hidden_encoding, "depth": self.hidden_depth, "latent": self.hidden_latent,
                 "codes": self.hidden_codes, "code_scales": self.hidden_code_scales,
                 "code_cells": self.hidden_code_cells, "eps2d": self.hidden_eps2d,
                 "scale_gain": self.hidden_scale_gain}
        # The anchor frame leaves what is not given to PrivateHeads' own defaults (the public k and d).
        defaults = BOX_FRAME_DEFAULTS if frame == "box" else {}
        return {"frame": frame, **defaults, **{name: value for name, value in given.items() if value is not None}}

    def gradient_shares(self, kind: str | None, mode: str) -> tuple[float, float]:
        """(feature, scaling): the shares of the hidden loss's gradient that reach the public anchor
        features and scalings for a secret hiding ``kind`` in a run of density ``mode``: those given,
        else 0 where the secret's decoder has private codes (they take the shares' place, so the
        hidden loss moves nothing in the release) and GRADIENT_SHARES otherwise."""
        defaults = (0.0, 0.0) if self.private_options(kind, mode).get("codes") else GRADIENT_SHARES
        given = (self.hidden_feature_grad, self.hidden_scaling_grad)
        return tuple(default if share is None else share for share, default in zip(given, defaults))

    def __post_init__(self):
        if self.hidden_frame not in (None, "anchor", "box"):
            raise ValueError(f"hidden_frame must be 'anchor' or 'box', got {self.hidden_frame!r}")
        if self.hidden_start not in HIDDEN_STARTS:
            raise ValueError(f"hidden_start must be one of {HIDDEN_STARTS}, got {self.hidden_start!r}")
        for name in ("hidden_offsets", "hidden_width", "hidden_anchors", "hidden_depth", "hidden_stride"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.hidden_finish is not None and not 0.0 <= self.hidden_finish < math.inf:
            raise ValueError(f"hidden_finish must be >= 0 (a fraction of the iterations), got {self.hidden_finish}")
        if self.hidden_encoding is not None and self.hidden_encoding < 0:
            raise ValueError(f"hidden_encoding must be >= 0, got {self.hidden_encoding}")
        if self.hidden_eps2d is not None and not 0.0 <= self.hidden_eps2d < math.inf:
            raise ValueError(f"hidden_eps2d must be >= 0 and finite, got {self.hidden_eps2d}")
        if self.hidden_scale_gain is not None and not 1.0 <= self.hidden_scale_gain < math.inf:
            raise ValueError(f"hidden_scale_gain must be >= 1 and finite, got {self.hidden_scale_gain}")
        if self.hidden_codes is not None and self.hidden_codes < 0:
            raise ValueError(f"hidden_codes must be 0 (none) or a number of rows >= 1, got {self.hidden_codes}")
        if self.hidden_code_cells is not None and self.hidden_code_cells < 1:
            raise ValueError(f"hidden_code_cells must be >= 1, got {self.hidden_code_cells}")
        if self.hidden_code_cells is not None and self.hidden_codes == 0:
            raise ValueError("hidden_code_cells sizes the codes' cells: it needs hidden_codes >= 1")
        if self.hidden_code_scales and self.hidden_codes == 0:
            raise ValueError("hidden_code_scales adds the codes to the anchors' scalings: it needs hidden_codes >= 1")
        if self.hidden_latent is not None and (self.hidden_latent < 0 or self.hidden_latent == 1):
            raise ValueError(f"hidden_latent must be 0 (none) or a grid resolution >= 2, got {self.hidden_latent}")
        if self.hidden_weight is not None and not self.hidden_weight >= 0.0:
            raise ValueError(f"hidden_weight (λ) must be >= 0, got {self.hidden_weight}")
        if self.bit_margin is not None and not self.bit_margin > 0.0:
            raise ValueError(f"bit_margin must be > 0, got {self.bit_margin}")
        if self.bits_from not in BITS_FROM:
            raise ValueError(f"bits_from must be one of {', '.join(BITS_FROM)}, got {self.bits_from!r}")
        if not self.bit_cell_voxels > 0.0:
            raise ValueError(f"bit_cell_voxels must be > 0, got {self.bit_cell_voxels}")
        for name, meaning in (("hidden_feature_grad", "a share of a gradient"),
                              ("hidden_scaling_grad", "a share of a gradient"),
                              ("feature_grad_until", "a fraction of the run")):
            value = getattr(self, name)
            if value is not None and not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must lie in [0, 1] ({meaning}), got {value}")
        # Frozen: the one spelling of each recipe is set here, so that a recorded run and its
        # resume compare equal however either wrote the numbers.
        for name in ("robust", "finish_robust"):
            object.__setattr__(self, name, canonical_attacks(getattr(self, name), name))


@dataclasses.dataclass(frozen=True)
class GSHiderConfig:
    """GS-Hider (Zhang et al., NeurIPS 2024) on a plain 3DGS ``TrainConfig`` (its iterations, seed,
    rasterizer, SSIM weight, densification and learning rates; the feature's learning rate is
    ``gaussians.sh_lr``, 0.0025 as GS-Hider's ``semantic_feature_lr``). Defaults are the authors'
    code (xuanyuzhang21/GS-Hider, train_wm.py, decoder.py) where it states them.

    channels: M, the width of each Gaussian's coupled feature (the authors' 16). decoder_width,
    decoder_layers: both decoders are that many 3×3 convolutions, ReLU between, ``decoder_width``
    wide (theirs: 5 layers, 64 wide). hidden_weight: ℓ = ℓ_scene + w·ℓ_message (their 0.5).
    decoder_lr: Adam for both decoders (their 1e-3). feature_background: the value every feature
    channel takes behind the Gaussians (their rasterizer writes the background's first channel
    into all 16; black on their real scenes, so 0 by default).
    Run by ``baselines.gs_hider`` (and scripts/compare_methods.py), not a run folder's section.
    """

    channels: int = 16
    decoder_width: int = 64
    decoder_layers: int = 5
    hidden_weight: float = 0.5
    decoder_lr: float = 0.001
    feature_background: float = 0.0

    def __post_init__(self):
        for name in ("channels", "decoder_width"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.decoder_layers < 2:
            raise ValueError(f"decoder_layers must be >= 2 (an input and an output convolution), "
                             f"got {self.decoder_layers}")
        for name in ("hidden_weight", "decoder_lr"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """How to (re)build a run's scene: a built-in name or a data folder, with loader options.

    source: a built-in scene name (synthetic, room, garden) or a COLMAP / Blender folder (stored as
    an absolute path, so a run can be evaluated from another working directory).
    width, height, n_train, n_test, seed: synthetic scenes only. hidden, level: what the synthetic
    scene renders as hidden views (an object or scene name, a mesh file), and whether a hidden
    object stands alone ("object") or inside the scene ("scene"); hidden_position, hidden_size,
    hidden_yaw, hidden_up (a mesh file's up axis), hidden_placement: where and how it stands
    (``make_synthetic_scene``). downscale: real data only.
    """

    source: str = "synthetic"
    width: int = 128
    height: int = 96
    n_train: int = 32
    n_test: int = 8
    seed: int = 0
    hidden: str | None = None
    level: str = "object"
    hidden_position: tuple | None = None
    hidden_size: float = 1.2
    hidden_yaw: float = 0.0
    hidden_up: str = "z"
    hidden_placement: str = "stand"
    downscale: int = 1

    def __post_init__(self):
        check_seed(self.seed, "scene seed")
        for name in ("width", "height", "n_train", "n_test", "downscale"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.hidden_position is not None and (len(self.hidden_position) != 3
                                                 or not all(math.isfinite(v) for v in self.hidden_position)):
            raise ValueError(f"hidden_position must be x,y,z (finite), got {self.hidden_position}")
        if not (self.hidden_size > 0 and math.isfinite(self.hidden_size)):
            raise ValueError(f"hidden_size must be > 0 and finite, got {self.hidden_size}")
        if not math.isfinite(self.hidden_yaw):
            raise ValueError(f"hidden_yaw must be finite (degrees), got {self.hidden_yaw}")
        if reads_as_folder(self.source) and not Path(self.source).is_absolute():
            object.__setattr__(self, "source", str(Path(self.source).resolve()))

    @property
    def builtin(self) -> bool:
        """Whether the source names a built-in scene rather than a folder (``reads_as_folder``: a
        run's output named "garden" does not hide the built-in garden)."""
        return not reads_as_folder(self.source)

    def load(self):
        """The ``SceneData`` this spec describes."""
        if self.builtin:
            return load_scene(self.source, hidden=self.hidden, level=self.level, width=self.width,
                              height=self.height, n_train=self.n_train, n_test=self.n_test, seed=self.seed,
                              hidden_position=self.hidden_position, hidden_size=self.hidden_size,
                              hidden_yaw=self.hidden_yaw, hidden_up=self.hidden_up,
                              hidden_placement=self.hidden_placement)
        return load_scene(self.source, downscale=self.downscale)


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """What a run folder's ``config.json`` holds: the scene, the training, and SecureGS (or None)."""

    scene: SceneSpec = dataclasses.field(default_factory=SceneSpec)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)
    secure: SecureConfig | None = None

    def __post_init__(self):
        if self.secure is not None and self.train.model != "scaffold":
            raise ValueError(f"SecureGS hides in a Scaffold-GS model; train.model {self.train.model!r} cannot "
                             "carry its payload")


# ---------------------------------------------------------------------------------------------
# To and from plain dicts (JSON), by field name
# ---------------------------------------------------------------------------------------------


def to_dict(config) -> dict:
    """A config dataclass as nested plain dicts (JSON-able; tuples become lists)."""
    out = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            value = to_dict(value)
        elif isinstance(value, tuple):
            value = list(value)
        elif isinstance(value, float) and math.isinf(value):
            value = str(value)  # "inf": JSON has no infinity
        out[f.name] = value
    return out


# Fields whose default differs from how runs recorded before the field existed trained: (config
# class name, field) -> the value those runs used, which a recorded config without the field takes,
# so that reading or resuming such a run keeps what it did.
RECORDED_BEFORE = {("SecureConfig", "bits_from"): "start"}


def from_dict(cls, data: dict, where: str = ""):
    """Build config dataclass ``cls`` from ``to_dict`` output; unknown fields are refused by name.

    Fields missing from ``data`` (a config written before a field existed) take the value such runs
    used (RECORDED_BEFORE), else their defaults.
    """
    if not isinstance(data, dict):
        raise ValueError(f"{where or cls.__name__}: expected a mapping of options, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ValueError(f"unknown option {_path(where, unknown[0])!r} (known: {', '.join(sorted(known))})")
    kwargs = {name: value for (owner, name), value in RECORDED_BEFORE.items()
              if owner == cls.__name__ and name not in data}
    for name, value in data.items():
        kwargs[name] = _coerce(hints[name], value, _path(where, name))
    return cls(**kwargs)


def _coerce(hint, value, where: str):
    """``value`` (from JSON or a command line) as the type ``hint`` names."""
    options = [a for a in typing.get_args(hint) if a is not type(None)] if typing.get_origin(hint) in (
        typing.Union, getattr(__import__("types"), "UnionType", None)) else [hint]
    if value is None or (isinstance(value, str) and value.lower() == "none"):
        if len(options) < len(typing.get_args(hint)) or hint is type(None):
            return None
        raise ValueError(f"{where} cannot be empty")
    target = options[0]
    if dataclasses.is_dataclass(target):
        return value if isinstance(value, target) else from_dict(target, value, where)
    try:
        if target is bool:
            if isinstance(value, str):
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError
                return value.lower() in ("true", "1")
            return bool(value)
        if target is tuple or typing.get_origin(target) is tuple:
            items = value.split(",") if isinstance(value, str) else value
            return tuple(float(v) for v in items)
        if target is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError
            return int(value)
        if target is float:
            return float(value)
        if target is str:
            return str(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {value!r} is not a valid {getattr(target, '__name__', target)}") from None
    return value


def _path(where: str, name: str) -> str:
    return f"{where}.{name}" if where else name


def field_paths(config) -> dict[str, type]:
    """Dotted path -> type of every leaf field of a config dataclass (nested sections expanded;
    an optional section that is None has no leaves)."""
    out = {}
    hints = typing.get_type_hints(type(config))
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            out.update({f"{f.name}.{k}": t for k, t in field_paths(value).items()})
        else:
            out[f.name] = hints[f.name]
    return out


def resolve_field(config, name: str) -> str:
    """The dotted path of field ``name`` in ``config``: a full path, or a tail of one that is unique in
    the tree (``r_down`` or ``strategy.r_down`` for ``secure.strategy.r_down``)."""
    paths = field_paths(config)
    if name in paths:
        return name
    matches = [p for p in paths if p.endswith("." + name)]
    if len(matches) == 1:
        return matches[0]
    if matches:
        raise ValueError(f"option {name!r} is ambiguous: {', '.join(matches)}")
    raise ValueError(f"unknown option {name!r}; known: {', '.join(sorted(paths))}")


def apply_overrides(config, overrides: dict):
    """A copy of ``config`` with ``{field name or dotted path: value}`` set; values may be strings
    (from a command line or a variant) and are converted to the field's type. Checks run as for a
    freshly built config (a bad value raises ValueError naming the field)."""
    for name, value in overrides.items():
        config = _set(config, resolve_field(config, name).split("."), value, "")
    return config


def _set(config, parts: list[str], value, where: str):
    head, rest = parts[0], parts[1:]
    path = _path(where, head)
    if rest:
        return dataclasses.replace(config, **{head: _set(getattr(config, head), rest, value, path)})
    hint = typing.get_type_hints(type(config))[head]
    return dataclasses.replace(config, **{head: _coerce(hint, value, path)})


# Options a resumed run may change: the finishing phase acts after the joint run and never changes
# the release, so a run whose checkpoint has not begun it (a finished joint run with none, say) may
# take one of any length and attacks; once begun, they stay (SecureTrainer.restore).
RESUMABLE_CHANGES = ("secure.hidden_finish", "secure.finish_robust")


def canonical_attacks(text: str | None, option: str) -> str | None:
    """``text`` (attacks joined with +, the syntax of ``SecureConfig.robust``) with each attack
    written as ``Attack.text`` writes it ("prune-random:0.50" -> "prune-random:0.5"), in its order
    (the attacks draw their randomness in that order); None and "auto" are returned as they are. A
    bad spec raises ValueError naming ``option``."""
    if text in (None, "auto"):
        return text
    from .secure.robust import parse_robust  # the attacks module imports this one

    return "+".join(attack.text for attack in parse_robust(text, option))


def recorded_phase(secure: dict) -> dict:
    """Field name -> value of each of RESUMABLE_CHANGES in a recorded ``secure`` section (of
    config.json or a checkpoint's config), as the run trained it: a run recorded before
    ``hidden_finish`` existed had no finishing phase, one recorded before ``finish_robust`` existed
    trained its phase against the joint run's attacks."""
    return {"hidden_finish": secure.get("hidden_finish") or 0.0,
            "finish_robust": canonical_attacks(secure.get("finish_robust", secure.get("robust")), "finish_robust")}


def first_difference(a, b, where: str = "", ignore: tuple = ()) -> str | None:
    """The dotted path of the first field where two configs of the same type differ, or None;
    fields at the dotted paths ``ignore`` are not compared."""
    if where in ignore:
        return None
    if type(a) is not type(b):
        return where or "config"
    if not dataclasses.is_dataclass(a):
        return None if a == b else where
    for f in dataclasses.fields(a):
        diff = first_difference(getattr(a, f.name), getattr(b, f.name), _path(where, f.name), ignore)
        if diff is not None:
            return diff
    return None
