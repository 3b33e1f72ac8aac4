"""``rasterize``: the differentiable Warp rasterizer as a torch autograd op.

A ``RenderPlan`` holds one render's Warp views and launches: projection (its adjoint is Warp's
generated one), binning, and blending (hand-written adjoint). Torch tensors are shared with Warp
through ``wp.from_torch`` (no copies); Warp runs on the torch device of the inputs and on torch's
current stream, so the CPU and CUDA share one code path. ``RasterOptions.capture`` replays a plan
kept per shape from Warp graphs (``securegs_warp.raster_graph``).
"""
from __future__ import annotations

import dataclasses
import functools
import math

import torch
import warp as wp

from .kernels import binning
from .kernels.blend import (CPU_BATCH, backward_threads, batch_size, blend_kernels, check_backward_pixels,
                            gradient_width, unpack_gradients_kernel)
from .kernels.records import COLOR_STORAGES, record_width
from .kernels.projection import RADIUS_RULES, projection_kernel
from .warp_scope import WarpScope

DEPTH_MODES = (None, "accumulated", "expected")
# Which tiles a Gaussian is binned to: every tile of its radius rectangle (gsplat 1.5), or only those
# its ellipse at the alpha threshold reaches (same image, fewer intersections to sort and blend).
TILE_OVERLAPS = ("ellipse", "rectangle")
# Each render's buffers are released by its backward (a training loop would otherwise hold them until
# the autograd graph is freed), so a render has one backward.
SECOND_BACKWARD = ("rasterize: this render's backward has already run and released its buffers (one backward a "
                   "render; retain_graph=True does not keep them): render again for another backward")
# The most entries of the sort's key and value buffers: Warp's array dimensions are int32.
MAX_SORTED = 2**31 - 1
# The least transmittance_min: the blending backward rebuilds each earlier transmittance from the
# last one, which keeps too few significant bits below float32's smallest normal number (2⁻¹²⁶).
TRANSMITTANCE_FLOOR = 2.0 ** -126
BACKWARD_WALKS = ("block", "warp")
GATHERS = ("fields", "packed")


@dataclasses.dataclass(frozen=True)
class RasterOptions:
    """Everything that changes what or how ``rasterize`` computes. Defaults are gsplat 1.5's.

    Flags (antialiased, radius_rule, tile_size, depth on/off, channel count, fast_math,
    color_storage) select compiled kernel variants, so an effect that is off costs nothing; the
    numbers are run-time kernel arguments.

    Accuracy for time (scripts/accuracy_vs_time.py measures both):
    fast_math: projection and blending compiled with Warp's fast math (CUDA only; Warp 1.19's
        CPU compiler ignores the option, so on the CPU it changes nothing). On by default because
        gsplat 1.5 is itself compiled with ``--use_fast_math``; gradients move against the exact
        float32 path by the amounts docs/results.md measures ("Packed Gaussian records").
    color_storage: "float16" blends from a float16 copy of ``colors`` made once per render (half
        the bytes per colour read, for wide feature fields on the GPU; on the CPU each read pays a
        conversion). The image error is at most the colours' float16 rounding (≤ 2⁻¹¹·max|colour|,
        2⁻¹² for colours in [0, 1]); colour gradients are still float32. Colours beyond ±65504
        would become inf there and raise ValueError.
    """

    near_plane: float = 0.01
    far_plane: float = 1e10
    eps2d: float = 0.3
    radius_clip: float = 0.0
    alpha_min: float = 1.0 / 255.0
    alpha_max: float = 0.999
    transmittance_min: float = 1e-4
    tile_size: int = 16
    antialiased: bool = False
    radius_rule: str = "opacity_aware"
    render_depth: str | None = None
    fast_math: bool = True
    color_storage: str = "float32"
    # "ellipse": bin a Gaussian only to the tiles of its radius rectangle where opacity·e^(−σ) reaches
    # alpha_min at some pixel centre (an exact ellipse–rectangle test; kernels/binning.py). The image
    # is the same as "rectangle"'s (gsplat's binning): the dropped tiles receive no contribution.
    tile_overlap: str = "ellipse"
    # Replay the forward (projection → binning → blend) and the backward as Warp graphs kept per
    # input shape, for loops that render the same N, C and image size again and again: no host
    # launches or synchronisations per render. The sort runs over a fixed intersection capacity (the
    # first render's count with headroom). A later render that needs more lacks intersections, which
    # its info["complete"] tells; the next call of its pooled entry grows the capacity, and raises if
    # nobody asked. One with non-finite inputs raises there, or at complete()
    # (securegs_warp/raster_graph.py). Same images and gradients as eager otherwise. On the CPU it
    # runs the same fixed-capacity launches without a graph.
    capture: bool = False
    # CUDA launch shape only (results do not depend on it): threads per block of the forward and
    # backward blending kernels; a block owns that many pixels of a tile and shares each batch of
    # Gaussians between them. 256 because backward blocks of 256 measured faster than blocks of 32
    # (docs/results.md, "Rasterizer speed against gsplat"; scripts/bench_rasterizer.py --variant
    # b32:backward_block=32 compares them).
    forward_block: int = 256
    backward_block: int = 256
    # Where each pixel group of the backward starts its back-to-front walk of a batch: at the last
    # Gaussian any pixel of the block used ("block"), or of its own CUDA warp ("warp", gsplat's
    # bound: warps whose pixels stopped early skip the tail). Same gradients; launch work only
    # (scripts/bench_rasterizer.py --variant warpwalk:backward_walk=warp compares them).
    backward_walk: str = "block"
    # CUDA only: registers per thread the backward blending kernel may use (0: the compiler's
    # choice, 92 for 3 channels on sm_90). At 256 threads a block, ≤ 80 fits 3 blocks on an H100
    # multiprocessor instead of 2, ≤ 64 fits 4, against a few bytes spilled to local memory.
    backward_max_registers: int = 0
    # Pixels each thread of the backward blending kernel walks (1, 2 or 4; 4 needs tiles of 16 or 32):
    # a thread reads each Gaussian once for its pixels and sums their gradients before the warp's
    # shuffles and atomics, which P pixels a thread divide by P, against more registers a thread.
    # Same gradients up to the order of float sums. 2 because its backward measured fastest on an
    # H100 (docs/results.md, "Two pixels a thread in the blending backward";
    # scripts/bench_rasterizer.py --variant px1:backward_pixels=1 compares them).
    backward_pixels: int = 2
    # How the blending kernels gather each batch of Gaussians: one indexed load per field (means2d,
    # conics, opacities, colours, depths: "fields"), or one of a per-Gaussian record that the
    # projection writes beside its outputs ("packed": x, y, conic, opacity, depth, the blending box
    # and float32 colours in one 16-byte-aligned float32 row; float16 colours keep their own table).
    # On CUDA each indexed load into shared memory ends in a block barrier, so "packed" pays one
    # global-memory latency per batch where "fields" pays four or five (scripts/kernel_registers.py
    # counts the barriers), for N × 12 float32 words more memory (RGB; 4·⌈(9+C)/4⌉ for C float32
    # colours, 12 with float16 colours). Only "packed" carries the blending box with which the
    # backward skips, a warp at a time, the Gaussians its pixels all miss (kernels/records.py,
    # blend_box). Bit-identical images and gradients on the CPU; on CUDA the
    # gradients' atomic sums add in a varying order for either gather, so the two agree to float
    # rounding. scripts/bench_rasterizer.py --variant fields:gather=fields compares them. "packed" by default:
    # faster in both blending kernels on an H100 (docs/results.md, "Packed Gaussian records").
    gather: str = "packed"

    def __post_init__(self):
        if self.tile_size not in (8, 16, 32):
            raise ValueError(f"tile_size must be 8, 16 or 32, got {self.tile_size}")
        if self.radius_rule not in RADIUS_RULES:
            raise ValueError(f"radius_rule must be one of {RADIUS_RULES}, got {self.radius_rule!r}")
        if self.color_storage not in COLOR_STORAGES:
            raise ValueError(f"color_storage must be one of {tuple(COLOR_STORAGES)}, got {self.color_storage!r}")
        if self.tile_overlap not in TILE_OVERLAPS:
            raise ValueError(f"tile_overlap must be one of {TILE_OVERLAPS}, got {self.tile_overlap!r}")
        if self.backward_max_registers and not 32 <= self.backward_max_registers <= 255:
            raise ValueError(f"backward_max_registers must be 0 (the compiler's choice) or in [32, 255], "
                             f"got {self.backward_max_registers}")
        if self.gather not in GATHERS:
            raise ValueError(f"gather must be one of {GATHERS}, got {self.gather!r}")
        check_backward_pixels(self.tile_size, self.backward_pixels)
        if self.backward_walk not in BACKWARD_WALKS:
            raise ValueError(f"backward_walk must be one of {BACKWARD_WALKS}, got {self.backward_walk!r}")
        if self.render_depth not in DEPTH_MODES:
            raise ValueError(f"render_depth must be one of {DEPTH_MODES}, got {self.render_depth!r}")
        if not 0.0 < self.near_plane < self.far_plane:
            raise ValueError(f"need 0 < near_plane < far_plane, got {self.near_plane}, {self.far_plane}")
        if not 0.0 < self.alpha_min <= self.alpha_max < 1.0:
            raise ValueError(f"need 0 < alpha_min <= alpha_max < 1, got {self.alpha_min}, {self.alpha_max}")
        if not TRANSMITTANCE_FLOOR <= self.transmittance_min < 1.0:
            raise ValueError(f"need {TRANSMITTANCE_FLOOR:.4g} <= transmittance_min < 1 (float32's smallest normal "
                             f"number; below it the transmittance becomes subnormal and the backward, which "
                             f"rebuilds every earlier transmittance from the last, loses its precision), "
                             f"got {self.transmittance_min}")
        if self.eps2d < 0.0:
            raise ValueError(f"eps2d must be >= 0, got {self.eps2d}")
        for name in ("forward_block", "backward_block"):
            b = getattr(self, name)
            # At least one full warp: the backward reduces gradients with 32-lane shuffles.
            if b < 32 or b & (b - 1) or b > 1024:
                raise ValueError(f"{name} must be a power of two in [32, 1024], got {b}")

    @classmethod
    def for_device(cls, device: torch.device | str, **fields) -> RasterOptions:
        """Options for rendering on ``device``: the given ``fields``, and the tile size that suits it
        unless ``fields`` names one.

        The tile is 8 on the CPU, where each pixel's thread walks its tile's list of Gaussians and
        smaller tiles give shorter lists (faster there), and 16 on CUDA (gsplat's default): there
        tiles of 8 blend faster too, but binning a trained scene's large Gaussians to them costs
        more than that saves (docs/results.md, "Gradient sums in shared memory, and tiles of 8 on
        CUDA"). This is the one place the rule is written. Raises ValueError as ``RasterOptions``
        does, and for an unknown field (``UnknownOptionError``, naming it and listing the valid ones).

        >>> RasterOptions.for_device("cpu").tile_size, RasterOptions.for_device("cuda").tile_size
        (8, 16)
        """
        check_option_names(fields)
        fields.setdefault("tile_size", 8 if torch.device(device).type == "cpu" else 16)
        return cls(**fields)

    def block(self, threads: int) -> int:
        """Block size for a blending kernel: at most one tile, a divisor of its pixel count."""
        return min(threads, self.tile_size * self.tile_size)


class UnknownOptionError(ValueError, TypeError):
    """A keyword that is not a ``RasterOptions`` field. A ValueError like every other bad option;
    also a TypeError, which is what an unexpected keyword argument raises in Python."""


def check_option_names(names) -> None:
    """Raise ``UnknownOptionError`` naming every one of ``names`` that is not a ``RasterOptions``
    field, and listing the fields."""
    valid = [f.name for f in dataclasses.fields(RasterOptions)]
    unknown = [name for name in names if name not in valid]
    if unknown:
        raise UnknownOptionError(f"unknown rasterize option(s) {', '.join(map(repr, unknown))}; "
                                 f"valid RasterOptions fields: {', '.join(valid)}")


def resolve_options(options: RasterOptions | None = None, **overrides) -> RasterOptions:
    """``options`` (default ``RasterOptions()``) with ``overrides`` replacing its fields.

    Raises:
        UnknownOptionError (a ValueError): an override that is not a field, named with the valid ones.
        ValueError: a field value ``RasterOptions`` refuses.
    """
    if options is not None and not isinstance(options, RasterOptions):
        raise ValueError(f"options must be a RasterOptions, got {type(options).__name__}")
    check_option_names(overrides)
    if options is None:
        return RasterOptions(**overrides)
    return dataclasses.replace(options, **overrides) if overrides else options


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    options: RasterOptions | None = None,
    **overrides,
):
    """Render N 3D Gaussians from one pinhole camera, differentiably.

    ``rasterize(..., options=RasterOptions(tile_size=8))`` and ``rasterize(..., tile_size=8)`` are the
    same render; given both, the keywords replace those fields of ``options``
    (``dataclasses.replace(options, **overrides)``).

    Args:
        means: [N, 3] centres in world space.
        quats: [N, 4] rotations, w first; need not be normalised.
        scales: [N, 3] linear (not log) standard deviations along the rotated axes.
        opacities: [N] in [0, 1].
        colors: [N, C] per-Gaussian values, any C >= 1 (3 for RGB, 16+ for feature fields).
        viewmat: [4, 4] world-to-camera, OpenCV axes (x right, y down, z forward).
        K: [3, 3] pinhole intrinsics (fx, fy, cx, cy used).
        width, height: image size in pixels.
        background: [C] colour behind the Gaussians, or None for zeros.
        options: a ``RasterOptions``, or None for its defaults (gsplat 1.5's; see
            ``RasterOptions.for_device`` for the tile size that suits a device).
        **overrides: fields of ``RasterOptions`` (near_plane, far_plane, eps2d, radius_clip,
            alpha_min, alpha_max, transmittance_min, tile_size, antialiased, radius_rule,
            render_depth=None | "accumulated" | "expected", fast_math, color_storage="float32" |
            "float16", tile_overlap="ellipse" | "rectangle", capture, forward_block, backward_block,
            backward_walk, backward_max_registers, backward_pixels, gather="fields" | "packed"),
            replacing those of ``options``.

    Returns:
        image [H, W, C], alpha [H, W, 1], info: dict with
        ``radii`` [N, 2] int32 (0: culled), ``means2d`` [N, 2], ``conics`` [N, 3], ``depths`` [N],
        ``opacities`` [N] (after antialiasing compensation), ``n_intersections`` (an int; with
        ``capture`` a 0-d int64 device tensor, so that reading it is the caller's choice), ``tile_size``,
        ``width``, ``height``, ``depth`` [H, W, 1] when asked, and ``means2d_grad`` [N, 2], which the
        backward pass fills with dL/d means2d (pixels) for densification statistics. With
        ``capture`` also ``complete``: a function that waits for this render and tells whether its
        intersections fit the capacity (False: the image lacks some; see ``raster_graph``), raising
        for a non-finite input.

    Raises:
        ValueError: a tensor with the wrong shape, a non-finite value (naming the tensor), a bad
            option value, an unknown option keyword (``UnknownOptionError``, which names it and
            lists the valid fields; also a TypeError), a non-positive image size, or an image more
            than ``binning.MAX_TILES_PER_AXIS`` tiles wide or high.
    """
    opts = resolve_options(options, **overrides)
    named = _validated(means, quats, scales, opacities, colors, viewmat, K, width, height, background)
    means, quats, scales, opacities, colors, viewmat, K, background = named.values()
    # The table the blending kernels read: a float16 copy made once per render, or colors itself.
    color_table = colors.to(torch.float16) if opts.color_storage == "float16" else colors
    inputs = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, color_table=color_table,
                  background=background, viewmat=viewmat.detach().reshape(16), K=K.detach().reshape(9))
    # The inputs whose finiteness is checked, as name in an error message → key of ``inputs`` (an
    # empty tensor has nothing to check).
    checked = {name: name for name in named}
    if color_table is not colors:
        checked["colors (as float16: |value| > 65504)"] = "color_table"
    checked = {name: key for name, key in checked.items() if inputs[key].numel()}
    # means2d_grad is added after the op has queued its work (a captured render's replay starts the
    # GPU sooner); only the backward reads it.
    info = {"tile_size": opts.tile_size, "width": int(width), "height": int(height)}
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means, quats, scales, opacities, colors, background))
    if opts.capture:
        from .raster_graph import rasterize_captured  # noqa: PLC0415 (it builds on this module)

        # A replay checks finiteness in its graph (raster_graph).
        outputs = rasterize_captured(inputs, int(width), int(height), opts, info, checked)
    else:
        # Checked on the device and read back with the intersection count (the render's one host
        # synchronisation): one fused max-|value| reduction over the inputs (NaN and inf propagate
        # through it).
        tensors = [inputs[key] for key in checked.values()]
        flags = torch.stack(torch._foreach_norm(tensors, math.inf)).isfinite() if tensors else None
        outputs = _Rasterize.apply(*inputs.values(), int(width), int(height), opts, info, (tuple(checked), flags),
                                   needs_grad)
    image, alpha, depth, radii, means2d, conics, depths, opac, n_isect = outputs
    info["means2d_grad"] = torch.zeros(means.shape[0], 2, device=means.device, dtype=torch.float32)
    info.update(radii=radii, means2d=means2d, conics=conics, depths=depths, opacities=opac, n_intersections=n_isect)
    if opts.render_depth == "accumulated":
        info["depth"] = depth
    elif opts.render_depth == "expected":
        info["depth"] = depth / alpha.clamp_min(1e-10)
    return image, alpha, info


def _validated(means, quats, scales, opacities, colors, viewmat, K, width, height, background):
    """Check types, shapes and devices; return name → float32 contiguous tensor (background filled)."""
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
             "viewmat": viewmat, "K": K}
    for name, t in named.items():
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if not (t.dtype.is_floating_point):
            raise ValueError(f"{name} must be a floating-point tensor, got {t.dtype}")
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    n = means.shape[0]
    expected = {"quats": (n, 4), "scales": (n, 3), "opacities": (n,), "viewmat": (4, 4), "K": (3, 3)}
    for name, shape in expected.items():
        if tuple(named[name].shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {list(named[name].shape)}")
    if colors.ndim != 2 or colors.shape[0] != n or colors.shape[1] < 1:
        raise ValueError(f"colors must be [N, C] with N={n} and C >= 1, got {list(colors.shape)}")
    c = colors.shape[1]
    if background is None:
        background = _zero_background(c, means.device)
    elif not isinstance(background, torch.Tensor) or tuple(background.shape) != (c,):
        raise ValueError(f"background must be a tensor of shape [{c}] (one value per colour channel)")
    named["background"] = background
    for name, t in named.items():
        if t.device != means.device:
            raise ValueError(f"{name} is on {t.device} but means is on {means.device}")
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"width and height must be >= 1, got {width}x{height}")
    return {name: t.float().contiguous() for name, t in named.items()}


@functools.lru_cache(maxsize=16)
def _cached_zeros(c: int, device: torch.device) -> torch.Tensor:
    return torch.zeros(c, device=device, dtype=torch.float32)


def _zero_background(c: int, device: torch.device) -> torch.Tensor:
    """A [c] float32 zero background on ``device``: one tensor kept per (c, device), which nothing
    writes (a render reads its background), saving an allocation and a launch per render; made afresh
    inside a CUDA graph capture, where a new tensor's zeros would be written only by the replays."""
    if device.type == "cuda" and torch.cuda.is_current_stream_capturing():
        return torch.zeros(c, device=device, dtype=torch.float32)
    return _cached_zeros(c, device)


def _wp(t: torch.Tensor, dtype, grad: bool = False, retain_grad: bool = False):
    """Warp view of a contiguous torch tensor; with ``grad``, a zeroed torch-backed gradient too.

    ``retain_grad``: Warp's generated adjoints zero an output's gradient once they have read it,
    unless the array keeps it (``means2d``'s: densification statistics).
    """
    if grad:
        return wp.from_torch(t, dtype=dtype, requires_grad=True, grad=torch.zeros_like(t), retain_grad=retain_grad)
    return wp.from_torch(t, dtype=dtype, requires_grad=False)


def check_finite(finite) -> None:
    """Raise ValueError naming the inputs whose flag is False; ``finite`` = (names, host flags)."""
    names, flags = finite
    bad = [name for name, flag in zip(names, flags) if not flag]
    if bad:
        raise ValueError(f"non-finite values (NaN or inf) in: {', '.join(bad)}")


class RenderPlan:
    """The Warp views of one render's inputs, intermediates, outputs and gradients, and the launches
    between them. The eager op builds one per render; a captured render keeps one per shape and
    replays its launches as Warp graphs (``securegs_warp.raster_graph``).

    ``inputs``: name → tensor, as ``rasterize`` prepares them: means [N, 3], quats [N, 4],
    scales [N, 3], opacities [N], colors [N, C], color_table [N, C] (colors or their float16 copy),
    background [C], viewmat [16], K [9]; all float32 contiguous on one device. Outputs
    (``self.out``): image [H, W, C], alpha [H, W, 1], depth [H, W, 1], radii [N, 2] int32,
    means2d [N, 2], conics [N, 3], depths [N], opacities [N]; ``self.grads``: the gradients of
    means, quats, scales, opacities, colors and background, filled by ``backward`` (only
    ``with_grads``: a render nothing will differentiate allocates and zeroes no gradients).
    """

    def __init__(self, inputs: dict, width: int, height: int, opts: RasterOptions, with_grads: bool = True):
        tdev = inputs["means"].device
        self.device = wp.device_from_torch(tdev)
        self.width, self.height, self.opts = width, height, opts
        n, c = inputs["colors"].shape
        self.n = n
        packed = opts.gather == "packed"
        f32 = dict(device=tdev, dtype=torch.float32)
        ts = opts.tile_size
        self.tiles_x, self.tiles_y = math.ceil(width / ts), math.ceil(height / ts)
        if max(self.tiles_x, self.tiles_y) > binning.MAX_TILES_PER_AXIS:
            raise ValueError(f"a {width}x{height} image has more than {binning.MAX_TILES_PER_AXIS} tiles of {ts} "
                             "pixels along a side, which the binning cannot index")
        self.n_tiles = self.tiles_x * self.tiles_y
        self.out = {"image": torch.empty(height, width, c, **f32), "alpha": torch.empty(height, width, 1, **f32),
                    "depth": torch.zeros(height, width, 1, **f32),
                    # The projection writes every row of these (zeros for a culled Gaussian).
                    "radii": torch.empty(n, 2, device=tdev, dtype=torch.int32),
                    "means2d": torch.empty(n, 2, **f32), "conics": torch.empty(n, 3, **f32),
                    "depths": torch.empty(n, **f32), "opacities": torch.empty(n, **f32)}
        self.transmittance = torch.empty(height, width, **f32)
        self.last = torch.empty(height, width, device=tdev, dtype=torch.int32)
        # The depth sort's keys and values (Gaussian ids in depth order), twice N as the sort needs.
        self.depth_keys = torch.empty(max(2 * n, 2), device=tdev, dtype=torch.int32)
        self.order = torch.empty(max(2 * n, 2), device=tdev, dtype=torch.int32)
        self.tile_counts = torch.empty(n, device=tdev, dtype=torch.int32)  # in index order
        self.counts = torch.empty(n, device=tdev, dtype=torch.int64)  # in depth order
        self.ends = torch.empty(n, device=tdev, dtype=torch.int64)
        self.tile_spans = torch.empty(n, 2, device=tdev, dtype=torch.int64)  # in index order
        # Without gradients (no_grad, or no input that needs one) nothing is allocated for them.
        g = with_grads
        with wp.ScopedDevice(self.device):
            w_in = {
                "means": _wp(inputs["means"], wp.vec3, grad=g),
                "quats": _wp(inputs["quats"], wp.vec4, grad=g),
                "scales": _wp(inputs["scales"], wp.vec3, grad=g),
                "opacities": _wp(inputs["opacities"], wp.float32, grad=g),
                # Colours only reach the hand-written blend adjoint, whose gradient table is unpacked
                # into colors_grad (every entry, float32 whatever the table's storage type).
                "color_table": _wp(inputs["color_table"], COLOR_STORAGES[opts.color_storage]),
                "colors_grad": _wp(torch.empty_like(inputs["colors"]), wp.float32) if g else None,
                "background": _wp(inputs["background"], wp.float32, grad=g),
                "viewmat": _wp(inputs["viewmat"], wp.float32),
                "K": _wp(inputs["K"], wp.float32),
            }
            o = self.out
            w_out = {
                "means2d": _wp(o["means2d"], wp.vec2, grad=g, retain_grad=g),
                "conics": _wp(o["conics"], wp.vec3, grad=g),
                "depths": _wp(o["depths"], wp.float32, grad=g),
                "opac_out": _wp(o["opacities"], wp.float32, grad=g),  # after antialiasing
                "radii": _wp(o["radii"], wp.vec2i),
                "image": _wp(o["image"], wp.float32),
                "alpha": _wp(o["alpha"], wp.float32),
                "depth": _wp(o["depth"], wp.float32),
                "transmittance": _wp(self.transmittance, wp.float32),
                "last": _wp(self.last, wp.int32),
                "depth_keys": _wp(self.depth_keys, wp.int32),
                "order": _wp(self.order, wp.int32),
                "tile_counts": _wp(self.tile_counts, wp.int32),
                "counts": _wp(self.counts, wp.int64),
                "ends": _wp(self.ends, wp.int64),
                "tile_spans": _wp(self.tile_spans, wp.int64),
                "depth_bits": wp.from_torch(o["depths"].view(torch.int32), dtype=wp.int32),
                # Allocated by torch, like every buffer here: in order on torch's stream.
                "ranges": _wp(torch.empty(self.n_tiles, 2, device=tdev, dtype=torch.int32), wp.int32),
                # The blending backward's per-Gaussian gradients, one row each (kernels/blend.py).
                "gaussian_grads": _wp(torch.zeros(n, gradient_width(c, opts.render_depth is not None), **f32),
                                      wp.float32) if g else None,
            }
            w_out["records"] = w_out["record_pairs"] = None
            if packed:
                # Packed per-Gaussian records, [N, P / 4] vec4 (P float32 words a row) as the
                # blending kernels gather them, and [N, P / 2] int64 as the projection writes them.
                words = record_width(c, opts.color_storage)
                records = torch.empty(n, words, **f32)
                w_out["records"] = _wp(records.view(n, words // 4, 4), wp.vec4)
                w_out["record_pairs"] = _wp(records.view(torch.int64), wp.int64)
        self.w = {**w_in, **w_out}
        if g:
            self.grads = [wp.to_torch(self.w[k].grad) for k in ("means", "quats", "scales", "opacities")] + [
                wp.to_torch(self.w["colors_grad"]), wp.to_torch(self.w["background"].grad)]
            self.means2d_grad = wp.to_torch(self.w["means2d"].grad)
        w = self.w
        self._projection = dict(
            kernel=projection_kernel(opts.antialiased, opts.radius_rule, opts.fast_math,
                                     record=(c, opts.color_storage) if packed else None), dim=n,
            inputs=[w["means"], w["quats"], w["scales"], w["opacities"], w["viewmat"], w["K"],
                    w["color_table"] if packed else None, width, height,
                    opts.near_plane, opts.far_plane, opts.eps2d, opts.alpha_min, opts.radius_clip],
            outputs=[w["means2d"], w["conics"], w["depths"], w["radii"], w["opac_out"], w["record_pairs"]],
        )
        self.keys = self.values = None
        with_depth = opts.render_depth is not None
        cooperative = not (self.device.is_cpu and not wp.config.enable_cpu_blocks)
        self._fwd_block = opts.block(opts.forward_block)
        self._bwd_threads = backward_threads(opts.tile_size, opts.backward_pixels)
        self._bwd_block = min(opts.block(opts.backward_block), self._bwd_threads)
        self._blend = blend_kernels_for(opts, c, with_depth, cooperative)
        self._unpack = unpack_gradients_kernel(c, with_depth)

    def scoped(self):
        """Device and stream scope of this plan's launches (torch's current stream on CUDA)."""
        return WarpScope(self.device, self.out["image"].device)

    def project_and_count(self) -> None:
        """Projection, the Gaussians' depth order, and their tile counts in that order with the
        inclusive prefix sum: ``self.ends[-1]`` is the number of intersections."""
        w, opts = self.w, self.opts
        wp.launch(**self._projection)
        if self.n == 0:
            return
        wp.launch(binning.count_tiles, dim=self.n,
                  inputs=[w["means2d"], w["radii"], *self._overlap(), opts.tile_size, self.tiles_x, self.tiles_y],
                  outputs=[w["tile_counts"], w["tile_spans"]])
        wp.launch(binning.depth_order_keys, dim=self.n, inputs=[w["depth_bits"]], outputs=[w["depth_keys"], w["order"]])
        # Depths are >= 0, so their bit patterns' sign bit is clear.
        wp.utils.radix_sort_pairs(w["depth_keys"], w["order"], self.n, end_bit=31)
        wp.launch(binning.depth_ordered_counts, dim=self.n, inputs=[w["order"], w["tile_counts"]],
                  outputs=[w["counts"]])
        wp.utils.array_scan(w["counts"], w["ends"], inclusive=True)

    def _overlap(self):
        opts = self.opts
        return [self.w["conics"], self.w["opac_out"], opts.alpha_min, int(opts.tile_overlap == "ellipse")]

    def allocate_intersections(self, capacity: int) -> None:
        """Key and value buffers for ``capacity`` intersections (radix_sort_pairs needs twice that)."""
        if 2 * capacity > MAX_SORTED:
            raise ValueError(f"{capacity} tile intersections exceed what the sort can hold ({MAX_SORTED // 2}: "
                             "its buffers are twice the count and Warp's arrays have int32 dimensions); render "
                             "fewer Gaussians or a smaller image at once")
        self.capacity = capacity
        tdev = self.out["image"].device
        self.keys = _wp(torch.empty(max(2 * capacity, 2), device=tdev, dtype=torch.int32), wp.int32)
        self.values = _wp(torch.empty(max(2 * capacity, 2), device=tdev, dtype=torch.int32), wp.int32)

    def sort_intersections(self, count: int, padded: bool) -> None:
        """Emit, sort and range the intersections: ``count`` of them exactly (eager), or, ``padded``,
        the whole capacity with padding keys past the last tile (captured: the count stays on the device)."""
        w, opts = self.w, self.opts
        self.w["ranges"].zero_()
        if count == 0 or self.n == 0:
            return
        # The padding tile id must fit the sorted bits: tile ids 0 .. n_tiles.
        tile_bits = max(1, int(self.n_tiles).bit_length())
        if padded:
            wp.launch(binning.pad_keys, dim=count, inputs=[w["ends"], self.n_tiles], outputs=[self.keys])
        wp.launch(binning.emit_intersections, dim=self.n,
                  inputs=[w["order"], w["means2d"], *self._overlap(), w["counts"], w["ends"], w["tile_spans"],
                          opts.tile_size, self.tiles_x, self.capacity],
                  outputs=[self.keys, self.values])
        wp.utils.radix_sort_pairs(self.keys, self.values, count, end_bit=tile_bits)
        wp.launch(binning.tile_ranges, dim=count, inputs=[self.keys, count], outputs=[w["ranges"]])

    def _blend_args(self):
        w, opts = self.w, self.opts
        return [w["ranges"], self.values, w["means2d"], w["conics"], w["opac_out"], w["color_table"], w["depths"],
                w["records"], w["background"], self.width, self.height, self.tiles_x, opts.alpha_min, opts.alpha_max]

    def blend(self) -> None:
        w, ts = self.w, self.opts.tile_size
        wp.launch(self._blend[0], dim=(self.n_tiles, ts * ts), block_dim=self._fwd_block,
                  inputs=self._blend_args() + [self.opts.transmittance_min],
                  outputs=[w["image"], w["alpha"], w["depth"], w["transmittance"], w["last"]])

    def backward(self, cotangents) -> None:
        """Blend adjoint, then the projection adjoint: accumulates into ``self.grads`` and
        ``means2d``'s gradient from ``cotangents``, Warp float32 views of dL/d image [H, W, C],
        dL/d alpha [H, W, 1] and dL/d depth [H, W, 1]."""
        w = self.w
        wp.launch(self._blend[1], dim=(self.n_tiles, self._bwd_threads), block_dim=self._bwd_block,
                  inputs=self._blend_args() + [w["transmittance"], w["last"], *cotangents],
                  outputs=[w["gaussian_grads"], w["background"].grad])
        wp.launch(self._unpack, dim=self.n, inputs=[w["gaussian_grads"]],
                  outputs=[w["means2d"].grad, w["conics"].grad, w["opac_out"].grad, w["colors_grad"], w["depths"].grad])
        # Warp's generated adjoint of the projection, launched as wp.Tape would launch it.
        adjoints = {key: [a.grad if isinstance(a, wp.array) else None for a in self._projection[key]]
                    for key in ("inputs", "outputs")}
        wp.launch(**self._projection, adj_inputs=adjoints["inputs"], adj_outputs=adjoints["outputs"], adjoint=True)


def blend_kernels_for(opts: RasterOptions, channels: int, with_depth: bool, cooperative: bool):
    """(forward, backward) blending kernels a render with ``opts`` launches for ``channels`` colour
    channels (``cooperative``: CUDA's shared-memory batches; the CPU reads directly)."""
    packed = opts.gather == "packed"
    batch = batch_size(channels, opts.block(opts.forward_block), with_depth, opts.color_storage, packed) \
        if cooperative else CPU_BATCH
    return blend_kernels(channels, opts.tile_size, with_depth, batch, cooperative, opts.color_storage, opts.fast_math,
                         opts.backward_walk == "warp", opts.backward_max_registers, packed=packed,
                         backward_pixels=opts.backward_pixels)


OUTPUT_NAMES = ("image", "alpha", "depth", "radii", "means2d", "conics", "depths", "opacities")


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, color_table, background, viewmat, K, width, height,
                opts, info, finite, needs_grad):
        wp.init()  # idempotent; Warp must be up before its devices can be named
        inputs = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                      color_table=color_table, background=background, viewmat=viewmat, K=K)
        plan = RenderPlan(inputs, width, height, opts, with_grads=needs_grad)
        with plan.scoped():
            plan.project_and_count()
            # The render's one host synchronisation: the intersection count and the finiteness flags.
            names, flags = finite
            parts = ([plan.ends[-1:]] if plan.n else []) + ([flags.long()] if flags is not None else [])
            host = torch.cat(parts).tolist() if parts else []
            n_isect = int(host[0]) if plan.n else 0
            check_finite((names, host[1:] if plan.n else host))
            plan.allocate_intersections(n_isect)
            plan.sort_intersections(n_isect, padded=False)
            plan.blend()
        ctx.plan = plan
        ctx.info = info
        ctx.mark_non_differentiable(*(plan.out[k] for k in OUTPUT_NAMES[3:]))
        # An output the loss does not use gets None in backward, not a tensor of zeros its size.
        ctx.set_materialize_grads(False)
        return (*(plan.out[k] for k in OUTPUT_NAMES), n_isect)

    @staticmethod
    def backward(ctx, g_image, g_alpha, g_depth, *_):
        plan = ctx.plan
        if plan is None:
            raise RuntimeError(SECOND_BACKWARD)
        # The incoming gradients are read in place (an unused output's may be None: zeros).
        cotangents = [_wp(torch.zeros_like(plan.out[k]) if g is None else g.float().contiguous(), wp.float32)
                      for k, g in zip(("image", "alpha", "depth"), (g_image, g_alpha, g_depth))]
        with plan.scoped():
            plan.backward(cotangents)
        ctx.info["means2d_grad"] += plan.means2d_grad
        grads = plan.grads
        ctx.plan = None  # release the Warp arrays
        # grads for means, quats, scales, opacities, colors (not color_table), background; none beyond.
        return (*grads[:5], None, grads[5], None, None, None, None, None, None, None, None)
